"""Variations of a drive's data: the same drive as another receiver or preprocessing would
present it (pure functions: the drive given is left as it is, a new one is returned).

* :func:`scale_variances`, :func:`set_variances`: the stated pseudorange variances times a
  factor, or all one constant (a receiver that reports one sigma for everything);
* :func:`decimate_gnss`: the GNSS epochs thinned to a lower rate (odometry, IMU and truth
  keep theirs);
* :func:`select_systems`: only the satellites of some systems (GPS only, GLONASS only),
  epochs left with too few of them dropped;
* :func:`start_after`: the drive joined some seconds after its start (GNSS, odometry and
  IMU before that dropped; the ground truth kept whole: it is only used for scoring);
* :func:`shift_cn0`, :func:`drop_cn0`: the C/N0 on another receiver's scale (every value
  offset by some dB-Hz: another antenna, front end or C/N0 estimator), or not reported.
* :func:`leave_troposphere`: the tropospheric delay left in the pseudoranges (a
  preprocessing that removed the satellite clocks but not the atmosphere, against the
  GNSS input contract of ``GnssEpoch.pr_m``).

Each appends a record of what it did to ``drive.info['variants']`` and a tag to the name.
:func:`drive_digest` names a drive's content, so that variations that leave a drive as it
was (the 5 Hz decimation of a 5 Hz file) can be recognised.
"""
from __future__ import annotations

import dataclasses
import hashlib

import numpy as np

from ..core.corrections import tropo_delay_m
from ..core.types import Drive, ImuSeries, OdometrySeries
from .errors import DatasetError

SECOND_NS = 1_000_000_000


def _with_variant(drive: Drive, tag: str, record: dict, **changes) -> Drive:
    """A copy of ``drive`` with ``changes``, its name tagged and ``record`` appended."""
    variants = [*drive.info.get('variants', []), record]
    return dataclasses.replace(drive, name=f'{drive.name}+{tag}',
                               info={**drive.info, 'variants': variants}, **changes)


def _check_epochs(drive: Drive, epochs: list, what: str) -> None:
    if not epochs:
        raise DatasetError(f'{drive.name}: {what} leaves no GNSS epoch')


def scale_variances(drive: Drive, factor: float) -> Drive:
    """Every stated pseudorange variance times ``factor``.

    Args:
        drive: The drive.
        factor: Positive finite factor (0.25 quarters the variances, i.e. halves the
            stated sigmas).

    Raises:
        ValueError: ``factor`` is not positive and finite.
    """
    factor = float(factor)
    if not (np.isfinite(factor) and factor > 0):
        raise ValueError(f'variance factor must be positive and finite, got {factor!r}')
    epochs = [dataclasses.replace(e, var_m2=e.var_m2 * factor) for e in drive.gnss]
    return _with_variant(drive, f'var_x{factor:g}', {'kind': 'scale_variances',
                                                     'factor': factor}, gnss=epochs)


def set_variances(drive: Drive, var_m2: float) -> Drive:
    """Every stated pseudorange variance set to ``var_m2`` [m^2].

    Raises:
        ValueError: ``var_m2`` is not positive and finite.
    """
    var_m2 = float(var_m2)
    if not (np.isfinite(var_m2) and var_m2 > 0):
        raise ValueError(f'variance must be positive and finite, got {var_m2!r} m^2')
    epochs = [dataclasses.replace(e, var_m2=np.full(e.n_sv, var_m2)) for e in drive.gnss]
    return _with_variant(drive, f'var_{var_m2:g}m2', {'kind': 'set_variances',
                                                      'var_m2': var_m2}, gnss=epochs)


def shift_cn0(drive: Drive, offset_dbhz: float) -> Drive:
    """Every reported C/N0 plus ``offset_dbhz`` (unknown ones stay unknown).

    Raises:
        ValueError: ``offset_dbhz`` is not finite.
    """
    offset = float(offset_dbhz)
    if not np.isfinite(offset):
        raise ValueError(f'C/N0 offset must be finite, got {offset_dbhz!r}')
    epochs = [dataclasses.replace(e, cn0_dbhz=e.cn0_dbhz + offset) for e in drive.gnss]
    return _with_variant(drive, f'cn0_{offset:+g}dB', {'kind': 'shift_cn0',
                                                       'offset_dbhz': offset}, gnss=epochs)


