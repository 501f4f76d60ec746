"""``messages``: malformed and mutated messages against a running pipeline_node.

Two passes over the same seeded drive, each with a fresh pipeline_node child process in a
ROS domain of its own: a **clean** pass (the valid stream only: the baseline accuracy, RSS
and rejections) and a **fault** pass (the same stream with bursts of faults before GNSS
epochs, :mod:`.schedule`). The valid stream is paced by the graph: the sensor messages up to
a GNSS epoch, then that epoch, then its ``integrity_risk`` (at most ``hang_s``).

Measured in the fault pass: messages tried per kind; **crashes** (the process exited: it is
restarted and the run goes on; a kind that crashed it is not played again, and is
reported); **hangs** (no ``integrity_risk`` at all for more than ``hang_s`` while valid
input flows); **blocked** epochs (a valid epoch that never got its verdict) and a
**permanent block** (the last epochs of the drive unanswered); **RSS** of the pipeline
process (``/proc``); the **accounting** of every burst (:mod:`.accounting`; each
mutated message judged malformed or valid after mutation by :mod:`.plausible`); **lies**
(integrity OK with the error above the alert limit; on an epoch the kit injected, a
``gnss/measurements`` fault that passed every check, the error of its ``fix`` against the
truth interpolated at its stamp, and an OK that cannot be scored so counts as one); and
the **recovery**: seconds after the last fault until the estimate is back within 10 % (or
3 m) of the clean pass at every later epoch.
"""
from __future__ import annotations

import copy
import itertools
import math
import os
import re
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from msg_adapters import wire

from . import accounting, cases as fault_cases, plausible, schedule
from .graph import LINKS, NODE_NAMES, NodeProcess, Probe, write_params
from .mutate import mutate
from .stream import INPUT_TOPICS, StreamConfig, ValidStream
from .report import at_least, at_most, Target

OK_LEVEL = 0
#: Messages larger than this go out in fragments after ``publish`` returns (Fast DDS sends
#: a sample above 64 kB asynchronously) [bytes].
LARGE_MESSAGE_BYTES = 60_000
_runs = itertools.count()


@dataclass
class MessagesConfig:
    """A ``messages`` run (the CLI's options)."""

    seed: int = 1
    duration_s: float = 60.0
    warmup_s: float = 15.0
    tail_s: float = 20.0
    structured: int = 1000
    mutations: int = 200
    heavy: bool = True
    floods: bool = True
    camera: bool = True
    prestart: bool = True
    clean_pass: bool = True
    topics: tuple[str, ...] = INPUT_TOPICS
    only: list | None = None
    burst: int = 10
    gnss_rate_hz: float = 1.0
    particles: int | None = None
    acquisition_particles: int | None = None
    hang_s: float = 10.0
    block_epochs: int = 5
    max_crashes_per_kind: int = 1
    memory_limit_mb: float = 4096.0
    alert_limit_m: float = 25.0
    recovery_rel: float = 0.10
    recovery_abs_m: float = 3.0
    domain: int | None = None
    work_dir: str | None = None
    # Targets of the issue.
    target_malformed: int = 10_000
    target_mutations: int = 1_000
    target_recovery_s: float = 10.0
    target_rss_rel: float = 0.10


def fresh_domain() -> int:
    """A ROS domain for one run (150-219: apart from the tests' 1-209 start and the
    replay's 220-232; with the pid, concurrent runs rarely meet)."""
    env = os.environ.get('GNSSCAM_FUZZ_DOMAIN')
    if env and env.isdigit():
        return int(env)
    return 150 + (os.getpid() * 3 + next(_runs)) % 60


