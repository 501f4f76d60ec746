"""A RINEX station (NYA1 fixture: GPS + Galileo + BeiDou, static) converted to a bag and
replayed through the four nodes gives the offline run's estimates and risk bounds, as the
emulated drive does (test_replay.py)."""
from pathlib import Path

import numpy as np
import pytest
import ros_harness  # noqa: F401  (the replay runs nodes: the module skips without rclpy)

from gnsscam_ros.bags.convert import convert_drive
from gnsscam_ros.bags.read import read_drive
from gnsscam_ros.core.filter import FilterConfig
from gnsscam_ros.core.frames import LocalFrame
from gnsscam_ros.datasets.rinex_drive import load_rinex
from gnsscam_ros.evaluation.bag_eval import evaluate_result_bag
from gnsscam_ros.evaluation.demo import node_series, offline_run
from gnsscam_ros.evaluation.runner import summarize
from gnsscam_ros.live.replay_through_nodes import replay_through_nodes

pytestmark = pytest.mark.ros

DATA = Path(__file__).resolve().parent / 'data' / 'rinex'
NYA1_OBS = DATA / 'NYA100NOR_S_20241240000_01D_30S_MO.crx.gz'
NYA1_NAV = [DATA / f'NYA100NOR_S_20241240000_01D_{s}.rnx.gz' for s in ('GN', 'EN', 'CN')]
NYA1_ECEF = np.array([1202433.613, 252632.407, 6237772.780])
SEED, N_PARTICLES = 7, 400


@pytest.mark.slow
def test_rinex_bag_through_nodes_equals_offline(tmp_path):
    drive = load_rinex(NYA1_OBS, NYA1_NAV, static=True, station_ecef_m=NYA1_ECEF)
    # The map frame at the station, so that nodes and offline run share it.
    drive.origin_llh = LocalFrame.from_ecef(NYA1_ECEF).origin_llh
    convert_drive(drive, tmp_path / 'bag')
    replayed = read_drive(tmp_path / 'bag')
    assert len(replayed.gnss) == len(drive.gnss) == 4
    params = {'fusion_node': {'n_particles': N_PARTICLES, 'seed': SEED, 'use_map_origin': True,
                              'map_origin_llh': [float(v) for v in drive.origin_llh]}}
    summary, _ = replay_through_nodes(tmp_path / 'bag', tmp_path / 'result', rate=0.0,
                                      parameters=params, layout='threads')
    assert summary.gnss_epochs_processed == summary.gnss_epochs == len(drive.gnss)
    assert summary.dropped_gnss_epochs == 0
    config = FilterConfig(n_particles=N_PARTICLES)
    off_record, frame = offline_run(replayed, config, SEED)
    series = node_series(tmp_path / 'result', frame)
    np.testing.assert_array_equal(series['stamp_ns'], off_record.stamp_ns)
    np.testing.assert_allclose(series['estimate_enu_m'], off_record.estimate_enu_m, rtol=0,
                               atol=1e-6)
    np.testing.assert_allclose(series['risk_bound'], off_record.risk_bound['exact'][:, 0],
                               rtol=1e-9, atol=1e-12)
    nodes = evaluate_result_bag(tmp_path / 'result')
    offline = summarize(off_record, config)
    assert nodes['rmse_2d_m'] == pytest.approx(offline['rmse_2d_m'], rel=1e-7)
    assert offline['rmse_2d_m'] < 3.0
