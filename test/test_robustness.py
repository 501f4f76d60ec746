"""``gnsscam_eval robustness``: the matrix's cells change the data as documented, a cell's
figures follow from its runs, and the command runs end to end on a 1-worker cluster
(the same runs as in-process) with its JSON, figure and exit codes.

Short cuts of the smartLoc excerpt (15 s) and 2 seeds keep this to seconds; the full
matrix on the Berlin file is run by hand (``gnsscam_eval robustness FOLDER``).
"""
import json

import numpy as np
import pytest
from conftest import SMARTLOC_EXCERPT

from gnsscam_ros.datasets.errors import DatasetError
from gnsscam_ros.evaluation import cli, robustness, robustness_cli
from gnsscam_ros.evaluation.campaign import campaign_config
from gnsscam_ros.evaluation.cli import main as eval_main
from gnsscam_ros.evaluation.robustness import (DEFAULT_CELLS, TARGETS, cell_drive,
                                               run_robustness, select_cells, summarize_cell)

#: Fields every cell of the JSON has.
CELL_FIELDS = ('name', 'description', 'variation', 'same_data_as', 'data', 'seeds',
               'mi_rate', 'rmse_2d_m', 'wls_rmse_2d_m', 'rmse_ratio_to_wls',
               'protection_level', 'median_error_m', 'pl_to_error_ratio',
               'cloud_calibration', 'recoveries', 'targets', 'pass', 'runs')


def test_every_cell_of_the_matrix_changes_the_data_as_it_says(smartloc_excerpt):
    drive = smartloc_excerpt
    made = {c.name: cell_drive(drive, c, duration_s=30.0) for c in DEFAULT_CELLS
            if c.name not in ('start_60s', 'start_120s')}
    base = made['baseline']
    assert (base.gnss[-1].stamp_ns - base.gnss[0].stamp_ns) / 1e9 <= 30.0
    var = np.concatenate([e.var_m2 for e in base.gnss])

    def variances(name):
        return np.concatenate([e.var_m2 for e in made[name].gnss])

    for f in (0.25, 0.5, 2.0, 4.0):
        np.testing.assert_allclose(variances(f'var_x{f:g}'), var * f)
    for v in (25.0, 4.0):
        assert np.all(variances(f'var_{v:g}m2') == v)
    for rate in (1.0, 2.0):
        kept = made[f'gnss_{rate:g}hz']
        assert len(kept.gnss) == pytest.approx(len(base.gnss) * rate / 4.85, rel=0.15)
        assert len(kept.odometry) == len(base.odometry)
    assert all(np.all(e.system == 1) for e in made['gps_only'].gnss)
    assert all(np.all(e.system == 4) and e.n_sv >= 5 for e in made['glonass_only'].gnss)
    for s in (60.0, 120.0):
        # The 60 s excerpt ends before: a late start is refused where it has no data.
        with pytest.raises(DatasetError, match='leaves no GNSS epoch'):
            cell_drive(drive, robustness.CELLS_BY_NAME[f'start_{s:g}s'])
    late = cell_drive(drive, robustness.Cell('start_20s', 'start', 20.0, ''), 30.0)
    assert late.gnss[0].stamp_ns - drive.gnss[0].stamp_ns >= 20e9
    # The truth is kept over what is scored (the duration cut trims it to that span).
    assert late.truth.stamp_ns[0] < drive.gnss[0].stamp_ns + 20e9
    assert late.truth.stamp_ns[-1] >= late.gnss[-1].stamp_ns
    for name in ('fault_step', 'fault_ramp'):
        faults = made[name].info['injected_faults']
        assert len(faults) == 1 and made[name].info['faulty_measurements'] > 0
        assert 1 <= len(faults[0]['satellites']) <= 2
        assert all(30.0 <= abs(b) <= 100.0 for b in faults[0]['bias_m'])
        assert 20.0 <= faults[0]['duration_s'] <= 60.0
    digests = {n: robustness.drive_digest(d) for n, d in made.items()}
    # The file is at 5 Hz and starts at 0 s: those two cells are the baseline's data.
    assert digests['gnss_5hz'] == digests['start_0s'] == digests['baseline']
    others = [d for n, d in digests.items() if n not in ('gnss_5hz', 'start_0s')]
    assert len(set(others)) == len(others)


def run(seed, mi, n, rmse, wls=20.0, recoveries=None, err=None, pl=None, nees=None):
    err = np.full(n, 5.0) if err is None else np.asarray(err, float)
    pl = np.full(n, 12.0) if pl is None else np.asarray(pl, float)
    nees = np.full(n, 2.0) if nees is None else np.asarray(nees, float)
    return {'seed': seed, 'mi_epochs': mi, 'epochs': n, 'rmse_2d_m': rmse,
            'wls_rmse_2d_m': wls, 'wls_epochs': n, 'recoveries': recoveries,
            'statuses': {}, 'filter_seconds': 1.0, 'error_m': err, 'protection_level_m': pl,
            'nees': nees, 'nees_dims': 2}