def node_parameters(cfg: MessagesConfig, stream: ValidStream) -> dict[str, dict]:
    """The nodes' parameters: fast diagnostics (the accounting reads them), a fixed
    filter seed (both passes compute the same), the drive's map frame (the camera
    database is in it), waits that do not depend on this machine's load."""
    fusion = {'diagnostics_period_s': 0.05, 'seed': cfg.seed, 'odometry_wait_s': 2.0,
              'odometry_timeout_s': 10.0, 'camera_wait_s': 1.0,
              'alert_limit_m': cfg.alert_limit_m}
    if cfg.particles is not None:
        fusion['n_particles'] = int(cfg.particles)
    if cfg.acquisition_particles is not None:
        fusion['acquisition_particles'] = int(cfg.acquisition_particles)
    camera = {'diagnostics_period_s': 0.05, 'input_reliable': True}
    if stream.database_path is not None:
        fusion.update(use_map_origin=True,
                      map_origin_llh=[float(v) for v in stream.drive.origin_llh])
        camera['database_path'] = str(stream.database_path)
    return {'gnss_node': {'diagnostics_period_s': 0.05},
            'imu_node': {'diagnostics_period_s': 0.05, 'source_timeout_s': 3600.0},
            'camera_node': camera, 'fusion_node': fusion}


@dataclass
class PassResult:
    """One pass (clean or with faults)."""

    label: str
    epochs: int = 0
    answered: set = field(default_factory=set)
    unanswered: list = field(default_factory=list)
    crashes: list = field(default_factory=list)
    blocks: list = field(default_factory=list)
    restarts: list = field(default_factory=list)
    bursts: list = field(default_factory=list)
    rss: list = field(default_factory=list)
    verdicts: list = field(default_factory=list)
    fixes: dict = field(default_factory=dict)
    collateral_rejections: float = 0.0
    sync_timeouts: int = 0
    exit_code: int | None = None
    slot_kinds: dict = field(default_factory=dict)
    last_fault_stamp: int | None = None
    quarantined: list = field(default_factory=list)
    seconds: float = 0.0


