"""The fault-injection kit (``python -m tools.fuzz``): its parts, and a short
seeded sample of each campaign.

The samples assert the kit's mechanics (it tried what it was asked to, in every topic and
tool, measured RSS, counted rejections, restarted what it killed) and only the targets of
the issue that already hold today:

* ``messages``: the clean pass answers every epoch without a crash; under fault no crash,
  no hang, no permanent block, no malformed message taken or lost without a count, the
  estimate back to its clean accuracy before the drive ends, and no misleading OK (no OK
  verdict with the error above the alert limit, on a valid epoch or, scored against the
  truth at its stamp, on one the kit injected);
* ``processes``: each killed node restarted and the graph answering again before the drive
  ends; no integrity OK while a needed input is missing or reset, while OK verdicts
  outside those windows show the check bites; no other node exits when one is killed;
  every node exits 0 when stopped;
* ``files``: every tool's corrupt inputs handled as documented (no traceback, the
  documented exit code, the file named, nothing overwritten or left behind).

How fast (recovery seconds, restart time) and RSS are the campaigns' figures, measured
alone: a loaded test machine would turn them into flaky tests.
"""
from __future__ import annotations

import copy
import math

import numpy as np
import pytest
from ros_harness import ros_domain_id, serialize_message  # skips without rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.serialization import deserialize_message

import msg_adapters as ma
from gnsscam_ros.core.gnss import check_epoch
from msg_adapters import limits, wire
from tools.fuzz import accounting, cases, mutate, plausible, schedule
from tools.fuzz.cases import flip_bit
from tools.fuzz.corpus import build_corpus
from tools.fuzz.corrupt_data import BAG_VARIANTS, replay_case
from tools.fuzz.files import GENERATORS, FilesConfig, run_case, run_files
from tools.fuzz.graph import DRAINED_QUIET_S, TOPIC_TYPES, Counters, Verdict
from tools.fuzz.messages import MessagesConfig, PassResult, injected_ok_errors, run_messages
from tools.fuzz.processes import ProcessesConfig, run_processes
from tools.fuzz.report import Target, verdict_line
from tools.fuzz.stream import INPUT_TOPICS, StreamConfig, ValidStream
from tools.fuzz.tools import fingerprint, run_in_process


@pytest.fixture(scope='module')
def stream(tmp_path_factory):
    return ValidStream(StreamConfig(seed=1, duration_s=6.0),
                       tmp_path_factory.mktemp('fuzz_stream'))


# ====================================================================== parts
def test_every_case_builds_a_message_of_its_topic(stream):
    tpl = stream.templates(stream.gnss_stamps[2])
    rng = np.random.default_rng(0)
    all_cases = cases.all_cases(heavy=False)
    assert {c.topic for c in all_cases} == set(INPUT_TOPICS)
    assert len({c.kind for c in all_cases}) == len(all_cases)
    for case in all_cases:
        msg = cases.build(case, tpl[case.topic], stream.gnss_stamps[2] + 1000, rng)
        assert isinstance(msg, type(tpl[case.topic])), case.kind
        assert serialize_message(msg), case.kind
    issue = {c.kind for c in cases.all_cases(heavy=True) if c.issue}
    for kind in ('gnss/pseudoranges:stamp_sec_max', 'gnss/pseudoranges:coord_1e160',
                 'gnss/pseudoranges:satellites_10000', 'odom/twist:linear_x_1.7e308',
                 'camera/matches:position_1e300', 'odometry/dead_reckoning:position_1e300',
                 'camera/image_raw:image_8000x8000', 'imu/data:stamp_far_future'):
        assert kind in issue


def test_mutations_are_seeded_and_leave_the_template_alone(stream):
    tpl = stream.templates(stream.gnss_stamps[2])
    for topic in INPUT_TOPICS:
        original = copy.deepcopy(tpl[topic])
        for operator in mutate.OPERATORS:
            a = mutate.mutate(tpl[topic], np.random.default_rng(5), operator)[0]
            b = mutate.mutate(tpl[topic], np.random.default_rng(5), operator)[0]
            # CDR padding bytes are not initialised by the serialiser: raw mutations are
            # compared by size, message mutations field by field.
            assert (len(a) == len(b)) if isinstance(a, bytes) else (a == b), \
                (topic, operator)
        assert tpl[topic] == original, topic