def drop_cn0(drive: Drive) -> Drive:
    """Every C/N0 unknown (NaN): a receiver or format that does not report it."""
    epochs = [dataclasses.replace(e, cn0_dbhz=np.full(e.cn0_dbhz.shape, np.nan))
              for e in drive.gnss]
    return _with_variant(drive, 'no_cn0', {'kind': 'drop_cn0'}, gnss=epochs)


def leave_troposphere(drive: Drive, lat_deg: float, height_m: float) -> Drive:
    """Every pseudorange plus its slant tropospheric delay at a receiver at ``lat_deg``,
    ``height_m`` (``core.corrections.tropo_delay_m``: Saastamoinen zenith delays of a
    standard atmosphere, about 2.4 m at sea level, Black-Eisner mapping: 9 m at 15 deg
    elevation). The common part goes into the receiver clock; what differs between
    satellites moves the position.

    Raises:
        DatasetError: A satellite's elevation is unknown (the delay depends on it).
        ValueError: ``lat_deg`` or ``height_m`` is not finite.
    """
    lat, height = float(lat_deg), float(height_m)
    if not (np.isfinite(lat) and np.isfinite(height)):
        raise ValueError(f'receiver latitude and height must be finite, got {lat_deg!r}, '
                         f'{height_m!r}')
    epochs = []
    for e in drive.gnss:
        if not np.all(np.isfinite(e.elevation_deg)):
            raise DatasetError(f'{drive.name}: an elevation is unknown at epoch '
                               f'{e.stamp_ns}: the tropospheric delay depends on it')
        delay = tropo_delay_m(np.radians(lat), height, np.radians(e.elevation_deg))
        epochs.append(dataclasses.replace(e, pr_m=e.pr_m + delay))
    return _with_variant(drive, 'troposphere_left', {'kind': 'leave_troposphere',
                                                     'lat_deg': lat, 'height_m': height},
                         gnss=epochs)


def gnss_stamps_ns(drive: Drive) -> np.ndarray:
    """(T,) GNSS epoch stamps [ns]."""
    return np.array([e.stamp_ns for e in drive.gnss], dtype=np.int64)


def gnss_rate_hz(drive: Drive) -> float | None:
    """Mean GNSS rate over the drive [Hz]: (epochs - 1) / span; None below two epochs."""
    stamps = gnss_stamps_ns(drive)
    if stamps.size < 2 or stamps[-1] == stamps[0]:
        return None
    return (stamps.size - 1) * SECOND_NS / float(stamps[-1] - stamps[0])


def decimate_gnss(drive: Drive, rate_hz: float) -> Drive:
    """The GNSS epochs thinned to ``rate_hz``; odometry, IMU and truth are kept whole.

    An epoch is kept when at least ``1 / rate_hz - dt / 2`` has passed since the last kept
    one, ``dt`` the file's median epoch interval: on a regular file the kept epochs are
    ``1 / rate_hz`` apart to within its jitter, and a rate at or above the file's own keeps
    every epoch (decimation never adds epochs).

    Args:
        drive: The drive.
        rate_hz: Requested GNSS rate [Hz], positive.

    Raises:
        ValueError: ``rate_hz`` is not positive and finite.
    """
    rate_hz = float(rate_hz)
    if not (np.isfinite(rate_hz) and rate_hz > 0):
        raise ValueError(f'GNSS rate must be positive and finite, got {rate_hz!r} Hz')
    stamps = gnss_stamps_ns(drive)
    native_ns = float(np.median(np.diff(stamps))) if stamps.size > 1 else 0.0
    threshold_ns = SECOND_NS / rate_hz - native_ns / 2.0
    keep, last = [], None
    for i, stamp in enumerate(stamps.tolist()):
        if last is None or stamp - last >= threshold_ns:
            keep.append(i)
            last = stamp
    epochs = [drive.gnss[i] for i in keep]
    out = _with_variant(drive, f'gnss_{rate_hz:g}hz', {
        'kind': 'decimate_gnss', 'rate_hz': rate_hz, 'epochs_before': len(drive.gnss),
        'epochs_kept': len(epochs)}, gnss=epochs)
    out.info['variants'][-1].update(rate_hz_before=gnss_rate_hz(drive),
                                    rate_hz_after=gnss_rate_hz(out))
    return out


