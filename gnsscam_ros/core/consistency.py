"""Is the particle cloud still consistent with the measurements? Detection and recovery.

A particle filter in a street canyon can lock onto a wrong mode: a cloud tens of metres
off that a subset of biased satellites explains, held there by the dynamics while the
rest are taken as outliers. Nothing inside the cloud notices; the protection level,
computed around the wrong estimate, bounds nothing. So every epoch the filter asks the
measurements a second question: would the same cloud explain them better somewhere
else? The alternative is the cloud moved horizontally onto a robust snapshot solution of
the epoch (:func:`snapshot_position`; its height stays the cloud's: snapshot heights in a
canyon are tens of metres off). Both are weighed by the same likelihood with the same
tempering exponent, so their difference ``d = log L(moved) - log L(cloud)`` is a log
likelihood ratio between two hypotheses of equal spread, and its sum over epochs is a
sequential test (Page's CUSUM, ``S <- max(0, S + d - allowance)``,
:class:`ConsistencyMonitor`):

* ``S >= suspect_nats``: inconsistent. The verdict is ERROR and the protection level
  covers the separation between the estimate and the snapshot solution (as it does until
  integrity has settled, whatever ``S``: ``core.filter``). The alarm ends when ``S``
  falls below ``suspect_nats`` again, not when it is back at zero: the allowance is the
  fitted snapshot's expected advantage, so under a consistent cloud ``S`` has almost no
  drift and returns to zero only by chance. Held until zero, three epochs of a
  snapshot pulled off by NLOS (the emulated drive, seed 1: steps of 18-20 times the
  allowance) kept a cloud within 1-5 m of the truth "inconsistent" for 89 of 151
  epochs; ended at the threshold, for 17. Nor is it an alarm while the smoothed
  separation is within the cloud's own protection level (``core.filter``): the truth at
  the snapshot solutions is covered either way. Snapshot errors persist, so the steps
  are correlated and ``S`` can stay at 2-4 nats for minutes with the snapshot solutions
  3-7 m off (emulated bags 3 and 4 were ERROR in half their epochs without this).
* ``S >= recover_nats`` and the smoothed separation beyond the cloud's own protection
  level: recovery, as augmented Monte Carlo localisation injects particles when the
  likelihood drops: a share of the cloud is moved by the smoothed separation onto the
  snapshot solutions (its spread kept), the likelihood decides between the two from then
  on, the test starts again and integrity settles again before it is certified. Within
  the level there is nothing to recover to (the filter gates it, ``core.filter``), and
  ``S`` stays where it is.

Under a consistent cloud ``d`` is close to the allowance on average, not below it: the
robust snapshot solution is not the likelihood's own fit, and on the emulated drive with
white errors its steps averaged 1.12-1.18 nats before tempering against the allowance's
1. So ``S`` drifts up slowly; tempered at 1 Hz (``tau`` = 10 s, one epoch worth 0.05) it
reaches the recovery level within a quarter of an hour, with every epoch independent in
under a minute. That drift is why neither the alarm nor the recovery is raised while the
snapshot solutions are within the cloud's own level. The steps are tempered like the
update, so the time to detect a given separation does not depend on the GNSS rate.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .kernels import snapshot as snapshot_kernels

#: Gauss-Newton steps of the plain least squares and of the robust (Cauchy) refinement.
PLAIN_STEPS = 4
ROBUST_STEPS = 5
#: Cauchy scale of the robust refinement, in standard deviations of the error model.
CAUCHY_SCALE = 2.0
#: Degrees of freedom of the move tested (east, north).
SHIFT_DOF = 2
#: Smoothing time of the separation a recovery moves the cloud by [s].
SHIFT_SMOOTHING_S = 10.0


def snapshot_position(sv_enu_m: np.ndarray, pr_m: np.ndarray, sigma_m: np.ndarray,
                      sys_index: np.ndarray, n_systems: int, start_enu_m: np.ndarray
                      ) -> np.ndarray | None:
    """Robust snapshot position of one epoch in the map frame, or None (too few
    satellites or no convergence).

    Plain weighted least squares first (it does not depend on the starting point beyond
    the linearisation), then iteratively reweighted least squares with a Cauchy loss: the
    solution one epoch's measurements give, whatever the filter believes.

    Args:
        sv_enu_m: (k, 3) satellite positions (Earth rotation corrected) [m].
        pr_m: (k,) pseudoranges [m].
        sigma_m: (k,) error standard deviations [m].
        sys_index: (k,) constellation of each satellite (one clock each).
        n_systems: Number of constellations.
        start_enu_m: (3,) linearisation point [m].
    """
    k = pr_m.shape[0]
    if k < 3 + n_systems + 1:
        return None
    # One compiled pass (core.kernels.snapshot.robust_snapshot): nine numpy lstsq calls on a
    # dozen rows cost more in call overhead than in arithmetic.
    x = np.empty(3)
    try:
        solved = snapshot_kernels.robust_snapshot(
            np.ascontiguousarray(sv_enu_m, dtype=float),
            np.ascontiguousarray(pr_m, dtype=float), np.ascontiguousarray(sigma_m, dtype=float),
            np.ascontiguousarray(sys_index, dtype=np.int64), int(n_systems),
            np.ascontiguousarray(start_enu_m, dtype=float).reshape(3), PLAIN_STEPS,
            ROBUST_STEPS, CAUCHY_SCALE, x)
    except np.linalg.LinAlgError:                   # the SVD did not converge
        return None
    return x if solved else None


@dataclass(frozen=True)
class ConsistencyState:
    """The test after an epoch.

    Attributes:
        statistic_nats: The CUSUM ``S`` [nats].
        step_nats: This epoch's log likelihood ratio ``d`` [nats] (NaN: not tested).
        separation_m: Horizontal distance from the cloud to the snapshot solution,
            smoothed [m] (NaN: none).
        inconsistent: ``S >= suspect_nats`` (the filter's result also needs the
            separation beyond the cloud's own protection level).
        recover: ``S >= recover_nats``: the filter recovers this epoch.
        shift_m: (2,) the smoothed move from the cloud to the snapshot solution, east and
            north [m] (None: none).
    """

    statistic_nats: float = 0.0
    step_nats: float = float('nan')
    separation_m: float = float('nan')
    inconsistent: bool = False
    recover: bool = False
    shift_m: np.ndarray | None = None

    def withdrawn(self) -> 'ConsistencyState':
        """This state with neither alarm nor recovery (the filter's, when the separation
        is within the cloud's own protection level)."""
        # dataclasses.replace's result without its walk over the fields: most epochs of a
        # drive with faults take this.
        return ConsistencyState(**{**vars(self), 'inconsistent': False, 'recover': False})


class ConsistencyMonitor:
    """Page's CUSUM of the log likelihood ratio "cloud moved to the snapshot solution"
    against "cloud where it is".

    The snapshot solution is fitted to the epoch itself, so even a cloud in the right
    place is beaten by it on average: for a Gaussian model the log likelihood ratio of a
    fitted position against the true one is ``chi^2 / 2`` with as many degrees of freedom
    as the move has (two: east and north), one nat per epoch before tempering. That
    expectation is the test's allowance: ``S <- max(0, S + d - tempering * 1)``.

    The move of a recovery is the separation smoothed over ``SHIFT_SMOOTHING_S`` (one
    epoch's snapshot solution in a canyon may be tens of metres off; a lock is a
    separation that persists).

    Args:
        suspect_nats: Statistic from which the cloud counts as inconsistent.
        recover_nats: Statistic at which the filter recovers.
    """

    def __init__(self, suspect_nats: float, recover_nats: float):
        self.suspect_nats = float(suspect_nats)
        self.recover_nats = float(recover_nats)
        self.statistic_nats = 0.0
        self.recoveries = 0
        self.shift_m: np.ndarray | None = None       # smoothed snapshot - cloud, E, N
        self._stamp_ns: int | None = None

    def observe(self, stamp_ns: int, step_nats: float, tempering: float = 0.0,
                shift_m: np.ndarray | None = None) -> ConsistencyState:
        """Fold one epoch into the test.

        Args:
            stamp_ns: Epoch time [ns].
            step_nats: The epoch's log likelihood ratio (NaN: no test this epoch; the
                statistic stays).
            tempering: The epoch's tempering exponent (scales the allowance).
            shift_m: (2,) snapshot solution minus cloud centre, east and north [m].
        """
        if math.isfinite(step_nats) and shift_m is not None:
            self.statistic_nats = max(
                0.0, self.statistic_nats + float(step_nats) - SHIFT_DOF / 2.0 * tempering)
            if self.shift_m is None or self._stamp_ns is None:
                self.shift_m = np.asarray(shift_m, dtype=float).copy()
            else:
                dt_s = max((stamp_ns - self._stamp_ns) * 1e-9, 0.0)
                keep = float(np.exp(-dt_s / SHIFT_SMOOTHING_S))
                self.shift_m = keep * self.shift_m + (1.0 - keep) * np.asarray(shift_m)
            self._stamp_ns = stamp_ns
        # np.hypot (libm's, which math.hypot is not) on the two values as floats.
        separation = (float('nan') if self.shift_m is None
                      else float(np.hypot(*self.shift_m.tolist())))
        return ConsistencyState(
            statistic_nats=self.statistic_nats, step_nats=float(step_nats),
            separation_m=separation, inconsistent=self.statistic_nats >= self.suspect_nats,
            recover=self.statistic_nats >= self.recover_nats and self.shift_m is not None,
            shift_m=None if self.shift_m is None else self.shift_m.copy())

    def recovered(self) -> None:
        """The filter moved the cloud (a state that said ``recover``, and the separation
        beyond the cloud's own level: ``core.filter``); integrity settles again, and the
        test starts again."""
        self.recoveries += 1
        self.statistic_nats = 0.0
        self.shift_m = None

    def reset(self) -> None:
        """Start the test again (a new initialisation); the recovery count stays."""
        self.statistic_nats = 0.0
        self.shift_m = None
        self._stamp_ns = None


class MovedFrom:
    """The place the last recovery moved the cloud from, covered by the protection level
    until integrity has settled again.

    A recovery is a decision the measurements have not confirmed yet: the snapshot
    solutions it followed may be the ones in error (persistent NLOS holds them tens of
    metres off for minutes), and the likelihood may then thin out the half of the cloud
    that stayed where it was. So the level also covers that place, carried with the
    predicted motion, widened by the level the cloud had there (smartLoc GPS only,
    development seeds 1-6: 149 of 188 missed epochs came in the minute after a recovery,
    none with this cover). The verdict is not OK while integrity settles, so the cover
    costs no availability.
    """

    def __init__(self):
        self.position_m: np.ndarray | None = None     # horizontal, map frame
        self.level_m = 0.0

    def start(self, estimate_m: np.ndarray, level_m: float) -> None:
        """A recovery moves the cloud away from ``estimate_m`` (its level ``level_m``)."""
        self.position_m = np.asarray(estimate_m, dtype=float)[:2].copy()
        self.level_m = float(level_m)

    def move(self, motion_m: np.ndarray) -> None:
        """Carry the place with the filter's predicted horizontal motion of one epoch."""
        if self.position_m is not None:
            self.position_m = self.position_m + np.asarray(motion_m, dtype=float)[:2]

    def cover(self, estimate_m: np.ndarray, level_m: float, unsettled: bool) -> float:
        """The protection level ``level_m`` widened to cover the place while integrity
        settles; once it has settled the place is forgotten."""
        if self.position_m is None:
            return level_m
        if not unsettled:
            self.position_m = None
            return level_m
        distance = float(np.hypot(*(np.asarray(estimate_m)[:2] - self.position_m)))
        return max(level_m, distance + self.level_m)
