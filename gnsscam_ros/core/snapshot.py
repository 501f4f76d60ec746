"""Robust snapshot weighted least squares: one epoch, no history.

The baseline the filter is compared with, the first fix that anchors the map frame, and
gnss_node's monitoring fix. Unknowns: ECEF position and one receiver clock per
constellation. A plain Gauss-Newton pass converges from the Earth's centre, then a robust
loss (scipy's Cauchy) down-weights satellites that disagree with the rest.

scipy's optimiser is imported on the first fix, not with this module: importing it takes
0.5-1 s here, which gnss_node would otherwise spend at start-up before it can forward the
first epoch (it publishes an epoch's satellites before it solves the fix); fusion_node
solves a fix while it warms up (``core.warmup``), before it subscribes.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .frames import sagnac_corrected
from .types import GnssEpoch


@dataclass(frozen=True)
class SnapshotFix:
    """A snapshot solution.

    Attributes:
        ecef_m: (3,) position [m].
        clock_m: (S,) receiver clock per constellation in metres of range.
        systems: (S,) constellation identifiers matching ``clock_m``.
        residual_m: (k,) post-fit residuals [m].
        converged: Whether the solver reported success.
    """

    ecef_m: np.ndarray
    clock_m: np.ndarray
    systems: np.ndarray
    residual_m: np.ndarray
    converged: bool


def solve_snapshot(epoch: GnssEpoch, initial_ecef_m: np.ndarray | None = None,
                   robust_scale_m: float = 10.0, measurement_var_m2: float = 10.0,
                   sigma_m: np.ndarray | None = None) -> SnapshotFix:
    """Robust weighted least-squares fix of one validated epoch.

    Args:
        epoch: Epoch with finite values, no duplicates and at least 3 + S satellites.
        initial_ecef_m: Starting point [m]; the Earth's centre when None.
        robust_scale_m: Residual scale where the Cauchy loss starts to saturate [m].
        measurement_var_m2: Floor of the pseudorange variance [m^2].
        sigma_m: (k,) error standard deviations to weigh with [m] (a learned error model's);
            None: the epoch's stated variances, floored at ``measurement_var_m2``.

    Returns:
        The fix; ``converged`` is False when the solver did not succeed.

    Raises:
        ValueError: Fewer satellites than unknowns.
    """
    from scipy.optimize import least_squares     # see the module docstring

    systems, sys_index = np.unique(epoch.system, return_inverse=True)
    n_unknowns = 3 + systems.shape[0]
    if epoch.n_sv < n_unknowns:
        raise ValueError(f'{epoch.n_sv} satellites for {n_unknowns} unknowns')
    sigma = (np.sqrt(np.maximum(epoch.var_m2, measurement_var_m2)) if sigma_m is None
             else np.asarray(sigma_m, dtype=float))
    x0 = np.zeros(n_unknowns)
    if initial_ecef_m is not None:
        x0[:3] = initial_ecef_m

    def residual(x: np.ndarray, sv: np.ndarray) -> np.ndarray:
        return (epoch.pr_m - np.linalg.norm(sv - x[:3], axis=1) - x[3:][sys_index]) / sigma

    def jacobian(x: np.ndarray, sv: np.ndarray) -> np.ndarray:
        los = (sv - x[:3]) / np.linalg.norm(sv - x[:3], axis=1)[:, None]
        jac = np.zeros((epoch.n_sv, n_unknowns))
        jac[:, :3] = los
        jac[np.arange(epoch.n_sv), 3 + sys_index] = -1.0
        return jac / sigma[:, None]

    sv = epoch.sv_pos_ecef_m
    fit = least_squares(residual, x0, jac=jacobian, args=(sv,), method='lm')
    # Earth rotation during signal flight, then the robust pass from the plain solution.
    sv = sagnac_corrected(epoch.sv_pos_ecef_m, fit.x[:3])
    fit = least_squares(residual, fit.x, jac=jacobian, args=(sv,), method='lm')
    robust = least_squares(residual, fit.x, jac=jacobian, args=(sv,), loss='cauchy',
                           f_scale=robust_scale_m / np.sqrt(measurement_var_m2),
                           method='trf')
    x = robust.x
    return SnapshotFix(ecef_m=x[:3].copy(), clock_m=x[3:].copy(), systems=systems,
                       residual_m=residual(x, sv) * sigma,
                       converged=bool(robust.success and np.all(np.isfinite(x))))
