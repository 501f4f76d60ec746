"""Protection-level evaluation: metric known answers, the per-epoch CSV (one row per GNSS
epoch), ``--plots``, the campaign's ``config`` and PL block, and the PL of a recorded bag."""
import csv
import dataclasses
import json
import math

import numpy as np
import pytest
from conftest import SMARTLOC_EXCERPT

from gnsscam_ros.core.filter import FilterConfig
from gnsscam_ros.datasets.emulated.drive import make_emulated_drive
from gnsscam_ros.evaluation import cli
from gnsscam_ros.evaluation.metrics import (cloud_calibration, level_sizing, nees,
                                            percentile_with_inf, protection_level_metrics)
from gnsscam_ros.io.atomic import write_json_atomic
from gnsscam_ros.evaluation.runner import EpochTable, run_filter, summarize

REQUIRED = ['stamp_ns', 'lat_deg', 'lon_deg', 'height_m', 'protection_level_m', 'risk_bound',
            'integrity']


# ---------------------------------------------------------------------------- metrics
def test_protection_level_metrics_known_answer():
    err = np.array([1.0, 5.0, 20.0, 3.0, 9.0])
    pl = np.array([2.0, 4.0, 10.0, np.inf, np.nan])    # NaN = no PL, counted as inf
    ok = np.array([True, True, False, False, False])
    m = protection_level_metrics(err, pl, 8.0, integrity_ok=ok)
    assert m['epochs'] == 5
    assert (m['mi_epochs'], m['mi_rate']) == (2, 0.4)     # 5 > 4 and 20 > 10; inf never MI
    assert m['no_pl_epochs'] == 2
    assert m['availability'] == {'8': 0.4, '16': 0.6, '25': 0.6, '50': 0.6}
    assert m['available_epochs'] == {'8': 2, '16': 3, '25': 3, '50': 3}
    # PL <= 16 for epochs 0, 1, 2; only epoch 2 (error 20) exceeds 16.
    assert m['hmi_given_available']['16'] == {'rate': 1 / 3, 'hmi_epochs': 1,
                                              'available_epochs': 3}
    assert m['hmi_given_available']['8']['rate'] == 0.0
    assert m['median_m'] == 10.0                       # sorted 2, 4, 10, inf, inf
    assert m['p95_m'] == math.inf
    assert m['flag_ok'] == {'ok_epochs': 2, 'error_above_al_epochs': 0,
                            'error_above_al_rate': 0.0}
    st = m['stanford']
    assert (st['nominal'], st['mi'], st['hmi'], st['unavailable'], st['unavailable_mi'],
            st['no_pl']) == (1, 1, 0, 2, 1, 2)
    assert sum(st[k] for k in ('nominal', 'mi', 'hmi', 'unavailable',
                               'unavailable_mi')) == 5
    # The configured limit is always among the availability limits.
    assert '12' in protection_level_metrics(err, pl, 12.0)['availability']
    # No epochs: rates None, no crash.
    empty = protection_level_metrics(np.zeros(0), np.zeros(0), 8.0)
    assert empty['mi_rate'] is None and empty['median_m'] is None
    with pytest.raises(ValueError):
        protection_level_metrics(np.ones(2), np.ones(3), 8.0)


def test_cloud_calibration_known_answers():
    rng = np.random.default_rng(4)
    # Correlated 2D errors drawn from the covariance reported with them: calibrated.
    cov = np.array([[4.0, 1.5], [1.5, 2.0]])
    err = rng.multivariate_normal(np.zeros(2), cov, size=20_000)
    covs = np.broadcast_to(cov, (err.shape[0], 2, 2))
    values = nees(err, covs)
    assert values.mean() == pytest.approx(2.0, rel=0.03)          # chi-square, 2 dof
    calibrated = cloud_calibration(values, 2)
    assert calibrated['calibrated_median_nees'] == pytest.approx(2.0 * math.log(2.0))
    assert calibrated['spread_to_error'] == pytest.approx(1.0, abs=0.03)
    # A cloud reported twice as wide as its errors (four times the covariance).
    assert cloud_calibration(nees(err, 4.0 * covs), 2)['spread_to_error'] == pytest.approx(
        2.0, rel=0.03)
    # 3D, overconfident by a factor 2 in spread.
    err3 = rng.normal(scale=2.0, size=(20_000, 3))
    wide = cloud_calibration(nees(err3, np.broadcast_to(np.eye(3), (20_000, 3, 3))), 3)
    assert wide['calibrated_median_nees'] == pytest.approx(2.366, abs=1e-3)
    assert wide['spread_to_error'] == pytest.approx(0.5, rel=0.03)
    # Covariances that are not finite or not positive definite are left out, not scored.
    bad = np.stack([np.eye(2), np.full((2, 2), np.nan), np.zeros((2, 2)),
                    np.array([[1.0, 2.0], [2.0, 1.0]])])
    values = nees(np.ones((4, 2)), bad)
    assert values[0] == pytest.approx(2.0) and np.isnan(values[1:]).all()
    assert cloud_calibration(values, 2)['epochs'] == 1
    assert cloud_calibration(np.zeros(0), 2)['spread_to_error'] is None