class FaultPass:
    """Runs one pass: the valid stream, the bursts of ``plan`` in their slots.

    Args:
        cfg: The run's configuration.
        stream: The valid stream.
        plan: Bursts (empty: a clean pass).
        label: ``'clean'`` or ``'faults'``.
        work: Folder for the params file and logs.
        log: Progress printer.
    """

    def __init__(self, cfg: MessagesConfig, stream: ValidStream, plan: list, label: str,
                 work: Path, domain: int, log=print):
        self.cfg, self.stream, self.label, self.log = cfg, stream, label, log
        self.work = work / label
        self.work.mkdir(parents=True, exist_ok=True)
        self.by_slot: dict[int, list] = {}
        for b in plan:
            self.by_slot.setdefault(b.slot, []).append(b)
        params = write_params(self.work / 'params.yaml', node_parameters(cfg, stream))
        self.pipeline = NodeProcess('pipeline', params, domain, self.work,
                                    cfg.memory_limit_mb)
        self.result = PassResult(label)
        self.rng = np.random.default_rng([cfg.seed, 2])
        self.last_stamp: dict[str, int] = {}
        self.last_kind = None
        self.crashed_kinds: dict[str, int] = {}
        self._reset_ledger()
        self.probe: Probe | None = None

    # ------------------------------------------------------------------ ledger
    def _reset_ledger(self) -> None:
        self.sent = {t: 0 for t in LINKS}
        self.known_lost = {t: 0.0 for t in LINKS}
        self.last_rejected = 0.0
        self.unsynced: accounting.BurstResult | None = None
        self.unacknowledged: set[str] = set()
        # A restarted node counts from 0 again: the losses it owed are never counted.
        self.losses = accounting.LossLedger()

    def _expected(self, topic: str, counters) -> float:
        return self.sent[topic] + counters.upstream(topic) - self.known_lost[topic]

    def sync(self, settle_s: float = 0.0) -> tuple[dict, bool]:
        """Wait until the reliable subscribers acknowledged the large messages the probe
        sent, every node reported twice since then (by its own clock) and each has
        either received what was sent to it or taken everything that was waiting (the
        same counts for :data:`.graph.DRAINED_QUIET_S`): what is missing then was lost on
        the way. The figures come from one copy of the reports. False at
        the timeout (``hang_s``: a node stuck in one callback) or when the process exited.
        Never before ``settle_s`` (a large message takes a while on the way)."""
        c = self.probe.counters
        # A large message the probe sent is in the nodes' queues first (reliable
        # subscribers acknowledge it): a window that closed while one was still on its way
        # would book it as lost, and its refusal as the next window's. (Small ones leave
        # within publish(); an acknowledgement waits for the writer's next heartbeat, up
        # to 3 s.)
        if self.pipeline.alive():
            for topic in sorted(self.unacknowledged):
                self.probe.acknowledged(topic, self.cfg.hang_s)
        self.unacknowledged.clear()
        since_ns = time.time_ns()
        not_before = time.monotonic() + settle_s
        nodes_of = {node: [t for t, link in LINKS.items() if link[0] == node]
                    for node in NODE_NAMES}

        def settled() -> bool:
            if not self.pipeline.alive():
                return True
            if time.monotonic() < not_before or not all(
                    c.reported_since(n, since_ns) for n in NODE_NAMES):
                return False
            now = c.reading()
            return all(c.drained(n) or all(now.received(t) >= self._expected(t, now)
                                           for t in nodes_of[n]) for n in NODE_NAMES)

        ok = self.probe.spin_until(settled, self.cfg.hang_s)
        if not ok:
            # A node busy for hang_s (one long callback): what it has not taken yet may
            # still come; only a node that has taken everything decides what was lost.
            self.result.sync_timeouts += 1
        now = c.reading()
        if ok and self.pipeline.alive():
            for t in LINKS:
                short = self._expected(t, now) - now.received(t)
                if short > 0:
                    self.known_lost[t] += short
        return now.snapshot(), ok and self.pipeline.alive()

    def _sent_large(self, topic: str, msg) -> None:
        size = len(msg) if isinstance(msg, bytes) else len(getattr(msg, 'data', b''))
        if size > LARGE_MESSAGE_BYTES:
            self.unacknowledged.add(topic)

    # ------------------------------------------------------------------ process
    def start(self) -> None:
        self.pipeline.start()
        self.probe.counters.reset()
        self._reset_ledger()
        counters = self.probe.counters

        def matched() -> bool:
            # Every input link matched at the node's end (its diagnostics say so): the
            # probe's publisher, and the graph's own for the links between nodes.
            return all(counters.get(node, f'publishers_{topic}') >= (2 if up else 1)
                       for topic, (node, _, up, _) in LINKS.items())

        subscribed = self.probe.spin_until(
            lambda: not self.pipeline.alive() or (
                all(n in counters.values for n in NODE_NAMES) and matched()), 90.0)
        if not subscribed or not self.pipeline.alive():
            raise RuntimeError(f'pipeline_node did not start: {self.pipeline.failure()}')
        self.probe.wait(0.5)       # best-effort readers match a moment after the writer

    def _restart(self) -> None:
        t0 = time.monotonic()
        if self.pipeline.alive():
            self.pipeline.stop()
        self.start()
        self.result.restarts.append((t0, time.monotonic()))

    def _check_alive(self, k: int, during: str) -> bool:
        """False (and a restarted pipeline) when the process exited."""
        if self.pipeline.alive():
            return True
        kind = self.last_kind or 'valid input'
        cause = self.pipeline.failure()
        failed = re.search(r'\[(\w+_node)\]', cause)
        # A node that fails on its own state (poisoned by an earlier fault) names itself:
        # the recent faults on its inputs are suspects too.
        suspects = [] if failed is None else list(dict.fromkeys(
            b.kind for b in reversed(self.result.bursts[-12:])
            if LINKS[b.topic][0] == failed.group(1) and b.kind != kind))
        self.result.crashes.append({
            'kind': kind, 'during': during, 'epoch': k, 'suspects': suspects,
            'exit_code': self.pipeline.exit_code(), 'cause': cause,
            'peak_rss_mb': self.pipeline.peak_rss_mb})
        self.crashed_kinds[kind] = self.crashed_kinds.get(kind, 0) + 1
        self.log(f'[{self.label}] pipeline_node exited ({self.pipeline.exit_code()}) after '
                 f'{kind} ({during}): {self.pipeline.failure(1)}; restarting')
        self._restart()
        return False

    def _suspects(self, k: int) -> list[str]:
        """The kinds played last before epoch ``k`` (those of the nearest slot with any)."""
        for slot in range(k, -2, -1):
            if self.result.slot_kinds.get(slot):
                return list(self.result.slot_kinds[slot])
        return []

    def _blocked(self, k: int, streak: list[int]) -> None:
        """``streak``: consecutive valid epochs without a verdict, up to ``k``. Long enough
        and the process alive: a block; it is recorded with its suspects and the pipeline
        restarted, so that the rest of the run still measures something."""
        if len(streak) < self.cfg.block_epochs or not self.pipeline.alive():
            return
        suspects = self._suspects(streak[0])
        self.result.blocks.append({'kinds': suspects, 'epoch': streak[0],
                                   'epochs_unanswered': len(streak)})
        if len(suspects) == 1:
            self.crashed_kinds[suspects[0]] = self.crashed_kinds.get(suspects[0], 0) + 1
        self.log(f'[{self.label}] no verdict for {len(streak)} epochs from epoch '
                 f'{streak[0]} on (after {", ".join(suspects) or "valid input"}); '
                 'restarting pipeline_node')
        self._restart()
        streak.clear()

    # ------------------------------------------------------------------ valid stream
    def _publish_valid(self, event) -> None:
        msg = self.stream.message(event)
        if self.probe.publish(event.topic, msg):
            self.sent[event.topic] += 1
            self._sent_large(event.topic, msg)
        self.last_stamp[event.topic] = event.stamp_ns

    def _wait_verdict(self, stamp_ns: int) -> bool:
        probe = self.probe

        def answered() -> bool:
            return (not self.pipeline.alive()) or any(
                v.epoch_stamp_ns == stamp_ns and v.epoch_status is not None
                for v in probe.verdicts[-20:])
        return probe.spin_until(answered, self.cfg.hang_s) and self.pipeline.alive()

    # ------------------------------------------------------------------ bursts
    def _last_stamp(self, topic: str) -> int | None:
        source = {wire.GNSS_MEASUREMENTS: wire.GNSS, wire.DEAD_RECKONING: wire.TWIST,
                  wire.MATCHES: wire.IMAGE}.get(topic, topic)
        return self.last_stamp.get(source)

    def _base_stamp(self, topic: str, slot: int) -> int:
        stamps = self.stream.gnss_stamps
        epoch = stamps[max(slot, 0)] if slot >= 0 else stamps[0] - 10**9
        if topic in (wire.GNSS, wire.GNSS_MEASUREMENTS):
            # Between the previous epoch and this one.
            period = stamps[1] - stamps[0] if len(stamps) > 1 else 10**9
            return epoch - int(0.4 * period)
        return epoch                          # just after the motion and image of it

    def _messages(self, burst, slot: int, serial: list[int]) -> list:
        """The burst's messages, each with its judgement (:mod:`.plausible`; None for a
        fault that is not judged)."""
        fault = burst.fault
        topic = fault.topic
        base = self._base_stamp(topic, slot)
        templates = self.stream.templates(max(base, self.stream.gnss_stamps[0]))
        out = []
        for _ in range(burst.n):
            serial[0] += 1
            stamp = base + 1000 * serial[0]
            if getattr(fault, 'reuse_stamp', False):
                stamp = self._last_stamp(topic) or stamp
            original = fault_cases.stamped(copy.deepcopy(templates[topic]), stamp)
            if isinstance(fault, fault_cases.Case):
                msg = fault_cases.build(fault, templates[topic], stamp, self.rng)
            else:
                msg = mutate(original, self.rng, fault.operator)[0]
            judged = plausible.judge(topic, original, msg) if fault.judged else None
            out.append((msg, judged))
        return out

    def _burst(self, burst, slot: int, serial: list[int]) -> None:
        """Play one burst; a judged one as two: its malformed messages (expected refused)
        and those valid after mutation (``'any'``), each in a window of its own."""
        fault = burst.fault
        if self.crashed_kinds.get(fault.kind, 0) >= self.cfg.max_crashes_per_kind:
            if fault.kind not in self.result.quarantined:
                self.result.quarantined.append(fault.kind)
            return
        msgs = self._messages(burst, slot, serial)
        if not fault.judged:
            self._play(fault, [m for m, _ in msgs], fault.expect, slot)
            return
        for valid, expect in ((False, fault_cases.REJECT), (True, fault_cases.ANY)):
            group = [(m, j) for m, j in msgs if j.valid == valid]
            if group:
                self._play(fault, [m for m, _ in group], expect, slot,
                           valid_after_mutation=valid,
                           judged=list(dict.fromkeys(j.why for _, j in group))[:3])
            if not self.pipeline.alive():
                return

    def _play(self, fault, msgs: list, expect: str, slot: int,
              valid_after_mutation: bool = False, judged: list | None = None) -> None:
        before, _ = self.sync()
        self.losses.observe(before['lost'], self.known_lost)
        self._after_window(before)
        size = sum(len(m) if isinstance(m, bytes) else len(getattr(m, 'data', b''))
                   for m in msgs)
        t0 = time.monotonic()
        res = accounting.BurstResult(fault.kind, fault.topic, fault.family, expect,
                                     sent=0, epoch=slot, t_wall=t0, judged=judged or [])
        self.last_kind = fault.kind
        for msg in msgs:
            if self.probe.publish(fault.topic, msg):
                res.sent += 1
                self.sent[fault.topic] += 1
                self._sent_large(fault.topic, msg)
            else:
                res.unsendable += 1
        del msgs
        if valid_after_mutation:
            res.valid_after_mutation = res.sent
        after, res.synced = self.sync(settle_s=0.05 + size / 20e6)
        res.seconds = time.monotonic() - t0
        if not self.pipeline.alive():      # a crash: booked as such, not as a loss
            res.delivered, res.synced = res.sent, False
            self.result.bursts.append(res)
            return
        res.delivered = int(after['received'][fault.topic] - before['received'][fault.topic])
        if not res.synced:            # still being processed: delivery not known yet
            res.delivered = max(res.delivered, res.sent)
        res.counted_loss = int(after['lost'][fault.topic] - before['lost'][fault.topic])
        res.rejected = int(after['rejected'] - before['rejected'])
        res.dropped = int(after['dropped'][fault.topic] - before['dropped'][fault.topic])
        res.satellites = int(after['satellites'] - before['satellites'])
        res.reasons = {k: int(v - before['by_reason'].get(k, 0.0))
                       for k, v in after['by_reason'].items()
                       if v > before['by_reason'].get(k, 0.0)}
        self.last_rejected = after['rejected']
        self.losses.observe(after['lost'], self.known_lost, res)
        self.unsynced = None if res.synced else res
        self.result.bursts.append(res)

    def _after_window(self, snapshot: dict) -> None:
        """Rejections since the last burst's window: the collateral damage of the faults
        (valid messages refused), unless that window closed before the node had taken the
        burst (a sync that timed out): its refusals come now and are the burst's."""
        late = max(0.0, snapshot['rejected'] - self.last_rejected)
        if self.unsynced is not None:
            res, self.unsynced = self.unsynced, None
            owed = (max(0, res.delivered - res.rejected - res.dropped)
                    if res.satellites <= 0 else 0)
            taken = int(min(late, owed))
            res.rejected += taken
            late -= taken
        self.result.collateral_rejections += late
        self.last_rejected = snapshot['rejected']

    def _faults_before(self, slot: int) -> None:
        serial = [0]
        for burst in self.by_slot.get(slot, []):
            self.result.slot_kinds.setdefault(slot, []).append(burst.kind)
            self._burst(burst, slot, serial)
            self.result.last_fault_stamp = (self.stream.gnss_stamps[max(slot, 0)]
                                            - (1 if slot >= 0 else 10**9))
            self._check_alive(slot, 'burst')

    # ------------------------------------------------------------------ the pass
    def run(self, probe: Probe) -> PassResult:
        self.probe = probe
        t_start = time.monotonic()
        first_verdict = len(probe.verdicts)
        self.start()
        stream, res = self.stream, self.result
        self._faults_before(-1)
        events = iter(stream.events)
        pending = next(events, None)
        streak: list[int] = []
        for k, stamp in enumerate(stream.gnss_stamps):
            while pending is not None and (pending.stamp_ns < stamp or (
                    pending.stamp_ns == stamp and pending.topic != wire.GNSS)):
                self._publish_valid(pending)
                pending = next(events, None)
            self._faults_before(k)
            if pending is not None and pending.topic == wire.GNSS:
                self._publish_valid(pending)
                pending = next(events, None)
            if self._wait_verdict(stamp):
                streak.clear()
            else:
                streak.append(k)
            if self._check_alive(k, f'epoch {k}'):
                res.rss.append((stream.seconds(stamp), self.pipeline.rss_mb(),
                                self.pipeline.peak_rss_mb))
                self._blocked(k, streak)
            else:
                streak.clear()
        final, _ = self.sync()
        self.losses.observe(final['lost'], self.known_lost)
        self._after_window(final)
        probe.spin_until(lambda: False, 0.3)
        res.exit_code = self.pipeline.stop()
        res.epochs = len(stream.gnss_stamps)
        res.verdicts = probe.verdicts[first_verdict:]
        res.answered = {v.epoch_stamp_ns for v in res.verdicts
                        if v.epoch_stamp_ns is not None and v.epoch_status is not None}
        res.unanswered = [s for s in stream.gnss_stamps if s not in res.answered]
        res.fixes = dict(probe.fixes)
        probe.fixes.clear()
        res.seconds = time.monotonic() - t_start
        return res


