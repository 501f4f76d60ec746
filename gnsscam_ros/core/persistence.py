"""How much of the snapshot solutions' error persists, measured without ground truth.

The GNSS likelihood is tempered because its errors persist: an epoch counted as new
evidence when its error is the last one's again makes the filter bold where it is wrong.
How much of the error persists differs by receiver and street. Code noise is white: a
drive in open sky gives snapshot solutions whose errors are new every second, and
tempering them as if they persisted leaves the cloud several times wider than its errors.
Multipath and NLOS in a canyon persist for tens of seconds. So the share that persists is
measured, on the quantity the tempering is about: the position each epoch gives alone.

The snapshot solution minus the dead-reckoned path (the filter's own motion prediction
summed, never corrected by GNSS) is the snapshot error plus a slow drift. Its
semivariogram ``gamma(L) = E |d(t) - d(t - L)|^2 / 2`` over the window gives, at a short
lag, the part of the error that is new within ``SHORT_LAG_S`` and, at a long lag, nearly
all of it; ``1 - gamma(short) / gamma(long)`` is the persisting share ``s``. For a white
error it is 0; for a first-order Gauss-Markov error of correlation time 10 s it is 0.88.
Both lags are in seconds, so ``s`` does not depend on the GNSS rate. Medians, not means,
of the squared increments: one NLOS jump of a snapshot must not decide the share. The
drift of the dead reckoning over the long lag can only add to ``gamma(long)``, that is to
``s``: it errs towards tempering, never towards boldness. No feedback from the filter's
GNSS corrections enters either term.

Until ``MIN_PAIRS`` pairs at each lag are in the window the share is 1 (all of the error
persists: the tempering of a fully correlated error).
"""
from __future__ import annotations

import math

import numpy as np

from .kernels import persistence as persistence_kernels

#: Lag at which the semivariogram holds the new part of the error [s].
SHORT_LAG_S = 1.0
#: Lag at which it holds nearly all of it [s] (several correlation times of code noise
#: and short multipath; within the window).
LONG_LAG_S = 16.0
#: A pair is at a lag if its spacing is within this share of it.
PAIR_TOLERANCE = 0.25
#: Pairs at each lag before the measured share replaces the prior share of 1.
MIN_PAIRS = 20


class SnapshotPersistence:
    """Persisting share of the snapshot solutions' horizontal error over a window.

    Args:
        window_s: Length of the window [s] (the error model's).
    """

    def __init__(self, window_s: float = 60.0):
        self.window_s = float(window_s)
        self._path_m = np.zeros(2)             # dead-reckoned path since the start
        # The window's stamps [ns] and offsets [m] are rows ``_first .. _first + _count``
        # of two buffers that grow as needed: the kernels read them as they stand, with
        # no per-epoch conversion of a window of hundreds of epochs (10 Hz, 60 s).
        self._stamps = np.empty(64, dtype=np.int64)
        self._offsets = np.empty((64, 2))
        self._first = 0
        self._count = 0
        self._share = 1.0                      # of the window as it stands

    def move(self, motion_xy_m: np.ndarray) -> None:
        """Add the filter's predicted horizontal motion of one epoch [m]. A motion that is
        not finite (a poisoned state, which the filter discards) starts the window again."""
        step = np.asarray(motion_xy_m, dtype=float)[:2]
        # math.isfinite on the two values: np.isfinite and np.all dispatch for 2 us.
        if not all(map(math.isfinite, step.tolist())):
            self.reset()
            return
        self._path_m = self._path_m + step

    def observe(self, stamp_ns: int, snapshot_xy_m: np.ndarray) -> None:
        """Add one epoch's snapshot solution (horizontal, map frame) [m]; one that is not
        finite is left out."""
        offset = np.asarray(snapshot_xy_m, dtype=float)[:2] - self._path_m
        if not all(map(math.isfinite, offset.tolist())):
            return
        horizon = stamp_ns - int(self.window_s * 1e9)
        first, count = self._first, self._count
        while count and self._stamps[first] < horizon:
            first += 1
            count -= 1
        if first + count == self._stamps.shape[0]:
            # Full at the end: move the window to the front, doubling the buffers when
            # it fills more than half of them.
            size = self._stamps.shape[0] * (2 if 2 * count > self._stamps.shape[0] else 1)
            stamps, offsets = np.empty(size, dtype=np.int64), np.empty((size, 2))
            stamps[:count] = self._stamps[first:first + count]
            offsets[:count] = self._offsets[first:first + count]
            self._stamps, self._offsets, first = stamps, offsets, 0
        self._stamps[first + count] = int(stamp_ns)
        self._offsets[first + count] = offset
        self._first, self._count = first, count + 1
        self._share = self._measure()

    @staticmethod
    def _median_increments_m2(t: np.ndarray, d: np.ndarray) -> tuple[float, int, float, int]:
        """Median squared increments of the offsets ``d`` (n, 2) at times ``t`` (n,) about
        ``SHORT_LAG_S`` and about ``LONG_LAG_S`` apart, each with its pairs (one compiled
        call: ``core.kernels.persistence``)."""
        return persistence_kernels.median_increments_m2(
            t, np.ascontiguousarray(d, dtype=float), int(SHORT_LAG_S * 1e9),
            int(LONG_LAG_S * 1e9), PAIR_TOLERANCE)

    @property
    def persistent_share(self) -> float:
        """Share of the snapshot error that persists beyond ``SHORT_LAG_S`` (0..1)."""
        return self._share

    def _measure(self) -> float:
        if self._count < 2:
            return 1.0
        window = slice(self._first, self._first + self._count)
        short, n_short, long, n_long = self._median_increments_m2(self._stamps[window],
                                                                  self._offsets[window])
        if n_short < MIN_PAIRS or n_long < MIN_PAIRS or not long > 0.0:
            return 1.0
        share = 1.0 - short / long
        # np.clip's and np.isfinite's results on a float, without their dispatch.
        return min(max(share, 0.0), 1.0) if math.isfinite(share) else 1.0

    def reset(self) -> None:
        """Forget the window (a new drive or a reset filter)."""
        self.__init__(self.window_s)


def persisting_worth(dt_s: float, correlation_time_s: float) -> float:
    """What an epoch ``dt_s`` after the last is worth if all of its error persists.

    Errors that follow a first-order Gauss-Markov process with correlation time ``tau``
    make a new epoch worth ``c = (1 - phi) / (1 + phi) = tanh(dt / (2 tau))`` of an
    independent one, ``phi = exp(-dt / tau)`` (the information an AR(1) sample adds about
    a constant): ``dt / (2 tau)`` per epoch at a high rate, one per epoch when they are far
    apart, so that the information per second of driving is the same at any GNSS rate.
    ``tau <= 0``: every epoch independent (1).
    """
    if correlation_time_s <= 0.0:
        return 1.0
    return float(np.tanh(max(dt_s, 1e-3) / (2.0 * correlation_time_s)))


def tempering_exponent(persistent_share: float, persisting: float) -> float:
    """Tempering exponent of an epoch's GNSS log-likelihood, from what it is worth if all
    of its error persists (``persisting``, :func:`persisting_worth`).

    Only the share ``s`` of the error that persists (measured from the snapshot solutions,
    :class:`SnapshotPersistence`; 1 until measured) is correlated; the rest is new at
    every epoch. With the error variance split so, an epoch is worth
    ``1 / ((1 - s) + s / c)``: ``c`` when all of it persists, 1 when none does.
    """
    return 1.0 / ((1.0 - persistent_share) + persistent_share / persisting)