def test_plan_reaches_the_counts_and_spreads_the_bursts():
    rng = np.random.default_rng(1)
    all_cases = cases.all_cases(heavy=True)
    plan = schedule.plan(all_cases, INPUT_TOPICS, 400, 60, list(range(10, 200)), rng)
    structured = sum(b.n for b in plan if b.fault.family == 'structured' and b.slot >= 0)
    mutated = sum(b.n for b in plan if b.fault.family == 'mutation')
    assert structured >= 400 and mutated == 60
    heavy = [b for b in plan if getattr(b.fault, 'heavy', False)]
    assert len(heavy) == len({b.kind for b in heavy}) and all(b.n == 1 for b in heavy)
    assert sum(b.slot == -1 for b in plan) == len(schedule.PRESTART_TOPICS)
    assert {b.fault.topic for b in plan if b.fault.family == 'flood'} == set(INPUT_TOPICS)
    played = {b.kind for b in plan}
    assert all(c.kind in played for c in all_cases)          # every case at least once
    slots = [b.slot for b in plan if b.slot >= 0]
    assert min(slots) >= 10 and max(slots) < 200


def test_burst_accounting():
    lost = accounting.BurstResult('t:k', 't', 'structured', 'reject', sent=10, delivered=7,
                                  counted_loss=1, rejected=5)
    assert (lost.lost, lost.uncounted_loss, lost.refused, lost.silently_accepted) == \
        (3, 2, 5, 2)
    sanitised = accounting.BurstResult('t:k', 't', 'structured', 'reject', sent=2,
                                       delivered=2, satellites=3)
    assert sanitised.silently_accepted == 0
    plausible = accounting.BurstResult('t:m', 't', 'mutation', 'any', sent=5, delivered=5)
    assert plausible.silently_accepted == 0
    # A frame dropped from the full matcher queue (counted) is not accepted silently.
    queued = accounting.BurstResult('t:k', 't', 'structured', 'reject', sent=4, delivered=4,
                                    rejected=3, dropped=1)
    assert queued.silently_accepted == 0


def test_judged_bursts_count_valid_messages_apart_and_late_counts_settle_losses():
    valid = accounting.BurstResult('t:mutation_scale', 't', 'mutation', 'any', sent=3,
                                   delivered=3, valid_after_mutation=3)
    malformed = accounting.BurstResult('t:mutation_scale', 't', 'mutation', 'reject',
                                       sent=2, delivered=2, rejected=1)
    kinds = accounting.by_kind([valid, malformed], {})
    k = kinds['t:mutation_scale']
    assert (k.sent, k.malformed, k.valid_after_mutation, k.silently_accepted) == (5, 2, 3, 1)
    assert accounting.by_topic(kinds)['t']['valid_after_mutation'] == 3
    # A flood that lost 10, of which the node counted 6 in the window ...
    ledger = accounting.LossLedger()
    ledger.observe({'t': 0.0, 'u': 0.0}, {'t': 0.0, 'u': 0.0})
    flood = accounting.BurstResult('t:flood', 't', 'flood', 'any', sent=30, delivered=20,
                                   counted_loss=6)
    ledger.observe({'t': 6.0, 'u': 0.0}, {'t': 10.0, 'u': 0.0}, flood)
    assert flood.uncounted_loss == 4
    # ... a later rise of the count that the kit's own valid stream explains settles
    # nothing, one beyond it settles the debt (no further than the debt).
    ledger.observe({'t': 8.0, 'u': 0.0}, {'t': 12.0, 'u': 0.0})
    assert flood.uncounted_loss == 4
    ledger.observe({'t': 15.0, 'u': 3.0}, {'t': 12.0, 'u': 0.0})
    assert (flood.counted_late, flood.uncounted_loss) == (4, 0)


def _report(counters, node: str, t_s: float, **values) -> None:
    msg = DiagnosticArray()
    msg.header.stamp = ma.ns_to_stamp(int(t_s * 1e9))
    msg.status = [DiagnosticStatus(name=f'{node}: status', values=[
        KeyValue(key=k, value=str(v)) for k, v in values.items()])]
    counters.update(msg)