# ====================================================================== the run
def run_messages(cfg: MessagesConfig, log=print) -> dict:
    """Both passes and the figures (a JSON-able dict, ``targets`` included)."""
    work = Path(cfg.work_dir or tempfile.mkdtemp(prefix='gnsscam_fuzz_messages_'))
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    stream = ValidStream(StreamConfig(seed=cfg.seed, duration_s=cfg.duration_s,
                                      gnss_rate_hz=cfg.gnss_rate_hz, camera=cfg.camera),
                         work)
    topics = tuple(t for t in cfg.topics if t != wire.IMAGE or cfg.camera)
    cases = fault_cases.all_cases(topics, heavy=cfg.heavy, floods=cfg.floods)
    if cfg.only:
        cases = [c for c in cases if any(o in c.kind for o in cfg.only)]
    slots = [k for k, s in enumerate(stream.gnss_stamps)
             if cfg.warmup_s <= stream.seconds(s) <= cfg.duration_s - cfg.tail_s]
    plan = schedule.plan(cases, topics, cfg.structured, cfg.mutations, slots,
                         np.random.default_rng([cfg.seed, 1]), cfg.burst, cfg.prestart)
    log(f'messages: {len(stream.gnss_stamps)} epochs, {len(stream.events)} valid messages, '
        f'{sum(b.n for b in plan)} faults in {len(plan)} bursts over {len(slots)} epochs')
    domain = cfg.domain if cfg.domain is not None else fresh_domain()
    probe = Probe(domain)
    passes = {}
    try:
        if cfg.clean_pass:
            passes['clean'] = FaultPass(cfg, stream, [], 'clean', work, domain,
                                        log).run(probe)
            log(f"clean pass: {passes['clean'].seconds:.1f} s")
        passes['faults'] = FaultPass(cfg, stream, plan, 'faults', work, domain,
                                     log).run(probe)
        log(f"fault pass: {passes['faults'].seconds:.1f} s")
    finally:
        probe.close()
    meta = schedule.meta([b.fault for b in plan])
    every = fault_cases.all_cases(topics, heavy=True) + schedule.prestart_cases()
    out = summarize(cfg, stream, passes, meta, {c.kind for c in every if c.issue})
    out['seconds'] = time.monotonic() - t0
    out['work_dir'] = str(work)
    return out