def test_level_sizing_known_answers():
    rng = np.random.default_rng(5)
    miss = 0.0288
    # 2D Gaussian errors whose spread changes from epoch to epoch, and a level five times
    # each epoch's standard deviation: the level that misses ``miss`` of the epochs is
    # sqrt(-2 ln miss) standard deviations (Rayleigh), so the scale is that over five.
    sd = np.exp(rng.normal(scale=0.5, size=200_000))
    err = sd * np.hypot(*rng.normal(size=(2, sd.size)))
    sized = level_sizing(err, 5.0 * sd, miss)
    rayleigh = math.sqrt(-2.0 * math.log(miss))
    assert sized['epochs'] == sd.size and sized['miss_share'] == miss
    assert sized['scale'] == pytest.approx(rayleigh / 5.0, rel=0.01)
    assert np.mean(err > sized['scale'] * 5.0 * sd) <= miss
    assert sized['pl_to_error'] == pytest.approx(
        5.0 * np.median(sd) / np.median(err), rel=1e-12)
    # One spread for all: the sized level over the median error is the Rayleigh quantile
    # over its median, the floor docs/robustness.md gives for a calibrated cloud (2.26).
    flat = level_sizing(err / sd, np.full(sd.size, 3.0), miss)
    assert flat['pl_to_error_sized'] == pytest.approx(
        rayleigh / math.sqrt(2.0 * math.log(2.0)), rel=0.01)
    # Epochs without a finite level are left out; none left: nothing to say.
    part = level_sizing(np.array([1.0, 2.0, 3.0, 50.0]),
                        np.array([2.0, 2.0, 2.0, np.inf]), 0.0)
    assert part['epochs'] == 3 and part['scale'] == pytest.approx(1.5)
    empty = level_sizing(np.array([1.0]), np.array([np.inf]), miss)
    assert empty['epochs'] == 0 and empty['scale'] is None
    with pytest.raises(ValueError, match='differ in length'):
        level_sizing(np.ones(3), np.ones(2), miss)


def test_percentile_with_inf():
    assert percentile_with_inf([1.0, 3.0], 50) == 2.0
    assert percentile_with_inf([1.0, 3.0, np.inf], 50) == 3.0
    assert percentile_with_inf([1.0, np.inf], 50) == math.inf
    assert percentile_with_inf([np.inf], 0) == math.inf
    np.testing.assert_allclose(percentile_with_inf(np.arange(11.0), 95),
                               np.percentile(np.arange(11.0), 95))


def test_json_writes_inf_as_a_string(tmp_path):
    path = write_json_atomic(tmp_path / 'x.json', {'a': math.inf, 'b': np.array([1.0,
                                                                                -np.inf])})
    assert json.loads(path.read_text()) == {'a': 'inf', 'b': [1.0, '-inf']}
    with pytest.raises(ValueError):
        write_json_atomic(tmp_path / 'y.json', {'a': math.nan})


