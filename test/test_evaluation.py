"""End-to-end evaluation on the committed smartLoc excerpt, and the metric definitions."""
import csv
import json
import math

import numpy as np
import pytest
from conftest import SMARTLOC_EXCERPT

from gnsscam_ros.core.config import FilterConfig
from gnsscam_ros.evaluation import cli, filter_options
from gnsscam_ros.evaluation.metrics import integrity_metrics, rmse
from gnsscam_ros.evaluation.runner import RunRecord, summarize


def test_metrics_known_answer():
    err = np.array([1.0, 9.0, 20.0, 3.0])
    bound = np.array([0.05, 0.5, 0.05, 0.2])
    ref = np.array([0.0, 0.6, 0.9, 0.1])
    m = integrity_metrics(err, bound, ref, alert_limit_m=8.0, target_risk=0.1)
    # faults: epochs 1, 2; insufficient: epochs 1, 3.
    assert m['p_fa'] == 0.5 and m['p_mi'] == 0.5
    assert m['failure_ratio'] == 0.5 and m['failure_error_m'] == pytest.approx(14.5)
    assert m['bound_gap'] == pytest.approx(np.mean(bound - ref))
    assert rmse(np.array([3.0, 4.0])) == pytest.approx(np.sqrt(12.5))


def test_summary_of_a_constructed_run_known_answer():
    """A run built by hand, through the evaluation's summary (horizontal error, the flag
    declared by validity and PL <= AL, per alert limit): every figure known.

    Errors 5, 10, 20 and 1 m (the last 100 m up: horizontal), PL 6, 12, 15, 2 m, the last
    epoch not valid (settling). At 8 m: faults epochs 1, 2; declared OK epoch 0 only; false
    alarm epoch 3 of the fault-free 0, 3 -> P_FA 1/2, P_MI 0/2. At 16 m: fault epoch 2,
    declared OK 0, 1, 2 -> a missed identification (epoch 2) of 1 fault, P_MI 1, false
    alarm epoch 3 of 3 fault-free, P_FA 1/3. Bounds below the reference at epochs 1, 2
    (both limits): failure ratio 1/2, failure error (10 + 20) / 2 m.
    """
    truth = np.zeros((4, 3))
    estimate = np.array([[3.0, 4.0, 0.0], [0.0, 10.0, 0.0], [20.0, 0.0, 0.0],
                         [1.0, 0.0, 100.0]])
    bounds = np.array([[0.05, 0.01], [0.5, 0.4], [0.05, 0.04], [0.2, 0.1]])
    reference = np.array([[0.0, 0.0], [0.6, 0.5], [0.9, 0.8], [0.1, 0.05]])
    record = RunRecord(
        stamp_ns=np.arange(4) * 10**9, estimate_enu_m=estimate, truth_enu_m=truth,
        risk_bound={'exact': bounds}, reference_risk=reference,
        alert_limits_m=np.array([8.0, 16.0]),
        protection_level_m=np.array([6.0, 12.0, 15.0, 2.0]),
        integrity_ok=np.array([True, False, False, False]),
        integrity_valid=np.array([True, True, True, False]))
    out = summarize(record, FilterConfig(alert_limit_m=8.0, extra_alert_limits_m=(16.0,)))
    assert out['epochs'] == 4
    assert out['rmse_2d_m'] == pytest.approx(math.sqrt((25 + 100 + 400 + 1) / 4))
    assert out['rmse_3d_m'] == pytest.approx(math.sqrt((25 + 100 + 400 + 10001) / 4))
    at8, at16 = out['integrity']['8'], out['integrity']['16']
    assert (at8['p_fa'], at8['p_mi'], at8['faults']) == (0.5, 0.0, 2)
    assert (at16['p_fa'], at16['p_mi'], at16['faults']) == (pytest.approx(1 / 3), 1.0, 1)
    assert (at8['failure_ratio'], at8['failure_error_m']) == (0.5, 15.0)
    assert (at16['failure_ratio'], at16['failures']) == (0.5, 2)
    assert out['protection_level']['mi_epochs'] == 1               # 20 m > PL 15 m
    assert out['protection_level']['flag_ok'] == {
        'ok_epochs': 1, 'error_above_al_epochs': 0, 'error_above_al_rate': 0.0}


def _epochs_csv(path) -> list[dict]:
    with open(path, newline='', encoding='utf-8') as f:
        return list(csv.DictReader(f))