def _errors(stream: ValidStream, res: PassResult) -> dict[int, float]:
    valid = set(stream.gnss_stamps)
    return {s: stream.horizontal_error_m(s, *fix) for s, fix in res.fixes.items()
            if s in valid}


def silences(res: PassResult) -> list[tuple[float, float]]:
    """Intervals between consecutive verdicts (wall time), but those that span a restart
    (a crash or a block, counted as such)."""
    times = sorted(v.received_s for v in res.verdicts)
    return [(a, b) for a, b in zip(times, times[1:])
            if not any(a <= r1 and b >= r0 for r0, r1 in res.restarts)]


def injected_ok_errors(stream: ValidStream, res: PassResult, ok: list) -> list:
    """The horizontal error of the estimate of every OK verdict on an epoch the kit
    injected (a ``gnss/measurements`` fault that passed every check) [m]: its ``fix``
    against the truth interpolated at its stamp; None when it cannot be scored (a stamp
    outside the drive, no fix of that stamp)."""
    valid = set(stream.gnss_stamps)
    first, last = int(stream.truth_stamp_ns[0]), int(stream.truth_stamp_ns[-1])
    out = []
    for v in ok:
        stamp = v.epoch_stamp_ns
        if stamp in valid:
            continue
        fix = res.fixes.get(stamp)
        out.append(None if fix is None or not first <= stamp <= last
                   else stream.horizontal_error_m(stamp, *fix))
    return out