def test_a_node_is_drained_only_after_its_counts_stood_still_for_a_while():
    c = Counters()
    period = 0.05
    _report(c, 'imu_node', 10.0, received_imu=4, rejected_total=4)
    _report(c, 'imu_node', 10.0 + period, received_imu=4, rejected_total=4)
    # Two reports one period apart with the same counts: a best-effort message may still
    # be on its way on a loaded machine.
    assert not c.drained('imu_node')
    t = 10.0 + period
    while t < 10.0 + DRAINED_QUIET_S:
        assert not c.drained('imu_node')
        t += period
        _report(c, 'imu_node', t, received_imu=4, rejected_total=4)
    assert c.drained('imu_node')
    # A message taken starts the wait again.
    _report(c, 'imu_node', t + period, received_imu=5, rejected_total=5)
    _report(c, 'imu_node', t + 2 * period, received_imu=5, rejected_total=5)
    assert not c.drained('imu_node')


def test_a_snapshot_reads_one_set_of_reports():
    c = Counters()
    _report(c, 'imu_node', 1.0, received_imu=4, rejected_total=4, rejected_undecodable=4)
    reading = c.reading()
    _report(c, 'imu_node', 1.05, received_imu=5, rejected_total=5, rejected_undecodable=5)
    snap = reading.snapshot()
    assert (snap['received']['imu/data'], snap['rejected'],
            snap['by_reason']['imu_node.undecodable']) == (4.0, 4.0, 4.0)
    snap = c.snapshot()
    assert (snap['received']['imu/data'], snap['rejected']) == (5.0, 5.0)


def test_recovery_time():
    stamps = [i * 10**9 for i in range(10)]
    clean = {s: 2.0 for s in stamps}
    same = dict(clean)
    assert accounting.recovery_s(stamps, same, clean, stamps[3]) == 0.0
    late = {s: (50.0 if s <= stamps[6] else 2.1) for s in stamps}
    assert accounting.recovery_s(stamps, late, clean, stamps[3]) == 4.0
    never = {s: 50.0 for s in stamps}
    assert math.isinf(accounting.recovery_s(stamps, never, clean, stamps[3]))


def _set(msg, path, value):
    *parents, leaf = path.split('.')
    for p in parents:
        msg = getattr(msg, p)
    setattr(msg, leaf, value)


def _cov(msg, attr, index, value):
    cov = np.array(getattr(msg, attr), float)
    cov[index] = value
    setattr(msg, attr, cov)
    return msg


