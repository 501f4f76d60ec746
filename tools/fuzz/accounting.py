"""What a burst of faults did, by kind: sent, delivered, counted, silently accepted; and the
recovery of the estimate against the clean pass.

**Counting.** Each burst is one kind (one case or one mutation operator on one topic),
published while the valid stream pauses, between two synchronisations with the nodes'
``diagnostics`` (every node has reported after the last message of the burst, and every
input link holds what was sent on it). Over that window:

* ``delivered``: the burst's messages the node counted as received (``received_<topic>``);
* ``lost``: sent but never received; ``counted_loss``: what the taking node's loss
  counters of the burst's topic (``lost_<topic>``, ``qos_message_lost_<topic>``, the
  larger) rose by; ``counted_late``: a loss the node counted after the window, before the
  end of the pass (:class:`LossLedger`); a loss beyond both is *uncounted* (a queue that
  overwrote it and nobody says so);
* ``rejected``: what ``rejected_total`` of all nodes rose by (capped at the delivered
  messages); ``dropped``: what the taking node's other counts of messages it received
  and did not use rose by (a full matcher queue, an epoch queue, the engine's own
  refusals: :data:`.graph.DROP_COUNTERS`); ``sanitised``: satellites dropped by the
  checks (the message itself used);
* ``silently accepted``: a ``reject`` burst delivered, neither refused, dropped nor
  sanitised.

**Judged faults.** A random mutation (and a structured fault of random size) may leave a
valid message (:mod:`.plausible` judges each one against the message it was made from):
the messages of such a burst are played as two bursts of the same kind, the malformed
ones (``expect='reject'``) and those *valid after mutation* (``expect='any'``, counted
apart, not as malformed messages).

Rejections outside the bursts (valid messages refused after a fault: a time base that
jumped, a filter that broke) are counted apart: they are the collateral damage.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np


@dataclass
class BurstResult:
    """One burst of one kind."""

    kind: str
    topic: str
    family: str
    expect: str
    sent: int
    unsendable: int = 0
    delivered: int = 0
    counted_loss: int = 0
    counted_late: int = 0
    rejected: int = 0
    dropped: int = 0
    satellites: int = 0
    synced: bool = True
    seconds: float = 0.0
    epoch: int = -1
    reasons: dict = field(default_factory=dict)
    t_wall: float = 0.0
    valid_after_mutation: int = 0
    judged: list = field(default_factory=list)

    @property
    def lost(self) -> int:
        return max(0, self.sent - self.delivered)

    @property
    def uncounted_loss(self) -> int:
        return max(0, self.lost - self.counted_loss - self.counted_late)

    @property
    def refused(self) -> int:
        return min(self.delivered, self.rejected)

    @property
    def silently_accepted(self) -> int:
        if self.expect != 'reject' or self.satellites > 0:
            return 0
        return max(0, self.delivered - self.refused - self.dropped)


@dataclass
class KindStats:
    """Everything tried of one kind."""

    kind: str
    topic: str
    family: str
    expect: str
    issue: bool = False
    bursts: int = 0
    sent: int = 0
    unsendable: int = 0
    valid_after_mutation: int = 0
    delivered: int = 0
    counted_late: int = 0
    uncounted_loss: int = 0
    refused: int = 0
    dropped: int = 0
    sanitised_bursts: int = 0
    silently_accepted: int = 0
    crashes: int = 0
    blocks: int = 0
    hangs: int = 0
    max_burst_s: float = 0.0
    crash_causes: list[str] = field(default_factory=list)
    reasons: dict = field(default_factory=dict)

    def add(self, b: BurstResult) -> None:
        self.bursts += 1
        self.sent += b.sent
        self.unsendable += b.unsendable
        self.valid_after_mutation += b.valid_after_mutation
        self.delivered += b.delivered
        self.counted_late += min(b.counted_late, b.lost)
        self.uncounted_loss += b.uncounted_loss
        self.refused += b.refused
        self.dropped += min(b.dropped, b.delivered - b.refused)
        self.sanitised_bursts += int(b.satellites > 0)
        self.silently_accepted += b.silently_accepted
        self.max_burst_s = max(self.max_burst_s, b.seconds)
        for reason, n in b.reasons.items():
            self.reasons[reason] = self.reasons.get(reason, 0) + n

    @property
    def malformed(self) -> int:
        """Messages sent that were not valid after mutation."""
        return self.sent - self.valid_after_mutation

    @property
    def uncounted(self) -> int:
        return self.uncounted_loss + self.silently_accepted

    @property
    def outcome(self) -> str:
        """The worst thing this kind did, in words."""
        bad = []
        if self.crashes:
            bad.append(f'crash x{self.crashes}')
        if self.blocks:
            bad.append(f'block x{self.blocks}')
        if self.hangs:
            bad.append(f'hang x{self.hangs}')
        if self.uncounted_loss:
            bad.append(f'{self.uncounted_loss} lost uncounted')
        if self.silently_accepted:
            bad.append(f'{self.silently_accepted} accepted silently')
        if not self.sent:
            return 'not tried'
        return ', '.join(bad) or 'ok'

    def as_dict(self) -> dict:
        out = asdict(self)
        out.update(malformed=self.malformed, uncounted=self.uncounted, outcome=self.outcome)
        return out


def by_kind(bursts: list[BurstResult], meta: dict[str, dict]) -> dict[str, KindStats]:
    """Aggregate bursts per kind (``meta``: kind -> topic, family, expect, issue)."""
    out: dict[str, KindStats] = {}
    for kind, m in meta.items():
        out[kind] = KindStats(kind, m['topic'], m['family'], m['expect'], m['issue'])
    for b in bursts:
        if b.kind not in out:
            out[b.kind] = KindStats(b.kind, b.topic, b.family, b.expect)
        out[b.kind].add(b)
    return out


def by_topic(kinds: dict[str, KindStats]) -> dict[str, dict]:
    """Per input topic: structured and mutated messages sent, delivered, refused, uncounted,
    crashes."""
    out: dict[str, dict] = {}
    for k in kinds.values():
        row = out.setdefault(k.topic, dict(structured=0, mutations=0, floods=0,
                                           valid_after_mutation=0, delivered=0, refused=0,
                                           uncounted_loss=0, silently_accepted=0,
                                           crashes=0))
        row[{'structured': 'structured', 'mutation': 'mutations'}.get(k.family,
                                                                      'floods')] += k.sent
        for key in ('valid_after_mutation', 'delivered', 'refused', 'uncounted_loss',
                    'silently_accepted', 'crashes'):
            row[key] += getattr(k, key)
    return out


class LossLedger:
    """Losses a node counted after the burst that caused them.

    A node counts a lost message from the gap in its publisher's sequence numbers when
    that publisher's next message arrives. On a link with a second publisher (the kit's,
    beside the graph's own) whose numbers interleave with the first's, the node cannot
    tell which one a message came from (rclpy's message info carries no publisher id): it
    attributes the message to the nearest stream below it, so a flood whose numbers
    overtake the other publisher's counts part of its loss only when that publisher sends
    again, after the burst (the totals are exact then). The ledger carries each burst's
    uncounted loss as a debt per topic; a later rise of the topic's loss counter beyond the
    losses of the kit's own valid stream in the same interval settles the oldest debts
    (``counted_late``). What no count settles by the end of the pass stays uncounted.
    """

    def __init__(self):
        self.debts: dict[str, list[BurstResult]] = {}
        self.mark: dict[str, tuple[float, float]] = {}

    def observe(self, counted: dict[str, float], seen_lost: dict[str, float],
                burst: BurstResult | None = None) -> None:
        """A sync: ``counted`` (the nodes' loss counts per topic) and ``seen_lost``
        (losses the kit has seen per topic) now; ``burst``: the burst whose window ends
        here (its loss is judged by its own window first)."""
        for topic, count in counted.items():
            old = self.mark.get(topic)
            self.mark[topic] = (count, seen_lost.get(topic, 0.0))
            if old is None:
                continue
            surplus = (count - old[0]) - (seen_lost.get(topic, 0.0) - old[1])
            if burst is not None and burst.topic == topic:
                surplus = burst.counted_loss - burst.lost
                if burst.uncounted_loss > 0:
                    self.debts.setdefault(topic, []).append(burst)
            queue = self.debts.get(topic, [])
            while surplus > 0 and queue:
                settle = min(int(surplus), queue[0].uncounted_loss)
                if settle <= 0:
                    break
                queue[0].counted_late += settle
                surplus -= settle
                if queue[0].uncounted_loss == 0:
                    queue.pop(0)


# ------------------------------------------------------------------- recovery
def within(error: float, clean: float, rel: float, abs_m: float) -> bool:
    """An error back to the clean run's accuracy: at most ``clean * (1 + rel)`` or
    ``clean + abs_m``, whichever is larger."""
    return math.isfinite(error) and error <= max(clean * (1.0 + rel), clean + abs_m)


def recovery_s(stamps: list[int], fuzz_err: dict[int, float], clean_err: dict[int, float],
               end_stamp: int | None, rel: float = 0.10, abs_m: float = 3.0) -> float:
    """Seconds (stamp time) from ``end_stamp`` (the last fault) until the estimate is back
    within tolerance of the clean pass at every later epoch where the clean pass has a fix
    (0 when it never left; inf when it never came back).
    """
    if end_stamp is None:
        return 0.0
    later = [s for s in stamps if s > end_stamp and s in clean_err]
    if not later:
        return math.inf
    back = None
    for s in reversed(later):
        if s in fuzz_err and within(fuzz_err[s], clean_err[s], rel, abs_m):
            back = s
        else:
            break
    if back is None:
        return math.inf
    return max(0.0, (back - end_stamp) / 1e9) if back != later[0] else 0.0


def error_summary(errors: dict[int, float], stamps: list[int]) -> dict:
    """Median and max horizontal error over ``stamps`` [m] (epochs with a fix)."""
    vals = np.array([errors[s] for s in stamps if s in errors], dtype=float)
    if not vals.size:
        return {'epochs': 0, 'median_m': math.nan, 'max_m': math.nan}
    return {'epochs': int(vals.size), 'median_m': float(np.median(vals)),
            'max_m': float(np.max(vals))}
