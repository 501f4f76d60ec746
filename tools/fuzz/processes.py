"""``processes``: SIGKILL and restart of each node mid-replay.

The four nodes run as separate child processes (as ``ros2 run`` starts them) in a ROS
domain of their own; the probe plays the valid stream paced at ``rate`` times real time
(the nodes' wall-time timeouts keep their meaning). One after the other (the first after
``warmup_s``, each next one ``gap_s`` after the previous one recovered), each chosen node
is killed with SIGKILL, stays down for ``down_s`` of stamp time while the stream goes on,
and is started again. Measured per kill:

* **recovery**: wall seconds from the restart to the graph working again: the first
  updated epoch verdict (gnss_node, fusion_node: any epoch verdict of the new filter;
  imu_node: an updated verdict with the motion known again; camera_node: its first
  published match); also split into the node's own start-up (from the restart to its
  ready line, stamped by the node's log: imports, the map database, the kernels' warm-up),
  discovery (from the ready line until the probe hears its first ``diagnostics``: the
  DDS participants finding each other, plus at most one ``diagnostics_period_s`` of
  0.1 s) and what the graph adds after that (the next inputs, the epoch through the
  filter);
* **integrity while an input is missing or reset**: every ``integrity_risk`` OK whose
  epoch falls between the kill and the node being back (gnss_node: the verdict needs its
  input; an epoch it passes once back is a valid one) or one epoch after that (imu_node:
  after a restart the dead reckoning starts again from zero, so the motion of that
  epoch's interval spans the reset), or, for fusion_node, before the restarted filter could have
  settled (``integrity_settling_s`` after its first verdict) is a violation; the camera
  is not needed for a verdict (OK verdicts while it is down are counted, not failed);
* **collateral**: any other node that exits meanwhile; the exit status of every node
  at the end (stopped as Ctrl-C does: 0 expected).

To make the check bite, the filter certifies early (``alert_limit_m`` 50 m,
``integrity_settling_s`` 5 s): a run that saw no OK verdict outside the windows says so.

**The drive fits the schedule.** Every kill needs stamp time: ``down_s``, its recovery
(``rate`` stamp seconds per wall second) and ``gap_s`` before the next one. A drive shorter
than :func:`schedule_s` (the warm-up, then per kill ``down_s`` + a recovery of twice the
target + ``gap_s``: 144 s for the default four kills at 2x) is lengthened to it, and the
run says so; ``duration_s`` is the shortest drive. (A 90 s drive, the CLI's default, left
the last kill, fusion_node's, 2 s before the end: no epoch after its restart, recovery
inf.)
"""
from __future__ import annotations

import math
import re
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

from msg_adapters import wire

from .graph import NODE_NAMES, NodeProcess, Probe, write_params
from .messages import MessagesConfig, fresh_domain, node_parameters
from .report import Target, at_least, at_most, table
from .stream import StreamConfig, ValidStream

OK_LEVEL, STALE_LEVEL = 0, 3
#: Nodes whose input a verdict needs (the camera's is optional).
REQUIRED = ('gnss_node', 'imu_node', 'fusion_node')


@dataclass
class ProcessesConfig:
    """A ``processes`` run (the CLI's options)."""

    seed: int = 1
    duration_s: float = 90.0
    rate: float = 2.0
    down_s: float = 3.0
    nodes: list | None = None
    camera: bool = True
    warmup_s: float = 20.0
    gap_s: float = 8.0
    recover_timeout_s: float = 60.0
    alert_limit_m: float = 50.0
    integrity_settling_s: float = 5.0
    particles: int | None = None
    acquisition_particles: int | None = None
    domain: int | None = None
    work_dir: str | None = None
    start_timeout_s: float = 120.0
    target_recovery_s: float = 5.0


def schedule_s(cfg: ProcessesConfig, kills: int) -> float:
    """Stamp time the kill schedule needs [s]: the warm-up, then per kill the time it is
    down, a recovery of twice the target at the replay rate, and the gap after it."""
    per_kill = cfg.down_s + 2.0 * cfg.target_recovery_s * cfg.rate + cfg.gap_s
    return cfg.warmup_s + kills * per_kill


def _node_params(cfg: ProcessesConfig, stream: ValidStream) -> dict:
    base = MessagesConfig(seed=cfg.seed, alert_limit_m=cfg.alert_limit_m,
                          particles=cfg.particles,
                          acquisition_particles=cfg.acquisition_particles)
    params = node_parameters(base, stream)
    params['fusion_node'].update(integrity_settling_s=cfg.integrity_settling_s,
                                 odometry_wait_s=0.5, odometry_timeout_s=1.0)
    for node in params.values():
        node['diagnostics_period_s'] = 0.1
    return params