def test_plausibility_judgement_of_faulty_messages(stream):
    """The kit's own judgement (never the nodes' parsers): plausible changes are valid
    messages, values beyond the documented physics or structure are not."""
    tpl = stream.templates(stream.gnss_stamps[2] + 1000)

    def judged(topic, edit):
        msg = copy.deepcopy(tpl[topic])
        out = edit(msg)
        return plausible.judge(topic, tpl[topic], out if isinstance(out, bytes) else msg)

    def points(topic, dtype, edit):
        def change(msg):
            pts = cases.cloud_points(msg, dtype)
            edit(pts)
            return cases.with_points(msg, pts)
        return judged(topic, change)

    g, m = ma.GNSS_DTYPE, ma.MATCH_DTYPE
    assert judged('imu/data', lambda msg: None) == plausible.Judgement(True, 'unchanged')
    valid = [
        points('gnss/pseudoranges', g, lambda p: p['pseudorange'].__setitem__(0, 4.4e7)),
        points('gnss/measurements', g, lambda p: p['x'].__setitem__(
            0, flip_bit(p['x'][0], 52))),                   # x2 or /2: radius still fits
        judged('odom/twist', lambda msg: _set(msg, 'twist.twist.linear.x', 1e-150)),
        judged('imu/data', lambda msg: _set(msg, 'header.frame_id', 'imu_link')),
        judged('imu/data', lambda msg: _set(msg, 'orientation.x', 7.0)),   # REP 145: none
        judged('odometry/dead_reckoning', lambda msg: _set(
            msg, 'header.stamp.sec', msg.header.stamp.sec + 30)),
        judged('camera/image_raw', lambda msg: _set(msg, 'data', bytes(len(msg.data)))),
        points('camera/matches', m, lambda p: p['score'].__setitem__(0, 1.0))]
    assert all(j.valid for j in valid), valid
    malformed = [
        points('gnss/pseudoranges', g, lambda p: p['x'].__setitem__(0, 1e160)),
        points('gnss/pseudoranges', g, lambda p: p['variance'].__setitem__(0, -1.0)),
        points('gnss/measurements', g, lambda p: p['sv_id'].__setitem__(1, p['sv_id'][0])),
        points('gnss/measurements', g, lambda p: p['system'].__setitem__(0, 99)),
        judged('odom/twist', lambda msg: _cov(msg.twist, 'covariance', 0, -1.0)),
        judged('odom/twist', lambda msg: _cov(msg.twist, 'covariance', 1, 0.5)),
        judged('odom/twist', lambda msg: _set(msg, 'twist.twist.linear.y', 1e6)),
        judged('imu/data', lambda msg: _cov(msg, 'linear_acceleration_covariance', 0, -1.0)),
        judged('imu/data', lambda msg: _cov(_cov(msg, 'orientation_covariance', 0, 0.1),
                                            'orientation_covariance', 4, -1.0)),
        judged('camera/matches', lambda msg: _set(msg, 'header.frame_id', 'earth')),
        judged('odometry/dead_reckoning', lambda msg: _set(
            msg, 'pose.pose.orientation.z', 1e300)),
        judged('odometry/dead_reckoning', lambda msg: _set(msg, 'child_frame_id', 'imu')),
        judged('odometry/dead_reckoning', lambda msg: _set(
            msg, 'header.stamp.sec', msg.header.stamp.sec + 61)),
        judged('gnss/pseudoranges', lambda msg: _set(msg, 'header.stamp.nanosec', 2**32 - 1)),
        judged('camera/image_raw', lambda msg: _set(msg, 'height', msg.height + 1)),
        judged('imu/data', lambda msg: serialize_message(msg)[:-9])]
    assert not any(j.valid for j in malformed), malformed
    assert malformed[-1].why.startswith('undecodable')


def test_a_buffer_cut_short_is_judged_as_the_subscriber_receives_it(stream):
    """Fast DDS pads a payload to 4 bytes between processes: an IMU buffer cut by 1-3
    zero bytes arrives whole (the valid message), one cut by 4 or more does not decode."""
    imu = copy.deepcopy(stream.templates(stream.gnss_stamps[2] + 1000)['imu/data'])
    _cov(imu, 'linear_acceleration_covariance', 8, 0.0)     # the last 8 bytes are zeros
    raw = serialize_message(imu)
    assert len(raw) % plausible.PAYLOAD_ALIGNMENT == 0
    for cut in (1, 2, 3):
        assert plausible.judge('imu/data', imu, raw[:-cut]).why == 'unchanged'
    for cut in (4, 5, 9):
        assert plausible.judge('imu/data', imu, raw[:-cut]).why.startswith('undecodable')