# ---------------------------------------------------------------------------- epochs
@pytest.mark.slow
def test_epoch_table_has_every_gnss_epoch_stale_ones_without_pl():
    drive = make_emulated_drive(2, faults=2, duration_s=20)
    # Two satellites only: the epoch cannot be an update.
    gnss = list(drive.gnss)
    gnss[8] = gnss[8].subset(np.arange(gnss[8].pr_m.size) < 2)
    drive = dataclasses.replace(drive, gnss=gnss)
    config = FilterConfig(n_particles=200)
    record = run_filter(drive, config, seed=1)
    table = record.epochs
    assert len(table) == len(drive.gnss)
    np.testing.assert_array_equal(table.stamp_ns, [e.stamp_ns for e in drive.gnss])
    assert table.integrity[8] == 'STALE' and table.status[8] != 'updated'
    assert np.isnan(table.protection_level_m[8]) and np.isnan(table.risk_bound[8])
    updated = table.status == 'updated'
    assert set(table.integrity[updated]) <= {'OK', 'ERROR'}
    assert np.all(~np.isnan(table.protection_level_m[updated]))
    # The updated rows are the record's epochs, with the same PL and errors.
    np.testing.assert_array_equal(table.stamp_ns[updated], record.stamp_ns)
    np.testing.assert_array_equal(table.protection_level_m[updated],
                                  record.protection_level_m)
    np.testing.assert_array_equal(table.integrity[updated] == 'OK', record.integrity_ok)
    err = np.hypot(*(record.estimate_enu_m - record.truth_enu_m)[:, :2].T)
    np.testing.assert_allclose(table.horizontal_error_m[updated], err, atol=1e-9)
    # WGS84 estimate back in the map frame is the estimate.
    from gnsscam_ros.core.frames import LocalFrame
    frame = LocalFrame(*drive.origin_llh)
    back = frame.geodetic_to_enu(table.lat_deg[updated], table.lon_deg[updated],
                                 table.height_m[updated])
    np.testing.assert_allclose(back, record.estimate_enu_m, atol=1e-6)
    out = summarize(record, config)
    assert out['protection_level']['epochs'] == int(updated.sum())
    assert out['protection_level']['flag_ok']['ok_epochs'] == int(record.integrity_ok.sum())


def _read_csv(path):
    with open(path, newline='', encoding='utf-8') as handle:
        return list(csv.DictReader(handle))


@pytest.mark.slow
def test_cli_emulated_epochs_csv_and_plots(tmp_path, capsys):
    csv_path, plots, out = tmp_path / 'e.csv', tmp_path / 'plots', tmp_path / 'e.json'
    args = ['emulated', '--seed', '2', '--faults', '2', '--duration-s', '25', '--n-particles',
            '200', '--quiet', '--epochs-csv', str(csv_path), '--plots', str(plots),
            '--json', str(out)]
    assert cli.main(args) == 0
    printed = capsys.readouterr().out
    assert 'MI rate' in printed and 'Stanford at AL 8 m' in printed
    result = json.loads(out.read_text())
    # Every updated epoch reports its covariance: the calibration is over all of them.
    calibration = result['cloud_calibration']
    assert calibration['epochs'] == result['protection_level']['epochs'] > 0
    assert f"reported spread / error {calibration['spread_to_error']:.2f}" in printed
    rows = _read_csv(csv_path)
    assert list(rows[0])[:len(REQUIRED)] == REQUIRED
    assert len(rows) == result['dataset']['gnss_epochs'] == result['epochs_csv']['rows']
    assert {r['integrity'] for r in rows} <= {'OK', 'ERROR', 'STALE'}
    for r in rows:
        assert (r['protection_level_m'] == '') == (r['integrity'] == 'STALE')
    assert abs(float(rows[0]['lat_deg']) - 50.11) < 0.05
    pl = result['protection_level']
    assert set(pl['availability']) == {'8', '16', '25', '50'}
    for key in ('mi_rate', 'mi_epochs', 'epochs', 'median_m', 'p95_m', 'stanford',
                'hmi_given_available', 'flag_ok'):
        assert key in pl
    assert sorted(p.name for p in plots.iterdir()) == [
        'error_pl_emulated-urban-s2-f2.png', 'stanford_emulated-urban-s2-f2.png']
    assert all(p.stat().st_size > 10_000 for p in plots.iterdir())
    # The CSV is never overwritten without --force.
    before = csv_path.read_text()
    args_again = [a for a in args if a not in ('--json', str(out))]
    assert cli.main(args_again) == cli.EXIT_OUTPUT
    assert csv_path.read_text() == before


@pytest.mark.slow
def test_cli_smartloc_excerpt_csv_stamps_are_the_files_seconds(tmp_path, smartloc_excerpt):
    csv_path = tmp_path / 's.csv'
    assert cli.main(['smartloc', str(SMARTLOC_EXCERPT), '--quiet', '--n-particles', '200',
                     '--epochs-csv', str(csv_path)]) == 0
    rows = _read_csv(csv_path)
    assert len(rows) == len(smartloc_excerpt.gnss)
    assert [int(r['stamp_ns']) for r in rows] == [e.stamp_ns for e in smartloc_excerpt.gnss]
    # The first stamp is the file's first pseudorange time in seconds x 1e9.
    first = next(line for line in next(SMARTLOC_EXCERPT.glob('*_Input.txt')).open()
                 if line.startswith('pseudorange3'))
    assert int(rows[0]['stamp_ns']) == int(round(float(first.split()[1]) * 1e9))
    lat = np.array([float(r['lat_deg']) for r in rows if r['lat_deg']])
    assert lat.size and np.all(np.abs(lat - 52.5) < 0.2)          # Berlin