def test_cell_figures_follow_from_the_runs():
    runs = [run(s, mi, 200, rmse) for s, mi, rmse in ((0, 4, 8.0), (1, 10, 10.0),
                                                      (2, 6, 9.0))]
    cell = summarize_cell(runs)
    assert cell['mi_rate']['mean'] == pytest.approx(20 / 600)
    lo, hi = cell['mi_rate']['ci95']
    assert lo <= cell['mi_rate']['mean'] <= hi == cell['mi_rate']['upper']
    assert cell['rmse_2d_m']['mean'] == pytest.approx(9.0)
    assert cell['rmse_ratio_to_wls'] == pytest.approx(9.0 / 20.0)
    assert cell['protection_level']['median_m'] == 12.0
    assert cell['pl_to_error_ratio'] == pytest.approx(12.0 / 5.0)
    assert cell['recoveries'] == {'total': 0, 'reported': False, 'per_run': [0, 0, 0]}
    # NEES pooled over the seeds: 2.0 everywhere against the 2D chi-square median.
    assert cell['cloud_calibration']['epochs'] == 600
    assert cell['cloud_calibration']['spread_to_error'] == pytest.approx(
        np.sqrt(2.0 * np.log(2.0) / 2.0))
    assert all('nees' not in r for r in cell['runs'])
    # The level's size against its shape, when the bound's miss share is given: every
    # error is 5/12 of its level, so the level scaled to miss nothing is the error itself.
    assert 'level_sizing' not in cell
    sized = summarize_cell(runs, 0.03)['level_sizing']
    assert sized['epochs'] == 600 and sized['scale'] == pytest.approx(5.0 / 12.0)
    assert sized['pl_to_error_sized'] == pytest.approx(1.0)
    assert all(t['pass'] for t in cell['targets'].values()) and cell['pass']
    # Each target fails on its own.
    assert not summarize_cell([run(0, 60, 200, 8.0), run(1, 70, 200, 8.0)])['targets'][
        'mi_mean']['pass']
    assert not summarize_cell([run(0, 4, 200, 12.0), run(1, 4, 200, 12.0)])['targets'][
        'rmse_ratio_to_wls']['pass']
    wide = summarize_cell([run(0, 4, 200, 8.0, pl=np.full(200, 16.0)),
                           run(1, 4, 200, 8.0, pl=np.full(200, np.inf))])
    assert wide['protection_level']['median_m'] == float('inf')
    assert not wide['targets']['pl_to_error_ratio']['pass'] and not wide['pass']
    # One seed with every epoch MI, one with none: the mean passes, its upper bound not.
    split = summarize_cell([run(0, 0, 200, 8.0), run(1, 30, 200, 8.0)])
    assert split['targets']['mi_mean']['pass'] and not split['targets']['mi_upper']['pass']
    assert set(TARGETS) == set(cell['targets'])


def test_recoveries_are_read_from_the_evaluation(smartloc_excerpt, monkeypatch):
    cells = select_cells(['baseline'])
    config = campaign_config(n_particles=200)
    evaluate = robustness.evaluate_drive_record

    def run_with(recoveries):
        def patched(drive, cfg, seed=0, progress=False):
            result, record = evaluate(drive, cfg, seed, progress)
            assert result['recoveries'] == record.recoveries >= 0   # what the runner says
            result = {k: v for k, v in result.items() if k != 'recoveries'}
            if recoveries is not None:
                result['recoveries'] = recoveries(seed)
            return result, record

        monkeypatch.setattr(robustness, 'evaluate_drive_record', patched)
        out = run_robustness(smartloc_excerpt, cells, [0, 1], config, duration_s=8.0,
                             sequential=True, progress=False)
        return out['cells'][0]['recoveries']

    assert run_with(lambda seed: seed + 1) == {'total': 3, 'reported': True,
                                               'per_run': [1, 2]}
    # An evaluation without the count: the field is there, 0, and says so.
    assert run_with(None) == {'total': 0, 'reported': False, 'per_run': [0, 0]}


