"""Seeded emulated urban drive: ground truth, IMU, wheel odometry and GNSS pseudoranges.

The drive follows the streets of a generated grid city (:mod:`..city`) anchored at a real
city centre (Frankfurt am Main by default). Everything is deterministic per seed, and each
ingredient draws from its own random stream (:func:`.config.stream_rng`). One module per
step:

* :mod:`.config`: parameters (:class:`.config.EmulationConfig`) and random streams;
* :mod:`.route`, :mod:`.trajectory`, :mod:`.scenario`: a ~2.3 km lane-centre path through
  the street grid (straight lines and 10 m turn arcs, driving on the right), driven at
  8-14 m/s per street, 5 m/s in turns, with stops at some intersections; the ground is
  flat (``u`` = antenna height);
* :mod:`.imu_odometry`: 100 Hz IMU and 10 Hz wheel odometry from the truth;
* :mod:`.constellation`, :mod:`.pseudoranges`, :mod:`.gnss_faults`: GPS and GLONASS
  pseudoranges with receiver clock, noise, NLOS errors and injected faults;
* :mod:`.camera`: the rendered camera stream (random stream ``'camera'``), attached by
  :func:`make_emulated_drive` ``(camera=True)`` or :func:`.camera.with_camera`.

This module assembles them into a :class:`...core.types.Drive`.
"""
from __future__ import annotations

from dataclasses import asdict

import numpy as np

from ...core.types import GLONASS, GPS, Drive, GnssEpoch, ImuSeries, OdometrySeries, Trajectory
from .camera import with_camera
from .config import EmulationConfig, stream_rng
from .imu_odometry import (GRAVITY_MPS2, ImuSynthesis, OdometrySynthesis, synthesize_imu,
                           synthesize_odometry)
from .pseudoranges import GnssSynthesis, synthesize_gnss
from .scenario import Scenario, make_scenario
from .trajectory import Pose


def make_emulated_drive(seed: int, faults: int = 0, bias_m: float = 100.0, nlos: bool = True,
                        duration_s: float | None = None, gnss_rate_hz: float = 1.0,
                        fault_fraction: float = 0.3,
                        config: EmulationConfig | None = None,
                        camera: bool = False) -> Drive:
    """Generate the seeded emulated urban drive.

    The pseudorange model (geometric range, receiver clock and GLONASS inter-system bias,
    white noise of 10 m^2, NLOS delays on blocked satellites) is described in
    :mod:`.pseudoranges`, the faults in :mod:`.gnss_faults`: with ``faults > 0``, fault
    episodes of 3-10 s cover about ``fault_fraction`` of the epochs after the first 10 s,
    and in each of them ``faults`` of the 12 satellites get a constant bias of magnitude
    ``clip(|N(bias_m, (bias_m/4)^2)|, 20, 200)`` m and random sign. The same seed with a
    different ``faults`` gives the same episodes, and the faulty sets are nested.

    Args:
        seed: Drive seed (all randomness derives from it).
        faults: Number of faulty satellites per faulty epoch (0 .. 12).
        bias_m: Mean fault magnitude [m].
        nlos: Add NLOS errors on blocked satellites (False: open-sky-like measurements).
        duration_s: Keep only the first ``duration_s`` seconds (None: the whole drive).
        gnss_rate_hz: GNSS epoch rate [Hz] (the truth rate should be a multiple of it).
        fault_fraction: Target fraction of faulty epochs.
        config: Physical parameters (defaults when None).
        camera: Attach the rendered camera stream (:func:`.camera.with_camera`).

    Returns:
        The drive. ``info`` holds the provenance and the error decomposition; the arrays
        ``gnss_*`` of shape (n_epochs, 12) are aligned with each epoch's satellites.
    """
    cfg = config or EmulationConfig()
    if not 0 <= faults <= cfg.n_sv:
        raise ValueError(f'faults must be in 0..{cfg.n_sv}, got {faults}')
    if gnss_rate_hz <= 0:
        raise ValueError(f'gnss_rate_hz must be positive, got {gnss_rate_hz}')
    sc = make_scenario(seed, cfg)
    # The whole drive is synthesised, then cut: a shorter drive is a prefix of the full one.
    pose = sc.pose_at(sc.t_s)
    imu = synthesize_imu(stream_rng(seed, 'imu'), pose, cfg)
    odo = synthesize_odometry(stream_rng(seed, 'odometry'), pose, cfg)
    gnss = synthesize_gnss(sc, gnss_rate_hz, nlos, faults, bias_m, fault_fraction)
    t_end = sc.duration_s if duration_s is None else min(float(duration_s), sc.duration_s)
    n_keep = int(np.sum(gnss.t_s <= t_end + 1e-9))
    info = {
        'generator': 'gnsscam_ros.datasets.emulated.drive.make_emulated_drive',
        'seed': int(seed), 'faults': int(faults), 'bias_m': float(bias_m), 'nlos': bool(nlos),
        'duration_s': float(t_end), 'gnss_rate_hz': float(gnss_rate_hz),
        'fault_fraction': float(fault_fraction), 'config': asdict(cfg),
        't0_ns': int(sc.t0_ns), 'route_length_m': float(np.interp(t_end, sc.t_s, sc.s_m)),
        'stops': list(sc.stops), 'systems': {'GPS': GPS, 'GLONASS': GLONASS},
        'gravity_mps2': GRAVITY_MPS2,
        'imu_bias': {'accel_mps2': imu.accel_bias_mps2, 'gyro_rps': imu.gyro_bias_rps},
        **_gnss_info(gnss, n_keep),
    }
    odometry, imu_series, truth = _motion_series(sc, pose, imu, odo, t_end)
    name = f'emulated-urban-s{seed}-f{faults}' + ('' if nlos else '-nonlos')
    drive = Drive(name=name, origin_llh=sc.frame.origin_llh,
                  gnss=_gnss_epochs(sc, gnss, n_keep), odometry=odometry, imu=imu_series,
                  truth=truth, camera=None, info=info)
    return with_camera(drive) if camera else drive