def select_systems(drive: Drive, systems, min_satellites: int = 1) -> Drive:
    """Only the pseudoranges of ``systems``; epochs left with fewer than ``min_satellites``
    of them are dropped (a receiver of those systems alone would have no usable fix).

    Args:
        drive: The drive.
        systems: System identifiers to keep (``core.types.GPS``, ``GLONASS``, ...).
        min_satellites: Satellites an epoch needs to be kept (>= 1).

    Raises:
        ValueError: No system or ``min_satellites`` below 1.
        DatasetError: No epoch is left.
    """
    wanted = sorted({int(s) for s in systems})
    if not wanted or int(min_satellites) < 1:
        raise ValueError('select_systems needs a system and min_satellites >= 1')
    epochs = []
    for epoch in drive.gnss:
        keep = np.isin(epoch.system, wanted)
        if int(keep.sum()) >= min_satellites:
            epochs.append(epoch.subset(keep))
    what = f'systems {wanted} with >= {min_satellites} satellites'
    _check_epochs(drive, epochs, what)
    return _with_variant(drive, 'sys_' + '_'.join(str(s) for s in wanted), {
        'kind': 'select_systems', 'systems': wanted, 'min_satellites': int(min_satellites),
        'epochs_before': len(drive.gnss), 'epochs_kept': len(epochs),
        'epochs_dropped': len(drive.gnss) - len(epochs)}, gnss=epochs)


def start_after(drive: Drive, start_s: float) -> Drive:
    """The drive joined ``start_s`` seconds after its first GNSS epoch: GNSS epochs,
    odometry and IMU samples before that are dropped; the ground truth (scoring only) and
    anything else are kept. ``start_s = 0`` returns the data unchanged.

    Raises:
        ValueError: ``start_s`` negative or not finite.
        DatasetError: No GNSS epoch is left.
    """
    start_s = float(start_s)
    if not (np.isfinite(start_s) and start_s >= 0):
        raise ValueError(f'start must be a finite number of seconds >= 0, got {start_s!r}')
    if not drive.gnss:
        raise DatasetError(f'{drive.name}: no GNSS epoch')
    t_start = drive.gnss[0].stamp_ns + int(round(start_s * SECOND_NS))
    epochs = [e for e in drive.gnss if e.stamp_ns >= t_start]
    _check_epochs(drive, epochs, f'a start {start_s:g} s in')
    odo, imu = drive.odometry, drive.imu
    if odo is not None:
        k = odo.stamp_ns >= t_start
        odo = OdometrySeries(odo.stamp_ns[k], odo.speed_mps[k], odo.yaw_rate_rps[k],
                             odo.speed_var[k], odo.yaw_rate_var[k])
    if imu is not None:
        k = imu.stamp_ns >= t_start
        imu = ImuSeries(imu.stamp_ns[k], imu.accel_mps2[k], imu.gyro_rps[k])
    return _with_variant(drive, f'start_{start_s:g}s', {
        'kind': 'start_after', 'start_s': start_s, 'start_ns': int(t_start),
        'epochs_before': len(drive.gnss), 'epochs_kept': len(epochs)},
        gnss=epochs, odometry=odo, imu=imu)


def drive_digest(drive: Drive) -> str:
    """Digest of what the filter and its scoring read from a drive (GNSS epochs,
    odometry, IMU, truth, origin): equal digests, equal runs."""
    h = hashlib.sha256()

    def add(*arrays):
        for a in arrays:
            a = np.ascontiguousarray(a)
            h.update(str((a.dtype.str, a.shape)).encode())
            h.update(a.tobytes())

    h.update(repr(drive.origin_llh).encode())
    for e in drive.gnss:
        add(np.int64(e.stamp_ns), e.sv_pos_ecef_m, e.pr_m, e.var_m2, e.sv_id, e.system,
            e.elevation_deg, e.cn0_dbhz)
    for series in (drive.odometry, drive.imu, drive.truth):
        h.update(type(series).__name__.encode())
        if series is not None:
            add(*(v for v in dataclasses.astuple(series) if v is not None))
    return h.hexdigest()[:16]