@pytest.mark.slow
def test_command_end_to_end_on_a_one_worker_cluster(tmp_path, capsys):
    out_json, figure = tmp_path / 'rob.json', tmp_path / 'rob.png'
    common = ['--seeds', '2', '--duration-s', '15', '--n-particles', '300', '--quiet']
    args = ['robustness', str(SMARTLOC_EXCERPT), '--cells', 'baseline', 'var_x4',
            'glonass_only', 'start_0s', *common]
    assert eval_main(args + ['--workers', '1', '--json', str(out_json),
                             '--figure', str(figure)]) == 0
    text = capsys.readouterr().out
    assert 'MI rate [95 % CI]' in text and 'start_0s (= baseline)' in text
    result = json.loads(out_json.read_text())
    assert result['cluster']['kind'] == 'embedded' and result['cluster']['workers'] == 1
    assert result['command_line'].startswith('gnsscam_eval robustness ')
    assert result['date'] and result['machine']['cpus'] >= 1
    assert result['config']['n_particles'] == 300 and result['seeds'] == [0, 1]
    assert [c['name'] for c in result['cells']] == ['baseline', 'var_x4', 'glonass_only',
                                                    'start_0s']
    assert result['runs_computed'] == 6 and not result['failed']     # start_0s not rerun
    for c in result['cells']:
        assert all(f in c for f in CELL_FIELDS), c['name']
        mi = c['mi_rate']
        assert mi['ci95'][0] <= mi['mean'] <= mi['ci95'][1] == mi['upper']
        lo, hi = c['rmse_2d_m']['ci95']
        assert lo <= c['rmse_2d_m']['mean'] <= hi
        assert c['rmse_ratio_to_wls'] == pytest.approx(c['rmse_2d_m']['mean']
                                                       / c['wls_rmse_2d_m'])
        assert c['seeds'] == [0, 1] and len(c['runs']) == 2
        assert c['pass'] == all(t['pass'] for t in c['targets'].values())
        assert set(c['recoveries']) == {'total', 'reported', 'per_run'}
    base, var4, glo, start0 = result['cells']
    assert var4['data']['digest'] != base['data']['digest']
    assert var4['data']['variants'] == [{'kind': 'scale_variances', 'factor': 4.0}]
    # The runs saw the changed data: GLONASS alone gives other figures than the file. (A
    # filter that learns its error model may well be blind to a common variance scale.)
    assert [r['rmse_2d_m'] for r in glo['runs']] != [r['rmse_2d_m'] for r in base['runs']]
    assert var4['wls_rmse_2d_m'] > 0 and len(var4['runs']) == 2
    kept = glo['data']['variants'][0]
    assert kept['epochs_kept'] == glo['data']['gnss_epochs'] <= base['data']['gnss_epochs']
    assert start0['same_data_as'] == 'baseline' and start0['runs'] == base['runs']
    assert figure.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
    # In this process: the same runs as on the cluster.
    again = tmp_path / 'seq.json'
    assert eval_main(['robustness', str(SMARTLOC_EXCERPT), '--cells', 'var_x4', *common,
                      '--sequential', '--json', str(again)]) == 0
    seq = json.loads(again.read_text())['cells'][0]
    timing = ('worker', 'wall_seconds', 'filter_seconds')
    assert ([{k: v for k, v in r.items() if k not in timing} for r in seq['runs']]
            == [{k: v for k, v in r.items() if k not in timing} for r in var4['runs']])
    # An existing output is not replaced without --force; nothing else is written.
    assert eval_main(args + ['--sequential', '--json', str(out_json)]) == 4
    assert 'exists' in capsys.readouterr().err


def test_bad_input_and_arguments_get_the_documented_exit_codes(tmp_path, capsys):
    missing = tmp_path / 'nothing_here'
    assert eval_main(['robustness', str(missing), '--sequential', '--quiet']) == 3
    err = capsys.readouterr().err.strip()
    assert err.count('\n') == 0 and 'nothing_here' in err
    no_truth = tmp_path / 'no_truth'
    no_truth.mkdir()
    source = next(SMARTLOC_EXCERPT.glob('*_Input.txt'))
    (no_truth / source.name).write_text(''.join(source.read_text().splitlines(True)[:400]))
    assert eval_main(['robustness', str(no_truth), '--sequential', '--quiet']) == 3
    assert 'no ground truth' in capsys.readouterr().err
    assert eval_main(['robustness', str(SMARTLOC_EXCERPT), '--cells', 'nope']) == 2
    assert "unknown cell 'nope'" in capsys.readouterr().err
    assert eval_main(['robustness', str(SMARTLOC_EXCERPT), '--seeds', '1']) == 2
    for flag in ('--first-seed', '--fault-seed'):
        assert eval_main(['robustness', str(SMARTLOC_EXCERPT), flag, '-1']) == 2
        assert f'{flag} must be >= 0' in capsys.readouterr().err
    assert eval_main(['robustness', str(SMARTLOC_EXCERPT), '--n-particles', '0']) == 2
    assert eval_main(['robustness', str(SMARTLOC_EXCERPT), '--sequential',
                      '--scheduler', 'tcp://127.0.0.1:1']) == 2
    assert eval_main(['robustness', '--list-cells']) == 0
    listed = capsys.readouterr().out
    assert all(c.name in listed for c in DEFAULT_CELLS)
    rows = {line.split()[0]: line.split()[-1] for line in listed.splitlines()[2:]}
    assert all(rows[c.name] == 'yes' for c in DEFAULT_CELLS)
    assert all(rows[c.name] == 'no' for c in robustness.EXTRA_CELLS)