def _gnss_epochs(sc: Scenario, g: GnssSynthesis, n_keep: int) -> list[GnssEpoch]:
    """The first ``n_keep`` epochs as :class:`GnssEpoch` messages."""
    cfg = sc.config
    stamps = sc.stamps_ns(g.t_s)
    return [GnssEpoch(stamp_ns=int(stamps[k]), sv_pos_ecef_m=g.sv_pos_ecef_m[k], pr_m=g.pr_m[k],
                      var_m2=np.full(cfg.n_sv, cfg.pr_var_m2),
                      sv_id=g.sv_id[k].astype(np.int64), system=g.system[k].astype(np.int64),
                      elevation_deg=g.elevation_deg[k], cn0_dbhz=g.cn0_dbhz[k])
            for k in range(n_keep)]


def _gnss_info(g: GnssSynthesis, n_keep: int) -> dict:
    """The ``info`` entries of the GNSS error decomposition, cut to ``n_keep`` epochs."""
    return {
        'rx_clock_bias_m': g.clock_bias_m[:n_keep],
        'rx_clock_drift_mps': g.clock_drift_mps[:n_keep],
        'isb_glonass_m': float(g.isb_glonass_m),
        'gnss_truth_ecef_m': g.rx_ecef_m[:n_keep],
        'gnss_geometric_range_m': g.geometric_range_m[:n_keep],
        'gnss_clock_m': g.clock_m[:n_keep],
        'gnss_noise_m': g.noise_m[:n_keep],
        'gnss_blocked': g.blocked[:n_keep],
        'gnss_nlos_m': g.nlos_m[:n_keep],
        'gnss_fault_m': g.fault_m[:n_keep],
        'gnss_faults': [r for r in g.fault_records if r['epoch'] < n_keep],
        'fault_episodes': [(a, min(b, n_keep)) for a, b in g.fault_episodes if a < n_keep],
    }


def _motion_series(sc: Scenario, pose: Pose, imu: ImuSynthesis, odo: OdometrySynthesis,
                   t_end: float) -> tuple[OdometrySeries, ImuSeries, Trajectory]:
    """Odometry, IMU and truth series up to ``t_end`` (seconds from the start)."""
    cfg = sc.config
    stamps = sc.stamps_ns(sc.t_s)
    keep_t = sc.t_s <= t_end + 1e-9
    keep_o = keep_t[odo.index]
    n_odo = int(keep_o.sum())
    odometry = OdometrySeries(stamp_ns=stamps[odo.index][keep_o],
                              speed_mps=odo.speed_mps[keep_o],
                              yaw_rate_rps=odo.yaw_rate_rps[keep_o],
                              speed_var=np.full(n_odo, cfg.odom_speed_std_mps ** 2),
                              yaw_rate_var=np.full(n_odo, cfg.odom_yaw_rate_std_rps ** 2))
    imu_series = ImuSeries(stamp_ns=stamps[keep_t], accel_mps2=imu.accel_mps2[keep_t],
                           gyro_rps=imu.gyro_rps[keep_t])
    truth = Trajectory(stamp_ns=stamps[keep_t], ecef_m=sc.frame.enu_to_ecef(pose.enu_m)[keep_t],
                       yaw_rad=pose.yaw_rad[keep_t])
    return odometry, imu_series, truth