# ---------------------------------------------------------------------------- campaign
@pytest.mark.slow
def test_campaign_records_config_pl_and_writes_plots_and_csvs(tmp_path):
    from gnsscam_ros.evaluation.campaign import campaign_config
    from gnsscam_ros.evaluation.campaign_run import run_campaign
    from gnsscam_ros.evaluation.campaign_summary import campaign_tables
    result = run_campaign(seeds=(1,), base=campaign_config(n_particles=200),
                          methods=('gnss_robust',), cases=[(0, 0.0)], sequential=True,
                          plots_dir=tmp_path / 'plots', progress=False,
                          epochs_dir=tmp_path / 'epochs', duration_s=15)
    assert result['config']['inverse_bernoulli'] == 'exact'
    assert result['config']['inverse_bernoulli'] == FilterConfig().inverse_bernoulli
    assert result['config']['n_posteriors'] == FilterConfig().n_posteriors
    assert result['method_configs']['gnss_robust']['use_camera'] is False
    case = result['cases'][0]
    assert case['protection_level']['epochs'] == case['epochs']
    assert set(case['protection_level']['availability']) == {'8', '16', '25', '50'}
    rows = _read_csv(case['epochs_csv'])
    assert len(rows) == case['gnss_epochs']
    names = {p.name for p in (tmp_path / 'plots').iterdir()}
    assert {'stanford_gnss_robust_al8.png', 'error_pl_nlos_gnss_robust.png',
            'intervals_gnss_robust_al8.png'} <= names
    assert 'Protection level' in campaign_tables(result['cases'])
    write_json_atomic(tmp_path / 'c.json', result)          # JSON-ready (inf included)


# ---------------------------------------------------------------------------- bags
def _write_result_bag(path, record, frame, stale_stamps):
    """integrity_risk (with the PL) and fix as fusion_node publishes them."""
    from rclpy.serialization import serialize_message
    from rosbags.rosbag2 import StoragePlugin, Writer

    from gnsscam_ros.bags import schema
    from gnsscam_ros.core.verdict import ERROR, OK, STALE, IntegrityVerdict
    from msg_adapters import GeodeticFix, fix_to_navsatfix, integrity_risk_to_msg
    store = schema.typestore()
    bounds = record.risk_bound['exact']
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        ci = w.add_connection('/integrity_risk', schema.DIAGNOSTIC_ARRAY, typestore=store)
        cf = w.add_connection('/fix', schema.NAVSATFIX, typestore=store)
        items = [(int(s), k) for k, s in enumerate(record.stamp_ns)]
        items += [(int(s), None) for s in stale_stamps]
        for s, k in sorted(items):
            if k is None:
                w.write(ci, s, serialize_message(integrity_risk_to_msg(IntegrityVerdict(
                    stamp_ns=s, level=STALE, message='no valid solution', alert_limit_m=8.0,
                    target_risk=0.1, epoch_stamp_ns=s))))
                continue
            ok = bool(record.integrity_ok[k])
            w.write(ci, s, serialize_message(integrity_risk_to_msg(IntegrityVerdict(
                stamp_ns=s, level=OK if ok else ERROR, message='', risk_bound=float(
                    bounds[k, 0]), empirical_risk=0.0, divergence_risk=0.0,
                alert_limit_m=8.0, target_risk=0.1, epoch_stamp_ns=s,
                protection_level_m=float(record.protection_level_m[k]),
                details={'inverse_bernoulli': 'exact'}, epoch_status='updated'))))
            lat, lon, alt = frame.enu_to_geodetic(record.estimate_enu_m[k])
            w.write(cf, s, serialize_message(fix_to_navsatfix(GeodeticFix(
                stamp_ns=s, lat_deg=float(lat), lon_deg=float(lon), alt_m=float(alt),
                covariance_enu_m2=np.diag([4.0, 4.0, 9.0])))))