@pytest.mark.parametrize('topic', INPUT_TOPICS)
def test_what_the_kit_judges_malformed_the_boundary_refuses(stream, topic):
    """Seeded random mutations: every one the kit judges malformed is refused by the
    parser of its topic (or outside the stamp window of the gate, or, from the receiver,
    has satellites gnss_node drops and counts); every one judged valid parses."""
    parse = {wire.GNSS: ma.pointcloud2_to_gnss_epoch,
             wire.GNSS_MEASUREMENTS: lambda msg: ma.pointcloud2_to_gnss_epoch(
                 msg, wire.EARTH_FRAME, checked=True),
             wire.MATCHES: ma.pointcloud2_to_matches, wire.IMU: ma.imu_to_sample,
             wire.TWIST: ma.twist_to_sample, wire.DEAD_RECKONING: ma.odometry_to_dead_reckoning,
             wire.IMAGE: ma.image_to_array}[topic]
    original = stream.templates(stream.gnss_stamps[2] + 1000)[topic]
    rng = np.random.default_rng(11)
    counts = {True: 0, False: 0}
    for _ in range(120):
        msg = mutate.mutate(original, rng)[0]
        judgement = plausible.judge(topic, original, msg)
        counts[judgement.valid] += 1
        try:
            if isinstance(msg, bytes):        # as delivered: padded to 4 bytes
                msg = deserialize_message(
                    msg + bytes(-len(msg) % plausible.PAYLOAD_ALIGNMENT), TOPIC_TYPES[topic])
            parsed = parse(msg)
        except Exception as err:        # noqa: BLE001 - undecodable or refused
            assert not judgement.valid, (judgement, err)
            continue
        jump = abs(ma.stamp_to_ns(msg.header.stamp) - ma.stamp_to_ns(original.header.stamp))
        dropped = topic == wire.GNSS and (
            not np.isin(parsed.system, wire.KNOWN_SYSTEMS).all()
            or bool(check_epoch(parsed).rejected))
        refused = jump > limits.STAMP_WINDOW_NS or dropped
        assert refused != judgement.valid, (judgement, msg)
    assert counts[True] and counts[False], counts


def test_ok_on_injected_epochs_is_scored_against_the_truth(stream):
    s = stream.gnss_stamps
    between = s[1] + (s[2] - s[1]) // 3
    truth = stream.truth_at(between)
    on_truth = stream.frame.enu_to_geodetic(truth)
    off = stream.frame.enu_to_geodetic(truth + np.array([40.0, 0.0, 0.0]))
    res = PassResult('faults', fixes={between: tuple(map(float, on_truth)),
                                      between + 1: tuple(map(float, off)),
                                      s[3]: tuple(map(float, on_truth))})
    ok = [Verdict(0.0, 0, stamp, 'updated', 5.0, 'ok') for stamp in
          (between, between + 1, between + 2, s[-1] + 10**12, s[3])]
    errors = injected_ok_errors(stream, res, ok)
    assert len(errors) == 4                      # s[3] is a valid epoch: not injected
    assert errors[0] < 0.01 and abs(errors[1] - 40.0) < 0.01
    assert errors[2:] == [None, None]            # no fix; a stamp after the drive


def test_verdict_line():
    line = verdict_line('x', [Target('a == 0', True, '0'), Target('b == 0', False, '3')])
    assert line.startswith('verdict x: FAIL (1 of 2 targets)') and 'b == 0: FAIL (3)' in line


def test_in_process_run_reports_a_traceback_and_the_exit_code(tmp_path):
    missing = tmp_path / 'nothing.npz'
    out = run_in_process('mapdb_query', ['--db', str(missing), str(tmp_path / 'q.jpg')])
    assert out.code == 3 and not out.traceback and str(missing) in out.stderr
    bad = run_in_process('eval_smartloc', ['--particles', 'many'])
    assert bad.code == 2
    f = tmp_path / 'f.txt'
    f.write_text('a')
    assert fingerprint(f) == fingerprint(f) and fingerprint(tmp_path / 'none') is None


# ====================================================================== samples
@pytest.mark.slow
@pytest.mark.ros
def test_messages_sample(tmp_path):
    cfg = MessagesConfig(seed=3, duration_s=16.0, warmup_s=4.0, tail_s=6.0, structured=40,
                         mutations=20, heavy=False, prestart=False, domain=ros_domain_id(),
                         work_dir=str(tmp_path))
    result = run_messages(cfg, log=lambda *a: None)
    clean, faults = result['passes']['clean'], result['passes']['faults']
    assert clean['crashes'] == 0 and clean['unanswered'] == 0
    # Under fault: nothing crashed, hung or stayed blocked, every malformed message was
    # refused or lost with a count, and the estimate came back before the drive ended.
    assert (faults['crashes'], faults['hangs'], faults['blocks']) == (0, 0, 0), \
        (result['crashes'], result['blocks'])
    assert result['uncounted'] == 0, [
        (k['kind'], k['uncounted']) for k in result['kinds'].values() if k['uncounted']]
    assert faults['answered'] > 0 and math.isfinite(result['recovery_s'])
    # The kit tried what it was asked to, on every topic, and measured.
    m = result['messages']
    assert m['structured'] >= 40 and m['mutations'] == 20
    tried = {t for t, row in result['by_topic'].items()
             if row['structured'] + row['mutations']}
    assert len(tried) >= 5
    for figures in (clean, faults):
        assert figures['rss_end_mb'] > 50 and figures['rss_peak_mb'] >= figures['rss_end_mb']
    assert sum(row['refused'] for row in result['by_topic'].values()) > 0     # counted
    targets = {t['name']: t for t in result['targets']}
    assert len(targets) == 10
    assert targets['misleading OK == 0']['passed'], targets['misleading OK == 0']


