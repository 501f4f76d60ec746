"""A RINEX observation file and its broadcast navigation as a Drive (the model of the
smartLoc loader): corrected epochs from ``core.preprocess``, zero-motion odometry for a
static receiver, the station as ground truth.

With ``static=True`` the drive gets a wheel-odometry stream of zero speed and yaw rate
every :data:`STATIC_ODOMETRY_PERIOD_S` with a tight variance (what a parked vehicle's
odometry reports), fed to the filter as smartLoc's ``odom3`` is. Without it the filter has
no motion input (each epoch's motion is unknown, as for a receiver alone).

The truth (``station_ecef_m``, the marker) is moved to the antenna reference point by the
header's ``ANTENNA: DELTA H/E/N``; phase-centre offsets (millimetres to centimetres) are
left out.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..core.frames import LocalFrame
from ..core.preprocess import PreprocessConfig, Preprocessor
from ..core.types import Drive, OdometrySeries, Trajectory
from .errors import DatasetError
from .rinex import check_navigation_covers, read_navigation, read_observations

#: Zero-motion odometry: one sample per this much time [s] (under the dead reckoning's
#: 1 s largest gap) with these variances [(m/s)^2], [(rad/s)^2].
STATIC_ODOMETRY_PERIOD_S = 0.5
STATIC_SPEED_VAR = 1e-6
STATIC_YAW_RATE_VAR = 1e-8
#: Fewest satellites of a usable epoch (position + one clock).
MIN_SATELLITES = 4
#: Acknowledgement carried in the drive's info (the data's sources ask for it).
ATTRIBUTION = ('RINEX data of IGS / EUREF / NOAA NGS CORS / UNAVCO stations; acknowledge '
               'the International GNSS Service (IGS), NOAA/NGS CORS and UNAVCO')


def static_odometry(start_ns: int, end_ns: int) -> OdometrySeries:
    """Zero speed and yaw rate from ``start_ns`` to ``end_ns`` with a tight variance."""
    step = int(STATIC_ODOMETRY_PERIOD_S * 1e9)
    stamps = np.arange(int(start_ns), int(end_ns) + step, step, dtype=np.int64)
    zeros = np.zeros(stamps.size)
    return OdometrySeries(stamp_ns=stamps, speed_mps=zeros, yaw_rate_rps=zeros.copy(),
                          speed_var=np.full(stamps.size, STATIC_SPEED_VAR),
                          yaw_rate_var=np.full(stamps.size, STATIC_YAW_RATE_VAR))


def corrected_epochs(path: Path, observations: list, nav, config: PreprocessConfig | None,
                     systems: tuple[int, ...] | None) -> tuple[list, dict, int]:
    """Every observation epoch through one :class:`~..core.preprocess.Preprocessor`.

    Returns:
        The corrected epochs, the satellites skipped by reason (``system_excluded``: not in
        ``systems``), and the number of epochs with fewer than :data:`MIN_SATELLITES`.

    Raises:
        DatasetError: No epoch has enough satellites (``path`` named, with the counts).
    """
    pre = Preprocessor(nav, config)
    epochs, skipped = [], {}
    unusable = 0
    for raw in observations:
        result = pre.process(raw)
        for reason, n in result.skipped.items():
            skipped[reason] = skipped.get(reason, 0) + n
        epoch = result.epoch
        if systems is not None:
            keep = np.isin(epoch.system, systems)
            if not keep.all():
                skipped['system_excluded'] = (skipped.get('system_excluded', 0)
                                              + int((~keep).sum()))
                epoch = epoch.subset(keep)
        unusable += int(epoch.n_sv < MIN_SATELLITES)
        epochs.append(epoch)
    if unusable == len(epochs):
        raise DatasetError(f'{path}: no epoch has {MIN_SATELLITES} usable satellites '
                           f'(skipped over {len(epochs)} epochs: {skipped or "none"})')
    return epochs, skipped, unusable


def load_rinex(obs_path: Path, nav_paths: list[Path], static: bool = False,
               station_ecef_m: np.ndarray | None = None, duration_s: float | None = None,
               config: PreprocessConfig | None = None, name: str | None = None,
               systems: tuple[int, ...] | None = None) -> Drive:
    """Corrected epochs of a RINEX observation file.

    Args:
        obs_path: Observation file (RINEX 2/3, ``.gz``, ``.crx(.gz)``).
        nav_paths: Broadcast navigation files (one or more systems).
        static: Add zero-motion odometry (a receiver known not to move).
        station_ecef_m: (3,) published marker position [m] (ground truth), or None.
        duration_s: Only the first seconds of the file [s].
        config: Preprocessing parameters.
        name: Run name (default: the observation file's stem).
        systems: Keep only these system codes (None: every system with navigation); the
            others are counted as ``system_excluded``.

    Returns:
        The drive; ``info['skipped_satellites']`` counts the satellites left out by
        reason over all epochs, ``info['epochs_unusable']`` the epochs with fewer than
        :data:`MIN_SATELLITES` corrected satellites (kept: the filter reports them).

    Raises:
        DatasetError: Unreadable files, navigation of another time, or no epoch with
            enough usable satellites (the file named, with the skip counts).
    """
    if not nav_paths:
        raise DatasetError('give at least one navigation file (--nav)')
    obs = read_observations(Path(obs_path), duration_s)
    nav = read_navigation([Path(p) for p in nav_paths])
    check_navigation_covers(nav, obs)
    epochs, skipped, unusable = corrected_epochs(obs.path, obs.epochs, nav, config, systems)
    odometry = (static_odometry(epochs[0].stamp_ns, epochs[-1].stamp_ns) if static
                else None)
    truth = None
    if station_ecef_m is not None:
        station = np.asarray(station_ecef_m, dtype=float).reshape(3)
        if not 6.0e6 < np.linalg.norm(station) < 7.0e6:
            raise DatasetError(f'station ECEF {station.tolist()} m is not on the Earth '
                               '(radius 6,000-7,000 km)')
        frame = LocalFrame.from_ecef(station)
        arp = frame.enu_to_ecef(obs.antenna_delta_enu_m)
        stamps = np.array([e.stamp_ns for e in epochs], dtype=np.int64)
        truth = Trajectory(stamp_ns=stamps, ecef_m=np.repeat(arp[None, :], stamps.size, 0))
    return Drive(
        name=name or Path(obs_path).name.split('.')[0], origin_llh=None, gnss=epochs,
        odometry=odometry, imu=None, truth=truth,
        info={'observations': str(obs.path), 'navigation': list(nav.sources),
              'static': bool(static), 'systems': None if systems is None else list(systems),
              'epochs': len(epochs), 'epochs_unusable': unusable,
              'skipped_satellites': skipped, 'interval_s': obs.interval_s,
              'license': ATTRIBUTION})