def _pl_figures_by_definition(err, pl, alert_limit_m, ok) -> dict:
    """The protection-level figures of the module docstring of evaluation.metrics, counted
    here from their definitions (no PL = inf; percentiles by linear interpolation, inf as
    soon as an inf takes part)."""
    pl = np.where(np.isnan(pl), np.inf, pl)
    ranked = np.sort(pl)

    def percentile(q):
        pos = q / 100 * (len(ranked) - 1)
        lo, hi = ranked[math.floor(pos)], ranked[math.ceil(pos)]
        return math.inf if math.isinf(hi) else lo + (hi - lo) * (pos - math.floor(pos))

    available, bounded, within = pl <= alert_limit_m, err <= pl, err <= alert_limit_m
    return {
        'mi_epochs': int(np.sum(err > pl)),
        'availability': {f'{a:g}': float(np.mean(pl <= a)) for a in (8.0, 16.0, 25.0, 50.0)},
        'median_m': percentile(50), 'p95_m': percentile(95),
        'stanford': {'epochs': len(err), 'nominal': int(np.sum(available & bounded)),
                     'mi': int(np.sum(available & ~bounded & within)),
                     'hmi': int(np.sum(available & ~within)),
                     'unavailable': int(np.sum(~available & bounded)),
                     'unavailable_mi': int(np.sum(~available & ~bounded)),
                     'no_pl': int(np.sum(np.isinf(pl)))},
        'flag_ok': {'ok_epochs': int(ok.sum()),
                    'error_above_al_epochs': int(np.sum(ok & (err > alert_limit_m))),
                    'error_above_al_rate': (float(np.sum(ok & (err > alert_limit_m)))
                                            / ok.sum() if ok.any() else None)},
    }


@pytest.mark.ros
@pytest.mark.slow
def test_bag_eval_takes_the_pl_from_integrity_risk(tmp_path):
    from gnsscam_ros.bags.convert import convert_drive
    from gnsscam_ros.core.frames import LocalFrame
    from gnsscam_ros.evaluation.bag_eval import evaluate_result_bag_epochs

    drive = make_emulated_drive(2, faults=2, duration_s=15)
    config = FilterConfig(n_particles=200)
    record = run_filter(drive, config, seed=1)
    offline = summarize(record, config)
    frame = LocalFrame(*drive.origin_llh)
    convert_drive(drive, tmp_path / 'dataset')
    # Pretend the last two epochs were not updated (STALE verdicts of their own).
    keep = slice(0, len(record.stamp_ns) - 2)
    stale = record.stamp_ns[keep.stop:]
    cut = dataclasses.replace(record, stamp_ns=record.stamp_ns[keep],
                              estimate_enu_m=record.estimate_enu_m[keep],
                              protection_level_m=record.protection_level_m[keep],
                              integrity_ok=record.integrity_ok[keep],
                              risk_bound={'exact': record.risk_bound['exact'][keep]})
    _write_result_bag(tmp_path / 'res', cut, frame, stale)
    out, table = evaluate_result_bag_epochs(tmp_path / 'res', tmp_path / 'dataset')
    pl = out['protection_level']
    n = keep.stop
    assert pl['epochs'] == n
    err = np.hypot(*(record.estimate_enu_m - record.truth_enu_m)[:n, :2].T)
    want = _pl_figures_by_definition(err, record.protection_level_m[:n], 8.0,
                                     record.integrity_ok[:n])
    for key in want:
        got, exp = pl[key], want[key]
        if isinstance(exp, float):
            assert got == pytest.approx(exp, rel=1e-6), key      # float32 on the wire
        else:
            assert got == exp, key
    assert offline['protection_level']['epochs'] == len(record.stamp_ns)
    # One row per GNSS epoch of the dataset bag; the stale ones without a PL.
    assert isinstance(table, EpochTable) and len(table) == len(drive.gnss)
    assert list(table.integrity[-2:]) == ['STALE', 'STALE']
    assert np.all(np.isnan(table.protection_level_m[-2:]))
    np.testing.assert_allclose(table.protection_level_m[:n], record.protection_level_m[:n],
                               rtol=1e-6)
    # The CLI writes the CSV and the plots of the bag.
    csv_path, plots = tmp_path / 'b.csv', tmp_path / 'plots'
    assert cli.main(['bag', str(tmp_path / 'res'), '--truth', str(tmp_path / 'dataset'),
                     '--quiet', '--epochs-csv', str(csv_path), '--plots', str(plots)]) == 0
    rows = _read_csv(csv_path)
    assert len(rows) == len(drive.gnss) and rows[-1]['integrity'] == 'STALE'
    assert {p.name for p in plots.iterdir()} == {'stanford_res.png', 'error_pl_res.png'}