class Campaign:
    """The kill/restart run (state shared by its steps)."""

    def __init__(self, cfg: ProcessesConfig, log=print):
        self.cfg, self.log = cfg, log
        self.work = Path(cfg.work_dir or tempfile.mkdtemp(prefix='gnsscam_fuzz_processes_'))
        self.work.mkdir(parents=True, exist_ok=True)
        names = [n for n in NODE_NAMES if cfg.camera or n != 'camera_node']
        victims = cfg.nodes or names
        unknown = set(victims) - set(names)
        if unknown:
            raise ValueError(f'no such node in this run: {sorted(unknown)}')
        self.drive_s = max(cfg.duration_s, schedule_s(cfg, len(victims)))
        if self.drive_s > cfg.duration_s:
            log(f'processes: drive lengthened from {cfg.duration_s:g} s to '
                f'{self.drive_s:g} s to fit {len(victims)} kills (schedule_s)')
        self.stream = ValidStream(StreamConfig(seed=cfg.seed, duration_s=self.drive_s,
                                               camera=cfg.camera), self.work)
        self.domain = cfg.domain if cfg.domain is not None else fresh_domain()
        params = write_params(self.work / 'params.yaml', _node_params(cfg, self.stream))
        self.procs = {n: NodeProcess(n, params, self.domain, self.work) for n in names}
        stamps = self.stream.gnss_stamps
        if self.stream.seconds(stamps[-1]) <= cfg.warmup_s:
            raise ValueError('the drive is shorter than the warm-up')
        # One node at a time: the next is killed gap_s after the previous one recovered.
        self.kills = [{'node': n} for n in victims]
        self.next_kill_s = cfg.warmup_s
        self.probe: Probe | None = None
        self.collateral: list[dict] = []

    # ---------------------------------------------------------------- start
    def start_all(self) -> None:
        for proc in self.procs.values():
            proc.start()
        c = self.probe.counters
        ok = self.probe.spin_until(
            lambda: all(n in c.values for n in self.procs)
            and all(p.get_subscription_count() > 0 for t, p in self.probe.pubs.items()
                    if t in (wire.GNSS, wire.IMU, wire.TWIST)
                    or (t == wire.IMAGE and self.cfg.camera)), self.cfg.start_timeout_s)
        dead = [n for n, p in self.procs.items() if not p.alive()]
        if not ok or dead:
            raise RuntimeError(f'the nodes did not start ({dead or "timeout"}): '
                               + '; '.join(p.failure(1) for p in self.procs.values()))
        self.probe.wait(1.0)

    # ---------------------------------------------------------------- the replay
    def _step_kills(self, now_s: float, stamp_s: float) -> None:
        """Kill, restart and watch the nodes, one after the other, as the stream goes."""
        c = self.probe.counters
        current = next((k for k in self.kills if 'done' not in k), None)
        if current is not None:
            node, proc = current['node'], self.procs[current['node']]
            if 'killed_wall' not in current:
                if stamp_s >= self.next_kill_s:
                    current['exit_status'] = proc.kill()
                    current['killed_wall'], current['kill_stamp_s'] = now_s, stamp_s
                    current['kill_at_s'] = stamp_s
                    c.reset([node])
                    self.log(f'processes: SIGKILL {node} at {stamp_s:.1f} s')
            elif 'restart_wall' not in current:
                if stamp_s >= current['kill_stamp_s'] + self.cfg.down_s:
                    proc.start()
                    current['restart_wall'], current['restart_stamp_s'] = now_s, stamp_s
                    current['restart_unix'], current['log'] = time.time(), proc.stderr_path
                    self.log(f'processes: restarted {node} at {stamp_s:.1f} s')
            else:
                if 'ready_wall' not in current and node in c.values:
                    current['ready_wall'], current['ready_stamp_s'] = now_s, stamp_s
                if (node == 'camera_node' and 'ready_wall' in current
                        and 'matched_wall' not in current
                        and c.get(node, 'published_matches') > 0):
                    current['matched_wall'] = now_s
                back = self._recovered_at(node, current, self.probe.verdicts)
                if back is not None or now_s - current['restart_wall'] > \
                        self.cfg.recover_timeout_s:
                    current['done'] = True
                    current['recovered_stamp_s'] = stamp_s
                    self.next_kill_s = stamp_s + self.cfg.gap_s
        for name, proc in self.procs.items():
            down = current is not None and current['node'] == name and \
                'killed_wall' in current and 'restart_wall' not in current
            if not down and not proc.alive() and not any(
                    d['node'] == name and d['start'] == proc.starts for d in self.collateral):
                self.collateral.append({'node': name, 'start': proc.starts,
                                        'exit_code': proc.exit_code(),
                                        'cause': proc.failure()})

    def replay(self) -> None:
        stream, rate = self.stream, self.cfg.rate
        t0 = time.monotonic()
        s0 = stream.events[0].stamp_ns
        for event in stream.events:
            due = t0 + (event.stamp_ns - s0) / 1e9 / rate
            while True:
                now = time.monotonic()
                self._step_kills(now, stream.seconds(event.stamp_ns))
                if now >= due:
                    break
                time.sleep(min(0.01, due - now))
            self.probe.publish(event.topic, stream.message(event))
        end = time.monotonic() + 5.0 / rate + 2.0
        while time.monotonic() < end:          # the last epochs, a late ready
            self._step_kills(time.monotonic(), stream.seconds(stream.events[-1].stamp_ns))
            time.sleep(0.02)
        for k in self.kills:
            if 'killed_wall' not in k:
                k['not_killed'] = 'the drive ended first (lengthen it)'

    # ---------------------------------------------------------------- figures
    def figures(self) -> dict:
        """Per kill: recovery and the verdicts of its window."""
        stream = self.stream
        verdicts = [v for v in self.probe.verdicts if v.epoch_stamp_ns is not None]
        period_s = (stream.gnss_stamps[1] - stream.gnss_stamps[0]) / 1e9
        windows, rows = [], []
        for k in self.kills:
            row = {key: k.get(key) for key in ('node', 'kill_at_s', 'exit_status',
                                               'not_killed')}
            if 'restart_wall' not in k:
                rows.append(dict(row, recovered=False, recovery_s=math.inf))
                continue
            node, t_r = k['node'], k['restart_wall']
            flowing = self._recovered_at(node, k, verdicts)
            row['recovery_s'] = flowing - t_r if flowing is not None else math.inf
            heard = (k['ready_wall'] - t_r) if 'ready_wall' in k else math.inf
            row['startup_s'] = min(_ready_line_s(node, k), heard)
            row['discovery_s'] = heard - row['startup_s']
            row['graph_s'] = (flowing - k['ready_wall']
                              if flowing is not None and 'ready_wall' in k else math.inf)
            lo = k['kill_stamp_s']
            # gnss_node: until it is back (an epoch it passes then is a valid one; the
            # epoch of the stamp it was seen back at too: GNSS goes last at equal stamps,
            # so the kit sent it to the node already back);
            # imu_node: one epoch more (that epoch's motion spans the reset).
            hi = k.get('ready_stamp_s', math.inf) + (period_s if node == 'imu_node' else 0.0)
            if node == 'fusion_node':
                firsts = [stream.seconds(v.epoch_stamp_ns) for v in verdicts
                          if v.received_s > t_r and v.epoch_status is not None]
                hi = (firsts[0] if firsts else math.inf) + self.cfg.integrity_settling_s
            inside = [v for v in verdicts if lo <= stream.seconds(v.epoch_stamp_ns) <= hi
                      and not (node == 'gnss_node' and stream.seconds(v.epoch_stamp_ns) == hi)]
            row['window_s'] = [lo, hi]
            row['ok'] = sum(v.level == OK_LEVEL for v in inside)
            row['ok_stamps_s'] = [round(stream.seconds(v.epoch_stamp_ns), 3) for v in inside
                                  if v.level == OK_LEVEL]
            row['ready_stamp_s'] = k.get('ready_stamp_s')
            row['stale'] = sum(v.level == STALE_LEVEL for v in inside)
            row['error'] = len(inside) - row['ok'] - row['stale']
            row['violations'] = row['ok'] if node in REQUIRED else 0
            windows.append((lo, hi))
            rows.append(row)
        outside_ok = sum(1 for v in verdicts if v.level == OK_LEVEL and not any(
            lo <= stream.seconds(v.epoch_stamp_ns) <= hi for lo, hi in windows))
        return {'kills': rows, 'ok_outside_windows': outside_ok,
                'verdicts': len(verdicts)}

    def _recovered_at(self, node: str, k: dict, verdicts: list) -> float | None:
        """When the graph worked again after the restart of ``k``: the first verdict of an
        epoch stamped after the restart (a late verdict of an older epoch does not
        count) that is an update (fusion_node: any epoch verdict of the new filter;
        imu_node: with the motion known again); camera_node: its first match."""
        t_r = k['restart_wall']
        if node == 'camera_node':
            return k.get('matched_wall')
        after_ns = self.stream.gnss_stamps[0] + int(k['restart_stamp_s'] * 1e9)
        for v in verdicts:
            if (v.received_s <= t_r or v.epoch_status is None or v.epoch_stamp_ns is None
                    or v.epoch_stamp_ns < after_ns):
                continue
            if node == 'fusion_node':
                return v.received_s
            if v.epoch_status == 'updated' and (node != 'imu_node'
                                                or v.motion_unknown_s == 0.0):
                return v.received_s
        return None

    def stop_all(self) -> dict[str, int | None]:
        return {name: proc.stop() for name, proc in self.procs.items()}


