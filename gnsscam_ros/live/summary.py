"""What a replay did (:class:`ReplaySummary`), as text and as JSON."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path


@dataclass
class ReplaySummary:
    """What a replay did.

    Attributes:
        bag: The bag played.
        rate: Rate factor (0 = as fast as the nodes keep up).
        published: Messages published per qualified topic.
        first_stamp_ns: Stamp of the first timed message published [ns].
        last_stamp_ns: Stamp of the last timed message published [ns].
        wall_s: Wall time from the first to the last message and the final
            acknowledgements [s].
        gnss_epochs: GNSS epochs published.
        gnss_epochs_processed: Of those, epochs whose ``integrity_risk`` came back
            (None: nobody publishes ``integrity_risk``).
        unacknowledged: Per relative topic, messages whose acknowledgement timed out.
        flow_control: Per relative topic, ``'on'``, ``'off: ...'`` with the reason.
        ack_wait_s: Per relative topic, wall time spent waiting for acknowledgements [s].
        interrupted: Stopped early (Ctrl-C or shutdown).
        cpu_s: CPU time [s] by process (``replay`` = this process during the replay, with
            any in-process nodes; child node processes by name, start-up included), when
            measured by :func:`.replay_through_nodes.replay_through_nodes`.
        node_diagnostics: The newest ``diagnostics`` values per status name seen during the
            replay (the nodes' counters: ``dropped_epochs``, ``dropped_frames``, ...).
        start: How the replay knew the graph was ready: ``'links matched'`` (the nodes
            reported every link), ``'links not matched'`` (they did not within ``wait``),
            ``'fixed settle'`` (no link reports) or ``''`` (no flow-controlled stream).
        start_wait_s: Wall time from the replay's start to its first message [s].
        reset_nodes: Nodes reset (``~/reset``) before the first message because they held
            another time base (a bag played again into running nodes).
        undelivered: Topics with a reliable subscriber that had not acknowledged every
            message when the replay ended (within ``ack_timeout_s``).
    """

    bag: Path
    rate: float
    published: dict[str, int] = field(default_factory=dict)
    first_stamp_ns: int | None = None
    last_stamp_ns: int | None = None
    wall_s: float = 0.0
    gnss_epochs: int = 0
    gnss_epochs_processed: int | None = None
    unacknowledged: dict[str, int] = field(default_factory=dict)
    flow_control: dict[str, str] = field(default_factory=dict)
    ack_wait_s: dict[str, float] = field(default_factory=dict)
    interrupted: bool = False
    cpu_s: dict[str, float] = field(default_factory=dict)
    node_diagnostics: dict[str, dict] = field(default_factory=dict)
    start: str = ''
    start_wait_s: float = 0.0
    reset_nodes: list[str] = field(default_factory=list)
    undelivered: list[str] = field(default_factory=list)

    @property
    def bag_span_s(self) -> float:
        """Bag time covered by the published messages [s]."""
        if self.first_stamp_ns is None or self.last_stamp_ns is None:
            return 0.0
        return (self.last_stamp_ns - self.first_stamp_ns) / 1e9

    @property
    def speed(self) -> float:
        """Replay speed as a multiple of real time (bag span / wall time)."""
        return self.bag_span_s / self.wall_s if self.wall_s > 0 else math.nan

    @property
    def dropped_gnss_epochs(self) -> int | None:
        """GNSS epochs published without an ``integrity_risk`` back (None: no filter)."""
        if self.gnss_epochs_processed is None:
            return None
        return self.gnss_epochs - self.gnss_epochs_processed

    def as_dict(self) -> dict:
        """JSON-able form."""
        return {'bag': str(self.bag), 'rate': self.rate, 'published': self.published,
                'messages': sum(self.published.values()), 'bag_span_s': self.bag_span_s,
                'wall_s': self.wall_s, 'speed_x_real_time': self.speed,
                'gnss_epochs': self.gnss_epochs,
                'gnss_epochs_processed': self.gnss_epochs_processed,
                'dropped_gnss_epochs': self.dropped_gnss_epochs,
                'unacknowledged': self.unacknowledged, 'flow_control': self.flow_control,
                'ack_wait_s': self.ack_wait_s, 'interrupted': self.interrupted,
                'cpu_s': self.cpu_s, 'node_diagnostics': self.node_diagnostics,
                'start': self.start, 'start_wait_s': self.start_wait_s,
                'reset_nodes': self.reset_nodes, 'undelivered': self.undelivered}

    def text(self) -> str:
        """Readable one-paragraph summary."""
        lines = [f'replayed {sum(self.published.values())} messages, '
                 f'{self.bag_span_s:.1f} s of bag time in {self.wall_s:.1f} s '
                 f'({self.speed:.1f}x real time, rate {self.rate:g})']
        if self.gnss_epochs and self.gnss_epochs_processed is None:
            lines.append(f'GNSS epochs: {self.gnss_epochs} published; none acknowledged '
                         '(nobody publishes integrity_risk: no filter to count them)')
        elif self.gnss_epochs:
            lines.append(f'GNSS epochs: {self.gnss_epochs} published, '
                         f'{self.gnss_epochs_processed} processed by the filter, dropped '
                         f'{self.dropped_gnss_epochs}')
        if self.reset_nodes:
            lines.append('reset first (they held another time base): '
                         + ', '.join(self.reset_nodes))
        lost = {k: v for k, v in self.unacknowledged.items() if v}
        if lost:
            lines.append(f'unacknowledged: {lost}')
        off = {k: v for k, v in self.flow_control.items() if v != 'on'}
        if off:
            lines.append(f'flow control off: {off}')
        if self.undelivered:
            lines.append('not acknowledged by every subscriber at the end: '
                         + ', '.join(self.undelivered))
        if self.start and self.start != 'links matched':
            lines.append(f'started on {self.start}')
        if self.interrupted:
            lines.append('interrupted')
        return '\n'.join(lines)
