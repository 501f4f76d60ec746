"""Checks of a GNSS epoch before it is used: the arrays fit together, and per satellite
finite and plausible values, no duplicates, the masks, the satellite count.

numpy only (no compiled kernel): gnss_node checks every epoch with these and imports
nothing of the filter's kernels (numba), so that it starts quickly; the filter
(``core.filter``) runs the same checks through ``core.gnss``, which re-exports them.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .types import GnssEpoch

#: Most satellites one epoch uses. The update's arrays are particles x motion samples x
#: satellites, so the satellite count sets what one epoch costs (memory and time; a
#: configuration whose sizes would exceed the memory budget of ``core.config`` with this
#: many uses fewer, ``FilterConfig.satellite_limit``); an epoch with more usable
#: satellites keeps the strongest by C/N0 (unknown C/N0 last, then the order received).
#: A receiver tracking GPS, GLONASS, Galileo, BeiDou and QZSS sees 40-60 satellites under
#: open sky (one row each: rows of the same satellite are duplicates), so 64 drops nothing
#: real, and 64 well-spread satellites fix the position as well as more would.
MAX_EPOCH_SATELLITES = 64
#: Farthest a satellite may be from the Earth's centre [m]: GNSS orbits reach 42,164 km
#: (geostationary); beyond twice that a position is corrupt, and its square (in the range
#: arithmetic) must stay far from overflow.
MAX_SATELLITE_RADIUS_M = 1e8
#: Longest pseudorange taken [m]: geometric ranges are below 4e7 m, receiver clock offsets
#: are steered within a millisecond (3e5 m).
MAX_PSEUDORANGE_M = 1e8
#: Largest pseudorange variance taken [m^2] (a standard deviation of 1,000 km carries no
#: position information, and its inverse must not underflow in the update weights).
MAX_VARIANCE_M2 = 1e12


def epoch_problem(epoch: GnssEpoch) -> str | None:
    """Why an epoch cannot be checked at all (None when its arrays fit together): an
    integer stamp and one row per satellite in every array. Values are checked per
    satellite by :func:`check_epoch`."""
    if not isinstance(epoch.stamp_ns, (int, np.integer)) or isinstance(epoch.stamp_ns, bool):
        return f'stamp must be an integer number of nanoseconds, got {epoch.stamp_ns!r}'
    try:
        k = int(np.shape(epoch.pr_m)[0]) if np.ndim(epoch.pr_m) == 1 else -1
        shapes_ok = (k >= 0 and np.shape(epoch.sv_pos_ecef_m) == (k, 3)
                     and all(np.shape(getattr(epoch, name)) == (k,)
                             for name in ('var_m2', 'sv_id', 'system', 'elevation_deg',
                                          'cn0_dbhz')))
    except TypeError:
        shapes_ok = False
    if not shapes_ok:
        return 'the arrays of the epoch do not hold one row per satellite'
    return None


@dataclass(frozen=True)
class GnssCheck:
    """Outcome of validating one epoch.

    Attributes:
        keep: (k,) mask of the satellites that passed every check.
        rejected: ``{reason: count}`` for the satellites that did not.
        usable: Whether enough satellites remain for a position update.
        reason: Why the epoch is unusable ('' when usable).
    """

    keep: np.ndarray
    rejected: dict = field(default_factory=dict)
    usable: bool = True
    reason: str = ''


def check_epoch(epoch: GnssEpoch, min_satellites: int = 4, elevation_mask_deg: float = 0.0,
                cn0_mask_dbhz: float = 0.0,
                max_satellites: int = MAX_EPOCH_SATELLITES) -> GnssCheck:
    """Validate an epoch: non-finite or implausible values, duplicates, masks, satellite
    count.

    Satellites with a NaN elevation or C/N0 are kept (unknown is not below the mask).
    Duplicated (system, sv_id) pairs are all dropped: there is no telling which is right.
    Positions, pseudoranges and variances beyond ``MAX_SATELLITE_RADIUS_M``,
    ``MAX_PSEUDORANGE_M`` and ``MAX_VARIANCE_M2`` are dropped ('out_of_range'); of more
    than ``max_satellites`` (at most ``MAX_EPOCH_SATELLITES``) remaining, the strongest by C/N0
    are kept ('satellite_limit').
    """
    k = epoch.n_sv
    codes = satellite_reasons(epoch, float(elevation_mask_deg), float(cn0_mask_dbhz))
    keep = codes == 0
    # One count for the test and the number kept (keep.all() and keep.sum(): 1.5 us more).
    n_keep = int(np.count_nonzero(keep))
    rejected: dict[str, int] = {}
    if n_keep < k:
        counts = np.bincount(codes, minlength=len(SATELLITE_REASONS) + 1)
        rejected = {reason: int(n) for reason, n in zip(SATELLITE_REASONS, counts[1:]) if n}

    def drop(mask: np.ndarray, reason: str) -> None:
        nonlocal keep
        hit = mask & keep
        if hit.any():
            rejected[reason] = rejected.get(reason, 0) + int(hit.sum())
            keep &= ~hit

    limit = min(int(max_satellites), MAX_EPOCH_SATELLITES)
    if n_keep > limit:
        # Strongest first; unknown (NaN) or absurd (infinite) C/N0 sorts last, equal ones
        # keep their order.
        cn0 = np.where(np.isfinite(epoch.cn0_dbhz), epoch.cn0_dbhz, -np.inf)
        order = np.flatnonzero(keep)[np.argsort(-cn0[keep], kind='stable')]
        over = np.zeros(k, dtype=bool)
        over[order[limit:]] = True
        drop(over, 'satellite_limit')
        n_keep = limit
    if n_keep < min_satellites:
        return GnssCheck(keep, rejected, False,
                         f'{n_keep} usable satellites, at least {min_satellites} needed')
    return GnssCheck(keep, rejected)


def kept_satellites(epoch: GnssEpoch, check: GnssCheck) -> GnssEpoch:
    """The satellites of an epoch that passed its checks: the epoch itself when all did
    (the usual case; a subset's eight copies cost about 10 us of a small epoch), so a
    caller that keeps the arrays must copy them (``gnss.prepare_epoch`` does)."""
    return epoch if check.keep.all() else epoch.subset(check.keep)


#: The reasons :func:`satellite_reasons` gives, by code (0: kept).
SATELLITE_REASONS = ('non_finite', 'non_positive', 'out_of_range', 'duplicate',
                     'elevation_mask', 'cn0_mask')


def satellite_reasons(epoch: GnssEpoch, elevation_mask_deg: float = 0.0,
                      cn0_mask_dbhz: float = 0.0) -> np.ndarray:
    """Why each satellite of an epoch is dropped: (k,) codes, 0 = kept, else 1 + the index
    in ``SATELLITE_REASONS`` of the first check it fails, in that order.

    Non-finite pseudorange, position or variance; non-positive pseudorange or variance;
    position radius, pseudorange or variance beyond its maximum; a (system, satellite
    number) that occurs more than once in the epoch (every copy); elevation or C/N0 below
    its mask (NaN is not below). A few whole-array operations on at most a few hundred
    satellites: tens of microseconds.
    """
    pr = np.asarray(epoch.pr_m, dtype=float)
    sv = np.asarray(epoch.sv_pos_ecef_m, dtype=float)
    var = np.asarray(epoch.var_m2, dtype=float)
    codes = np.zeros(pr.shape[0], dtype=np.int8)
    # From the last reason to the first: an earlier reason overwrites a later one.
    with np.errstate(invalid='ignore', over='ignore'):
        codes[np.asarray(epoch.cn0_dbhz, dtype=float) < cn0_mask_dbhz] = 6
        codes[np.asarray(epoch.elevation_deg, dtype=float) < elevation_mask_deg] = 5
        key = satellite_key(epoch, 100000)
        if len(set(key.tolist())) < key.shape[0]:      # (a set is the quicker screen)
            order = np.argsort(key)
            same = key[order[1:]] == key[order[:-1]]
            codes[order[1:][same]] = 4
            codes[order[:-1][same]] = 4
        radius2 = np.einsum('ij,ij->i', sv, sv)
        codes[(radius2 > MAX_SATELLITE_RADIUS_M ** 2)
              | (pr > MAX_PSEUDORANGE_M) | (var > MAX_VARIANCE_M2)] = 3
        codes[(pr <= 0.0) | (var <= 0.0)] = 2
        # The sum is a quick screen: NaN or inf when any value is (or it overflows; the
        # positions' squares stand for the positions).
        if not np.isfinite(pr + var + radius2).all():
            codes[~(np.isfinite(pr) & np.isfinite(var) & np.isfinite(sv).all(axis=1))] = 1
    return codes


def satellite_key(epoch: GnssEpoch, base: int) -> np.ndarray:
    """``system * base + sv_id`` (int64): one key per satellite."""
    return epoch.system.astype(np.int64) * base + epoch.sv_id.astype(np.int64)


#: Post-fit residuals this many times their stated standard deviation (robust RMS) mean
#: that the stated variances are far too small or a correction is missing
#: (``msg_adapters.wire``'s input contract); gnss_node warns.
IMPLAUSIBLE_RESIDUAL_RATIO = 5.0


def residual_ratio(residual_m: np.ndarray, var_m2: np.ndarray) -> float:
    """Robust RMS of post-fit residuals normalised by their stated standard deviations
    (1.48 x median |r / sigma|; ~1 when the variances are right). NaN without residuals."""
    r = np.asarray(residual_m, dtype=float)
    sigma = np.sqrt(np.asarray(var_m2, dtype=float))
    ok = np.isfinite(r) & (sigma > 0)
    if not ok.any():
        return float('nan')
    return float(1.4826 * np.median(np.abs(r[ok] / sigma[ok])))