@pytest.mark.slow
def test_eval_smartloc_excerpt_end_to_end(tmp_path, capsys):
    """The JSON's figures are those of its own per-epoch rows (--epochs-csv), recounted
    here from their definitions."""
    out, rows_csv = tmp_path / 'out.json', tmp_path / 'epochs.csv'
    code = cli.main(['smartloc', str(SMARTLOC_EXCERPT), '--json', str(out), '--quiet',
                     '--n-particles', '300', '--seed', '1', '--epochs-csv', str(rows_csv)])
    assert code == 0
    result = json.loads(out.read_text())
    assert result['epochs'] == 284
    rows = [r for r in _epochs_csv(rows_csv) if r['status'] == 'updated']
    assert len(rows) == result['epochs']
    err = np.array([float(r['horizontal_error_m']) for r in rows])
    assert result['rmse_2d_m'] == pytest.approx(math.sqrt(np.mean(err ** 2)), rel=1e-9)
    assert result['max_2d_m'] == pytest.approx(err.max(), rel=1e-9)
    declared = np.array([r['integrity'] == 'OK' for r in rows])
    at8 = result['integrity']['8']
    fault = err > 8.0
    assert at8['faults'] == int(fault.sum())
    assert at8['false_alarms'] == int(np.sum(~declared & ~fault))
    assert at8['missed_identifications'] == int(np.sum(declared & fault))
    assert at8['p_fa'] == pytest.approx(np.sum(~declared & ~fault) / np.sum(~fault))
    for key in ('rmse_2d_m', 'rmse_3d_m'):
        assert 0.0 < result['baseline_wls'][key]
    assert 'RMSE 2D' in capsys.readouterr().out
    # The filter on GNSS + odometry beats the snapshot fixes on the same data.
    assert result['rmse_2d_m'] < result['baseline_wls']['rmse_2d_m']
    # An existing output is not overwritten without --force.
    before = out.read_text()
    assert cli.main(['smartloc', str(SMARTLOC_EXCERPT), '--json', str(out), '--quiet']) == 4
    assert out.read_text() == before


def test_eval_reports_bad_input(tmp_path, capsys):
    bad = tmp_path / 'bad_Input.txt'
    bad.write_text('pseudorange3 0 1\n')
    assert cli.main(['smartloc', '--input', str(bad), '--quiet']) == 3
    assert f'{bad}:1' in capsys.readouterr().err


@pytest.mark.slow
def test_eval_emulated_short(tmp_path):
    out = tmp_path / 'emu.json'
    assert cli.main(['emulated', '--faults', '4', '--bias-m', '100', '--seed', '2',
                     '--duration-s', '120', '--n-particles', '300', '--quiet',
                     '--json', str(out)]) == 0
    result = json.loads(out.read_text())
    assert result['rmse_2d_m'] < result['baseline_wls']['rmse_2d_m']
    assert result['dataset']['faults'] == 4


def test_eval_help_explains_every_filter_option(capsys):
    """--target-risk had no help and --posteriors said "odometry perturbations M": every
    option now says what its FilterConfig parameter's metadata says."""
    with pytest.raises(SystemExit):
        cli.main(['emulated', '--help'])
    text = ' '.join(capsys.readouterr().out.split())
    text = text[text.index('filter:'):]          # the option list, not the usage line
    assert 'odometry perturbations' not in text
    for spec in filter_options.filter_option_specs():
        option = filter_options.option_name(spec.name)
        if isinstance(spec.default, bool):          # --use-camera, --no-use-camera
            option = '--no-' + option[2:]
        described = text.split(f'{option} ', 1)[1].split(' --', 1)[0]
        assert ' '.join(spec.doc.split()[:4]) in described, option
        assert 'default' in described, (option, described)
    for option in ('--alert-limits', '--seed'):
        described = text.split(option, 1)[1].split(' --', 1)[0]
        assert 'default' in described, (option, described)
    # The earlier spellings still work but are not offered.
    for old in ('--particles', '--posteriors', '--correlation-time-s'):
        assert old not in text


def test_eval_options_are_the_filter_parameters_under_their_names():
    values = {'n_particles': 300, 'n_posteriors': 10, 'likelihood': 'particle_raim',
              'use_camera': False, 'outlier_range_m': 150.0}
    argv = ['emulated', '--n-particles', '300', '--n-posteriors', '10', '--likelihood',
            'particle_raim', '--no-use-camera', '--outlier-range-m', '150']
    config = cli.config_from_args(cli.build_parser().parse_args(argv))
    assert config == FilterConfig(**values, alert_limit_m=8.0, extra_alert_limits_m=(16.0,))
    old = ['emulated', '--particles', '300', '--posteriors', '10', '--correlation-time-s', '2.5']
    config = cli.config_from_args(cli.build_parser().parse_args(old))
    assert (config.n_particles, config.n_posteriors, config.error_correlation_time_s) == (
        300, 10, 2.5)
    # Defaults are FilterConfig's own.
    default = cli.config_from_args(cli.build_parser().parse_args(['emulated']))
    assert default == FilterConfig(alert_limit_m=8.0, extra_alert_limits_m=(16.0,))


@pytest.mark.ros                 # the demo module runs nodes: imports rclpy
def test_eval_and_demo_share_the_default_seed():
    from gnsscam_ros.evaluation import demo
    parser = cli.build_parser()
    assert parser.parse_args(['emulated']).seed == demo.build_parser().parse_args([]).seed == 1


def test_eval_alert_limits_option(capsys):
    args = cli.build_parser().parse_args(['emulated', '--alert-limits', '10', '25', '50'])
    config = cli.config_from_args(args)
    assert config.alert_limit_m == 10.0 and list(config.alert_limits_m) == [10.0, 25.0, 50.0]
    with pytest.raises(SystemExit) as stop:          # argparse's usage error
        cli.main(['emulated', '--alert-limits', '8', '-3', '--quiet'])
    assert stop.value.code == 2
    assert '--alert-limits: -3 is not a positive number of metres' in capsys.readouterr().err


@pytest.mark.slow
def test_eval_reports_the_alert_limits_asked_for(tmp_path):
    out = tmp_path / 'emu.json'
    assert cli.main(['emulated', '--duration-s', '20', '--n-particles', '100', '--quiet',
                     '--alert-limits', '12', '30', '--json', str(out)]) == 0
    result = json.loads(out.read_text())
    assert set(result['integrity']) == {'12', '30'}