def _ready_line_s(node: str, k: dict) -> float:
    """Seconds from the restart of ``k`` to the node's ready line (the wall-clock stamp of
    its log line; inf when it never logged one)."""
    try:
        text = k['log'].read_text(errors='replace')
    except (KeyError, OSError):
        return math.inf
    found = re.search(r'\[(\d+\.\d+)\] \[' + re.escape(node) + r'\]: ready:', text)
    return float(found.group(1)) - k['restart_unix'] if found else math.inf


def run_processes(cfg: ProcessesConfig, log=print) -> dict:
    """The kill/restart campaign; its figures and targets (JSON-able)."""
    t0 = time.monotonic()
    campaign = Campaign(cfg, log)
    campaign.probe = Probe(campaign.domain, 'fuzz_processes_probe')
    try:
        campaign.start_all()
        log(f'processes: {len(campaign.procs)} nodes up in {time.monotonic() - t0:.1f} s; '
            'killing ' + ', '.join(k['node'] for k in campaign.kills))
        campaign.replay()
        fig = campaign.figures()
    finally:
        exits = campaign.stop_all()
        campaign.probe.close()
    kills = fig['kills']
    worst = max((r['recovery_s'] for r in kills), default=math.nan)
    violations = sum(r.get('violations', 0) for r in kills)
    targets = [
        at_most(f'graph recovers within {cfg.target_recovery_s:g} s of a restart '
                '(worst)', worst, cfg.target_recovery_s),
        at_most('integrity OK while a needed input is missing or reset == 0', violations,
                0),
        at_least('OK verdicts outside the windows (the check bites) > 0',
                 fig['ok_outside_windows'], 1),
        at_most('other nodes exited meanwhile == 0', len(campaign.collateral), 0),
        Target('every node exits 0 when stopped', all(c == 0 for c in exits.values()),
               ', '.join(f'{n} {c}' for n, c in exits.items())),
    ]
    return {'config': asdict(cfg), 'drive_s': campaign.drive_s, 'kills': kills,
            'collateral': campaign.collateral, 'exit_codes_at_stop': exits,
            'ok_outside_windows': fig['ok_outside_windows'],
            'verdicts': fig['verdicts'], 'seconds': time.monotonic() - t0,
            'work_dir': str(campaign.work), 'targets': [t.as_dict() for t in targets]}


def print_processes(result: dict) -> list[Target]:
    rows = [[r['node'], r['kill_at_s'], r.get('exit_status'), r.get('startup_s'),
             r.get('discovery_s'), r.get('graph_s'), r['recovery_s'], r.get('ok'),
             r.get('error'), r.get('stale'), r.get('violations')] for r in result['kills']]
    print(table(['node', 'killed at s', 'kill status', 'start-up s', 'discovery s',
                 'graph s', 'recovery s', 'OK in window', 'ERROR', 'STALE', 'violations'],
                rows))
    for r in result['kills']:
        if r.get('not_killed'):
            print(f"{r['node']} not killed: {r['not_killed']}")
    for c in result['collateral']:
        print(f"{c['node']} exited ({c['exit_code']}) meanwhile: {c['cause']}")
    print(f"\n{result['verdicts']} epoch verdicts, {result['ok_outside_windows']} OK outside "
          f"the kill windows; exit codes at the end: {result['exit_codes_at_stop']}")
    return [Target(**t) for t in result['targets']]
