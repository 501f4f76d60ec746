"""End-to-end evaluation on the committed smartLoc excerpt, and the metric definitions."""
import json

import numpy as np
import pytest
from conftest import SMARTLOC_EXCERPT

from gnsscam_ros.core.config import FilterConfig
from gnsscam_ros.evaluation import cli, filter_options
from gnsscam_ros.evaluation.metrics import integrity_metrics, rmse


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


@pytest.mark.slow
def test_eval_smartloc_excerpt_end_to_end(tmp_path, capsys):
    out = tmp_path / 'out.json'
    code = cli.main(['smartloc', str(SMARTLOC_EXCERPT), '--json', str(out), '--quiet',
                     '--n-particles', '300', '--seed', '1'])
    assert code == 0
    result = json.loads(out.read_text())
    assert result['epochs'] == 284
    for key in ('rmse_2d_m', 'rmse_3d_m'):
        assert 0.0 < result[key] < 60.0
        assert 0.0 < result['baseline_wls'][key]
    for limit in ('8', '16'):
        metrics = result['integrity'][limit]
        for key in ('p_fa', 'p_mi', 'failure_ratio', 'failure_error_m', 'bound_gap'):
            assert key in metrics
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