def pass_figures(cfg: MessagesConfig, stream: ValidStream, res: PassResult) -> dict:
    """The figures of one pass."""
    errors = _errors(stream, res)
    valid = set(stream.gnss_stamps)
    gaps = silences(res)
    ok = [v for v in res.verdicts if v.level == OK_LEVEL and v.epoch_stamp_ns is not None]
    misleading = [v for v in ok if v.epoch_stamp_ns in valid
                  and errors.get(v.epoch_stamp_ns, math.inf) > cfg.alert_limit_m]
    injected = injected_ok_errors(stream, res, ok)
    scored = [e for e in injected if e is not None]
    n_tail = min(cfg.block_epochs, len(stream.gnss_stamps))
    permanent = set(stream.gnss_stamps[-n_tail:]) <= set(res.unanswered)
    rss = [r for _, r, _ in res.rss if math.isfinite(r)]
    # The watchdog samples the peak on its own clock; a sample taken here can be the
    # larger one, so the peak is the largest of everything seen.
    peaks = ([p for _, _, p in res.rss] + rss
             + [c.get('peak_rss_mb', 0.0) for c in res.crashes])
    return {
        'epochs': res.epochs, 'answered': len(res.answered & valid),
        'unanswered': len(res.unanswered), 'permanent_block': bool(permanent),
        'blocks': len(res.blocks) + int(permanent),
        'longest_silence_s': max((b - a for a, b in gaps), default=0.0),
        'hangs': sum(1 for a, b in gaps if b - a > cfg.hang_s),
        'crashes': len(res.crashes), 'restarts': len(res.restarts),
        'sync_timeouts': res.sync_timeouts, 'exit_code_at_stop': res.exit_code,
        'rss_start_mb': rss[0] if rss else math.nan,
        'rss_peak_mb': max(peaks) if peaks else math.nan,
        'rss_end_mb': rss[-1] if rss else math.nan,
        'rejections_of_valid_input': res.collateral_rejections,
        'ok_verdicts': len(ok), 'misleading_ok': len(misleading),
        'ok_on_injected_epochs': len(injected),
        'ok_on_injected_scored': len(scored),
        'misleading_ok_on_injected': sum(1 for e in scored if e > cfg.alert_limit_m),
        'ok_on_injected_unscored': len(injected) - len(scored),
        'ok_on_injected_error_max_m': max(scored, default=None),
        'estimates_of_injected_epochs': sum(1 for s in res.fixes if s not in valid),
        'error': accounting.error_summary(errors, stream.gnss_stamps),
        'seconds': res.seconds,
    }