def test_extra_cells_run_only_when_named_and_change_the_data_as_they_say(smartloc_excerpt):
    extra = [c.name for c in robustness.EXTRA_CELLS]
    assert set(extra) == {'cn0_-8db', 'cn0_+8db', 'cn0_unknown', 'troposphere'}
    assert not set(extra) & {c.name for c in select_cells()}
    assert [c.name for c in select_cells(['cn0_unknown', 'baseline'])] == [
        'baseline', 'cn0_unknown']
    base = cell_drive(smartloc_excerpt, robustness.CELLS_BY_NAME['baseline'], 30.0)
    cn0 = np.concatenate([e.cn0_dbhz for e in base.gnss])
    for d in (-8.0, 8.0):
        shifted = cell_drive(smartloc_excerpt, robustness.CELLS_BY_NAME[f'cn0_{d:+g}db'],
                             30.0)
        np.testing.assert_array_equal(np.concatenate([e.cn0_dbhz for e in shifted.gnss]),
                                      cn0 + d)
    unknown = cell_drive(smartloc_excerpt, robustness.CELLS_BY_NAME['cn0_unknown'], 30.0)
    assert all(np.isnan(e.cn0_dbhz).all() for e in unknown.gnss)
    # The troposphere cell: the delay at the drive's place (Berlin, near sea level): each
    # pseudorange longer by 2.3-2.5 m at the zenith, by about 1 / sin(elevation) more
    # (within 1 % above 20 deg) the lower the satellite.
    tropo = cell_drive(smartloc_excerpt, robustness.CELLS_BY_NAME['troposphere'], 30.0)
    delay = np.concatenate([b.pr_m - a.pr_m for a, b in zip(base.gnss, tropo.gnss)])
    el = np.radians(np.concatenate([e.elevation_deg for e in base.gnss]))
    zenith = (delay * np.sin(el))[el > np.radians(20.0)]
    assert zenith.size > 100
    np.testing.assert_array_less(2.3, zenith)
    np.testing.assert_array_less(zenith, 2.5)
    assert tropo.info['variants'][-1]['kind'] == 'leave_troposphere'
    assert 52.0 < tropo.info['variants'][-1]['lat_deg'] < 53.0


def test_exit_codes_are_gnsscam_evals():
    assert robustness_cli.EXIT_OK == cli.EXIT_OK
    assert robustness_cli.EXIT_RUNS_FAILED == cli.EXIT_CASES_FAILED
    assert robustness_cli.EXIT_USAGE == cli.EXIT_USAGE
    assert robustness_cli.EXIT_INPUT == cli.EXIT_INPUT
    assert robustness_cli.EXIT_OUTPUT == cli.EXIT_OUTPUT
    assert robustness_cli.EXIT_INTERRUPTED == cli.EXIT_INTERRUPTED


@pytest.mark.slow
def test_the_default_matrix_runs_on_the_excerpt(tmp_path, capsys):
    """Every cell of the default matrix, 2 seeds, 10 s each. The excerpt is the first 60 s
    of the Berlin file: the 60 s and 120 s starts have no data in it and are reported as
    such (exit 1), every other cell is measured."""
    out_json = tmp_path / 'matrix.json'
    code = eval_main(['robustness', str(SMARTLOC_EXCERPT), '--seeds', '2', '--duration-s',
                      '10', '--n-particles', '200', '--sequential', '--quiet', '--json',
                      str(out_json)])
    assert code == 1
    assert 'runs or cells failed' in capsys.readouterr().err
    result = json.loads(out_json.read_text())
    assert [c['name'] for c in result['cells']] == [c.name for c in DEFAULT_CELLS]
    no_data = {f['cell'] for f in result['failed']}
    assert no_data == {'start_60s', 'start_120s'}
    assert all(f['seed'] is None and 'no GNSS epoch' in f['error'] for f in result['failed'])
    for c in result['cells']:
        if c['name'] in no_data:
            assert not c['pass'] and 'no GNSS epoch' in c['error']
            continue
        assert all(f in c for f in CELL_FIELDS), c['name']
        assert c['mi_rate']['n'] > 0 and len(c['runs']) == 2
    shared = {c['name']: c['same_data_as'] for c in result['cells'] if c['same_data_as']}
    assert shared == {'gnss_5hz': 'baseline', 'start_0s': 'baseline'}
    assert result['runs_computed'] == 2 * (len(DEFAULT_CELLS) - 4)