@pytest.mark.slow
@pytest.mark.ros
def test_processes_sample(tmp_path):
    # At 2x real time: at 5x a loaded machine's nodes fall behind the replay and the
    # filter never settles, so no OK verdict would show that the check below can bite.
    # The heading acquisition keeps its default set: with 1000 particles it left the cloud
    # 4-10 m off in places, the consistency test flagged it for the rest of the drive, and
    # whether an OK verdict came at all depended on where the kill's timing restarted the
    # filter (none in one CI run; offline: none from a start at 20 s or 30 s of this drive,
    # OK within 20 s from every start with the default set).
    cfg = ProcessesConfig(seed=2, duration_s=90.0, rate=2.0, warmup_s=10.0, gap_s=2.0,
                          down_s=2.0, nodes=['imu_node', 'fusion_node'], camera=False,
                          particles=300, domain=ros_domain_id(), work_dir=str(tmp_path))
    result = run_processes(cfg, log=lambda *a: None)
    assert [k['node'] for k in result['kills']] == ['imu_node', 'fusion_node']
    for kill in result['kills']:
        # Killed, restarted and the graph answering again before the drive ended; how fast
        # is the campaign's figure, not a test's (a restarted node's imports take seconds
        # on a loaded machine).
        assert kill['exit_status'] == -9, kill
        assert kill['not_killed'] is None and math.isfinite(kill['recovery_s']), kill
    targets = {t['name'].split(' (')[0]: t['passed'] for t in result['targets']}
    assert targets['integrity OK while a needed input is missing or reset == 0']
    assert targets['OK verdicts outside the windows']        # the check above bites
    assert targets['other nodes exited meanwhile == 0']
    assert targets['every node exits 0 when stopped'], result['exit_codes_at_stop']


@pytest.mark.slow
@pytest.mark.ros
def test_files_sample(tmp_path, monkeypatch):
    monkeypatch.setenv('ROS_LOG_DIR', str(tmp_path / 'ros_log'))
    result = run_files(FilesConfig(seed=1, per_tool=5, domain=ros_domain_id(),
                                   work_dir=str(tmp_path)), log=lambda *a: None)
    per_tool = result['per_tool']
    assert set(per_tool) == set(GENERATORS)
    assert all(t['cases'] == 5 and t['kit_errors'] == 0 for t in per_tool.values())
    assert per_tool['eval_bag']['ok'] == 5


@pytest.mark.slow
@pytest.mark.ros
def test_files_mcap_storage_named_db3_is_a_valid_bag(tmp_path, monkeypatch):
    """A bag whose MCAP file is named ``.db3`` (metadata still saying ``mcap``) is valid:
    the replay plays every message of the original bag and exits 0, and the kit expects
    just that (it expected a refusal before)."""
    monkeypatch.setenv('ROS_LOG_DIR', str(tmp_path / 'ros_log'))
    corpus = build_corpus(tmp_path, seed=1)
    folder = tmp_path / 'case'
    folder.mkdir()
    case = replay_case(BAG_VARIANTS.index('mcap_named_db3'), np.random.default_rng(1),
                       corpus, folder)
    assert [p.suffix for p in (folder / 'bag').iterdir() if p.name != 'metadata.yaml'] \
        == ['.db3']
    result = run_case(FilesConfig(domain=ros_domain_id()), case, folder)
    assert result.code == 0 and result.problems == [], (result.problems,
                                                        result.stderr_tail)