def summarize(cfg: MessagesConfig, stream: ValidStream, passes: dict, meta: dict,
              issue_kinds: set[str] = frozenset()) -> dict:
    """The run's figures and targets (``issue_kinds``: every single-message case of the
    issue, played or not)."""
    faults = passes['faults']
    kinds = accounting.by_kind(faults.bursts, meta)
    for crash in faults.crashes:
        if crash['kind'] in kinds:
            kinds[crash['kind']].crashes += 1
            kinds[crash['kind']].crash_causes.append(crash['cause'])
    for block in faults.blocks:
        for kind in block['kinds']:
            if kind in kinds:
                kinds[kind].blocks += 1
    for a, b in silences(faults):
        before = [x for x in faults.bursts if x.t_wall < b]
        if b - a > cfg.hang_s and before:
            kinds[before[-1].kind].hangs += 1
    figures = {label: pass_figures(cfg, stream, res) for label, res in passes.items()}
    structured = sum(k.sent for k in kinds.values() if k.family == 'structured')
    mutated = sum(k.sent for k in kinds.values() if k.family == 'mutation')
    valid_after = sum(k.valid_after_mutation for k in kinds.values()
                      if k.family in ('structured', 'mutation'))
    malformed = structured + mutated - valid_after
    flooded = sum(k.sent for k in kinds.values() if k.family == 'flood')
    uncounted = sum(k.uncounted for k in kinds.values())
    f = figures['faults']
    clean = figures.get('clean')
    rss_rel = math.nan
    recovery = math.nan
    if clean is not None:
        rss_rel = abs(f['rss_end_mb'] - clean['rss_end_mb']) / clean['rss_end_mb']
        recovery = accounting.recovery_s(
            stream.gnss_stamps, _errors(stream, faults), _errors(stream, passes['clean']),
            faults.last_fault_stamp, cfg.recovery_rel, cfg.recovery_abs_m)
    tried = {k.kind for k in kinds.values() if k.issue and k.sent}
    issue_all = set(issue_kinds) | {k.kind for k in kinds.values() if k.issue}
    issue_bad = [k.kind for k in kinds.values() if k.issue and k.outcome != 'ok']
    targets = [
        at_least(f'malformed messages >= {cfg.target_malformed}', malformed,
                 cfg.target_malformed),
        at_least(f'random mutations >= {cfg.target_mutations}', mutated,
                 cfg.target_mutations),
        Target('every single-message case of the issue tried', tried >= issue_all,
               f'{len(tried & issue_all)} of {len(issue_all)}'
               + ('' if cfg.heavy else ' (heavy cases left out)')),
        at_most('crashes == 0', f['crashes'], 0),
        at_most('hangs == 0', f['hangs'], 0),
        Target('no permanent block', f['blocks'] == 0,
               f"{f['blocks']} blocks ({cfg.block_epochs}+ epochs without a verdict), "
               f"{f['unanswered']} epochs unanswered"),
        at_most('uncounted rejections/losses == 0', uncounted, 0),
        Target('misleading OK == 0',
               f['misleading_ok'] + f['misleading_ok_on_injected']
               + f['ok_on_injected_unscored'] == 0,
               f"{f['misleading_ok']} on valid epochs, {f['misleading_ok_on_injected']} on "
               f"injected ones (of {f['ok_on_injected_scored']} scored), "
               f"{f['ok_on_injected_unscored']} injected unscored"),
        at_most(f'RSS after within {cfg.target_rss_rel:.0%} of clean', rss_rel,
                cfg.target_rss_rel),
        at_most(f'estimate back within {cfg.target_recovery_s:g} s', recovery,
                cfg.target_recovery_s),
    ]
    return {
        'config': {k: (list(v) if isinstance(v, tuple) else v)
                   for k, v in asdict(cfg).items()},
        'messages': {'structured': structured, 'mutations': mutated,
                     'total': structured + mutated, 'valid_after_mutation': valid_after,
                     'malformed': malformed, 'floods': flooded,
                     'unsendable': sum(k.unsendable for k in kinds.values())},
        'passes': figures, 'rss_rel_to_clean': rss_rel, 'recovery_s': recovery,
        'uncounted': uncounted, 'issue_cases_failing': issue_bad,
        'by_topic': accounting.by_topic(kinds),
        'kinds': {k: v.as_dict() for k, v in sorted(kinds.items())},
        'crashes': faults.crashes, 'blocks': faults.blocks,
        'bursts': [dict(asdict(b), lost=b.lost, uncounted_loss=b.uncounted_loss,
                        refused=b.refused, silently_accepted=b.silently_accepted)
                   for b in faults.bursts],
        'quarantined': faults.quarantined,
        'targets': [t.as_dict() for t in targets],
    }
