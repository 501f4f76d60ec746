"""Bias hypotheses: what slowly varying pseudorange biases do to the estimate.

In a city the estimate is wrong mostly because of NLOS and multipath biases that persist
for tens of seconds (smartLoc Berlin, residuals at the true position: robust SD 15 m,
correlation 0.94 after 1 s, 0.52 after 30 s, 0.30 after 60 s; their size falls with C/N0).
Motion perturbations alone cannot represent them, so each of the M posteriors of the risk
bound also carries one draw of a bias model, in the spirit of RAIM solution separation:

* per satellite, a first-order Gauss-Markov bias ``b_k`` with correlation time ``tau`` and
  a standard deviation that grows as C/N0 falls and scales with how much the pseudoranges
  disagree at the estimate (:class:`BiasModel`);
* its effect on the estimate, ``o_j``, propagated through the filter's own gain. With the
  prior and posterior position covariances ``P-`` and ``P+`` of the particle set and the
  linearised GNSS update (rows ``g_k = -u_k``, the negated unit line of sight; weights
  ``W = diag(tempering * inlier share / sigma^2)``; the per-constellation clocks projected
  out, ``Wp = W - W S (S^T W S)^-1 S^T W``), the information form of the update moves an
  offset as ``o+ = P (P-^-1 o- + G^T Wp b)`` with ``P = (P-^-1 + Lambda)^-1`` and
  ``Lambda`` the information the particle set gained this epoch (``P+^-1 - P-^-1``, its
  negative part clipped: a noisy covariance never inflates an offset). A constant bias
  converges to the weighted-least-squares offset ``(G^T Wp G)^-1 G^T Wp b``; information
  from elsewhere (the camera) shrinks it, exactly as it shrinks the posterior.

Each hypothesis also carries one *hidden fault* (:func:`with_hidden_faults`): a bias on one
satellite of the size its own residual cannot reveal. Spread over all satellites, biases
average out in the estimate as the satellites grow in number; a single one does not, and
where the satellites are few (one constellation, five to seven of them) the residuals
show almost nothing of it (leverage ~0.8; smartLoc GLONASS only: errors of 25-45 m for
minutes while every residual looked like noise).

The bound does not count twice what the particle set already holds
(:func:`beyond_cloud`). The GNSS likelihood is tempered for the persisting part of the
errors (``core.filter``), so the set's own spread already stands for the estimate error a
Gauss-Markov bias of that size leaves; the Gauss-Markov part of the offsets adds only what
exceeds that spread. The hidden faults are in no part of the likelihood and add in full;
the hypotheses track their part of the offsets separately (:attr:`BiasHypotheses.
fault_offsets_m`), which the update moves like the rest (it is linear in the biases).
The filter shrinks only once the error model has measured how long the errors persist
(``AdaptiveErrorModel.correlation_measured``): with epochs too far apart to measure it,
nothing says the set holds them, and every offset counts in full.

The estimate itself is unchanged; the offsets only displace the posteriors the bound sees
(``integrity.PosteriorSet``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .gnss_checks import MAX_EPOCH_SATELLITES
from .kernels import bias as bias_kernels

# Bias models of the posteriors behind the risk bound (the ``bias_model`` parameter).
BIAS_LEARNED = 'learned'  # Gauss-Markov bias per satellite, size: learned error model
BIAS_CN0 = 'cn0'         # Gauss-Markov bias per satellite, size from C/N0 and constants
BIAS_NONE = 'none'       # motion perturbations only (the paper's construction)
BIAS_MODELS = (BIAS_LEARNED, BIAS_CN0, BIAS_NONE)

#: Covariance floor added before inverting particle covariances [m^2]: a set collapsed by
#: resampling must not give a singular matrix.
COV_FLOOR_M2 = 1e-4
#: A satellite unseen for this many correlation times has forgotten its bias.
FORGET_AFTER_TAU = 5.0
#: Most satellites whose biases are remembered (each holds M values): four times the
#: satellites one epoch may use (``gnss.MAX_EPOCH_SATELLITES``), so that the sky turning over
#: keeps its history while a stream of made-up satellite numbers cannot grow the table.
MAX_TRACKED_SATELLITES = 256
#: Stamp of a row of the bias table that no satellite holds (never forgotten).
_FREE_ROW_NS = np.iinfo(np.int64).max


@dataclass(frozen=True)
class BiasModel:
    """Gauss-Markov pseudorange bias per satellite, its size from C/N0 and the residuals.

    ``sigma_k = max(floor_m, residual_scale * s) * sqrt(1 + 10^(-(C/N0_k - knee) / 10))``
    with ``s`` the smoothed residual RMS at the estimate (:meth:`BiasHypotheses.
    observe_residuals`): how much the pseudoranges disagree where the vehicle is, so that
    a street canyon (smartLoc: s ~ 20 m) gets larger hypotheses than open sky (the emulated
    drive: s ~ 5 m). Below the knee the bias grows 10 dB per decade of C/N0 (smartLoc:
    median |residual| 35 m below 30 dB-Hz, 7 m above 40 dB-Hz).

    Attributes:
        floor_m: Smallest bias standard deviation at high C/N0 [m].
        residual_scale: Bias standard deviation at high C/N0 per metre of residual RMS.
        cn0_knee_dbhz: C/N0 at which the C/N0 term equals the floor [dB-Hz]; unknown
            (NaN) C/N0 is taken as the knee.
        correlation_time_s: Correlation time tau of the biases [s].
        residual_time_s: Smoothing time of the residual RMS [s].
    """

    floor_m: float
    residual_scale: float
    cn0_knee_dbhz: float
    correlation_time_s: float
    residual_time_s: float = 10.0

    def sigma_m(self, cn0_dbhz: np.ndarray, residual_rms_m: float) -> np.ndarray:
        """Bias standard deviation of each satellite [m]."""
        cn0 = np.asarray(cn0_dbhz, dtype=float)
        cn0 = np.where(np.isfinite(cn0), cn0, self.cn0_knee_dbhz)
        level = max(self.floor_m, self.residual_scale * residual_rms_m)
        return level * np.sqrt(1.0 + 10.0 ** (-(cn0 - self.cn0_knee_dbhz) / 10.0))


def leverages(line_of_sight: np.ndarray, weights: np.ndarray, sys_index: np.ndarray,
              n_systems: int) -> np.ndarray:
    """Diagonal of the weighted least-squares hat matrix, position and one clock per
    constellation estimated: ``h_k``, the share of satellite k's own bias that the
    estimate absorbs, (k,) in [0, 1] (``core.kernels.bias.leverages``)."""
    return bias_kernels.leverages(_array(line_of_sight), _array(weights),
                                  np.ascontiguousarray(sys_index, dtype=np.int64),
                                  int(n_systems))


def hidden_fault_sizes(core_sd_m: np.ndarray, leverage: np.ndarray, core_sds: float,
                       largest_m: np.ndarray) -> np.ndarray:
    """The bias each satellite can carry unseen, (k,) [m].

    A bias ``b`` on satellite k leaves ``(1 - h_k) b`` in its own residual, whose noise
    has the spread ``sigma_k sqrt(1 - h_k)`` (``sigma_k`` the core of its signal class):
    ``b = c sigma_k / sqrt(1 - h_k)`` stays within ``c`` of that spread. Capped at
    ``largest_m``, the largest error the error model knows (a satellite without
    redundancy, ``h_k = 1``, would otherwise hide any bias).
    """
    # One compiled call: some six numpy calls on a dozen values cost more than their
    # arithmetic.
    return bias_kernels.hidden_fault_sizes(_array(core_sd_m), _array(leverage),
                                           float(core_sds), _array(largest_m))


def with_hidden_faults(biases_m: np.ndarray, sizes_m: np.ndarray) -> np.ndarray:
    """The biases (k, M) with one hidden fault per hypothesis added: hypothesis m biases
    satellite ``m mod k`` by ``+size`` in its first round over the satellites, ``-size``
    in the next, and so on (a copy; the Gauss-Markov draws are unchanged)."""
    if biases_m.shape[0] == 0:
        return biases_m
    return bias_kernels.with_hidden_faults(_array(biases_m), _array(sizes_m))


def beyond_cloud(offsets_m: np.ndarray, fault_offsets_m: np.ndarray,
                 cloud_cov_m2: np.ndarray, dims: int) -> np.ndarray:
    """The offsets the bound displaces the posteriors by, (M, 3) [m]: the hidden-fault
    part in full, the Gauss-Markov part shrunk to what exceeds the particle set's spread
    (module docstring).

    With ``O`` the second moment of the Gauss-Markov offsets ``g_j = o_j - f_j`` and ``C``
    the set's covariance (the first ``dims`` axes: east-north, or all three), the part
    kept is ``g_j' = A g_j`` with ``A = (O - C)_+^(1/2) O^(-1/2)``, so that
    ``E[g' g'^T] = (O - C)_+`` (the positive part): a set as wide as the biases' effect
    takes no Gauss-Markov offset at all, a narrow one nearly the whole. The moment is
    about zero, not the offsets' mean: the mean is an estimate error too.

    Args:
        offsets_m: (M, 3) the offsets of the hypotheses (:attr:`BiasHypotheses.offsets_m`).
        fault_offsets_m: (M, 3) their hidden-fault part.
        cloud_cov_m2: (3, 3) position covariance of the particle set.
        dims: 2 (horizontal risk) or 3.
    """
    return bias_kernels.beyond_cloud(_array(offsets_m), _array(fault_offsets_m),
                                     _array(cloud_cov_m2), int(dims))


def _array(values) -> np.ndarray:
    return np.ascontiguousarray(values, dtype=float)


class BiasHypotheses:
    """M bias hypotheses and the estimate errors they imply.

    Args:
        model: The bias model.
        n_hypotheses: M.
        rng: Random generator.
    """

    def __init__(self, model: BiasModel, n_hypotheses: int, rng: np.random.Generator):
        self.model = model
        self.n = int(n_hypotheses)
        self.rng = rng
        self.offsets_m = np.zeros((self.n, 3))
        # The hidden faults' part of ``offsets_m`` (module docstring) [m].
        self.fault_offsets_m = np.zeros((self.n, 3))
        # Smoothed residual variance at the estimate [m^2] and its stamp (None: none yet).
        self.residual_var_m2: float | None = None
        self._residual_stamp_ns: int | None = None
        # The remembered biases: (system, sv) key -> row of a table of their (M,) biases
        # [m] and the stamp [ns] they are at, so that an epoch gathers, steps and stores
        # them in one compiled call (core.kernels.bias.advance_biases). The table grows
        # in steps up to what MAX_TRACKED_SATELLITES and one epoch's satellites need.
        self._rows: dict[int, int] = {}
        self._row_keys: list = []
        self._bias_m = np.zeros((0, self.n))
        self._bias_stamp_ns = np.zeros(0, dtype=np.int64)
        self._free_rows: list[int] = []

    def biases_at(self, stamp_ns: int, keys: np.ndarray, cn0_dbhz: np.ndarray,
                  sigma_m: np.ndarray | None = None,
                  correlation_time_s: float | None = None) -> np.ndarray:
        """Advance the biases of the satellites in view to ``stamp_ns``, (k, M) [m].

        ``sigma_m`` (k,) gives each satellite's bias standard deviation [m] and
        ``correlation_time_s`` their correlation time [s] (the learned error model's);
        None takes them from the model (its C/N0 law, its correlation time).

        A satellite seen for the first time (or again after a long gap) draws its biases
        from the stationary distribution; one seen before moves by the Gauss-Markov step
        ``b <- phi b + sqrt(1 - phi^2) sigma xi``, ``phi = exp(-dt / tau)``, with the sigma
        of its current C/N0.
        """
        if sigma_m is None:
            rms = (0.0 if self.residual_var_m2 is None
                   else float(np.sqrt(self.residual_var_m2)))
            sigma = self.model.sigma_m(cn0_dbhz, rms)
        else:
            sigma = np.asarray(sigma_m, dtype=float)
        tau = (self.model.correlation_time_s if correlation_time_s is None
               else float(correlation_time_s))
        # One call: the same stream as one draw of M per satellite, in order.
        draws = self.rng.standard_normal((keys.shape[0], self.n))
        key_list = keys.tolist()
        if len(set(key_list)) < len(key_list):
            out = self._advance_one_by_one(stamp_ns, key_list, sigma, draws, tau)
        else:
            rows = [self._rows.get(key, -1) for key in key_list]
            if -1 in rows:
                rows = [self._take_row(key) if row < 0 else row
                        for key, row in zip(key_list, rows)]
            rows = np.array(rows, dtype=np.int64)
            # Every satellite at once: a new one draws from the stationary distribution
            # (phi = 0), one at or after this stamp keeps its bias (phi = 1), the rest
            # decay by numpy's exp (the kernels' rounds differently).
            decay = (np.exp(bias_kernels.decay_exponents(self._bias_stamp_ns, rows, stamp_ns,
                                                         tau))
                     if tau > 0 else np.zeros(rows.shape[0]))
            out = bias_kernels.advance_biases(self._bias_m, self._bias_stamp_ns, rows, decay,
                                              _array(sigma), draws, stamp_ns)
        horizon = stamp_ns - int(FORGET_AFTER_TAU * tau * 1e9)
        for row in np.flatnonzero(self._bias_stamp_ns < horizon).tolist():
            self._free_row(row)
        excess = len(self._rows) - MAX_TRACKED_SATELLITES
        if excess > 0:
            # The satellites seen longest ago go first (those in view now are the newest;
            # of those seen as long ago, the first remembered).
            for key in sorted(self._rows,
                              key=lambda k: self._bias_stamp_ns[self._rows[k]])[:excess]:
                self._free_row(self._rows[key])
        return out

    def _take_row(self, key: int) -> int:
        """A free row of the bias table for a satellite not remembered, holding no bias
        yet (``core.kernels.bias.NEW_ROW_NS``)."""
        if not self._free_rows:
            size = self._bias_stamp_ns.shape[0]
            grown = max(min(2 * size, MAX_TRACKED_SATELLITES + MAX_EPOCH_SATELLITES),
                        size + 16)
            self._bias_m = np.concatenate((self._bias_m, np.zeros((grown - size, self.n))))
            self._bias_stamp_ns = np.concatenate(
                (self._bias_stamp_ns, np.full(grown - size, _FREE_ROW_NS, dtype=np.int64)))
            self._row_keys.extend([None] * (grown - size))
            self._free_rows = list(range(grown - 1, size - 1, -1))
        row = self._free_rows.pop()
        self._rows[key] = row
        self._row_keys[row] = key
        self._bias_m[row] = 0.0
        self._bias_stamp_ns[row] = bias_kernels.NEW_ROW_NS
        return row

    def _free_row(self, row: int) -> None:
        """Forget the satellite of a row of the bias table."""
        del self._rows[self._row_keys[row]]
        self._row_keys[row] = None
        self._bias_stamp_ns[row] = _FREE_ROW_NS
        self._free_rows.append(row)

    def _advance_one_by_one(self, stamp_ns: int, keys: list, sigma: np.ndarray,
                            draws: np.ndarray, tau: float) -> np.ndarray:
        """:meth:`biases_at` for an epoch that lists a satellite twice (the second sees
        the first's bias)."""
        out = np.empty((len(keys), self.n))
        for i, key in enumerate(keys):
            row = self._rows.get(key)
            if row is None:
                bias = sigma[i] * draws[i]
                row = self._take_row(key)
            elif stamp_ns <= self._bias_stamp_ns[row]:
                bias = self._bias_m[row]
            else:
                then = int(self._bias_stamp_ns[row])
                phi = np.exp(-(stamp_ns - then) * 1e-9 / tau) if tau > 0 else 0.0
                bias = phi * self._bias_m[row] + np.sqrt(1.0 - phi * phi) * sigma[i] * draws[i]
            self._bias_m[row] = bias
            self._bias_stamp_ns[row] = stamp_ns
            out[i] = bias
        return out

    def observe_residuals(self, stamp_ns: int, residual_m: np.ndarray, inlier: np.ndarray,
                          n_unknowns: int) -> float:
        """Fold one epoch's residuals at the estimate into the smoothed residual variance.

        ``s^2 = sum v_k r_k^2 / sum v_k * V / (V - p)`` with the inlier probabilities ``v``
        of the robust likelihood, ``V = sum v`` and ``p`` unknowns (position and clocks):
        satellites the filter rejects (faults) do not move the filter and do not count;
        the factor restores the part of the errors the geometry absorbs (``(V - p) / V``
        on average). Smoothed exponentially over ``residual_time_s``.

        Returns:
            The smoothed residual standard deviation [m].
        """
        total = float(inlier.sum())
        dof = max(total - n_unknowns, 0.25 * total, 1e-9)
        var = float(inlier @ residual_m ** 2) / dof
        if self.residual_var_m2 is None:
            self.residual_var_m2 = var
        else:
            dt_s = max((stamp_ns - self._residual_stamp_ns) * 1e-9, 0.0)
            tau = self.model.residual_time_s
            keep = float(np.exp(-dt_s / tau)) if tau > 0 else 0.0
            self.residual_var_m2 = keep * self.residual_var_m2 + (1.0 - keep) * var
        self._residual_stamp_ns = stamp_ns
        return float(np.sqrt(self.residual_var_m2))

    def update(self, biases_m: np.ndarray, line_of_sight: np.ndarray, weights: np.ndarray,
               sys_index: np.ndarray, n_systems: int, prior_cov_m2: np.ndarray,
               posterior_cov_m2: np.ndarray, fault_biases_m: np.ndarray | None = None
               ) -> np.ndarray:
        """Move the offsets through one GNSS update (see the module docstring).

        Args:
            biases_m: (k, M) biases of the satellites used, hidden faults included.
            line_of_sight: (k, 3) unit vectors from the receiver to the satellites.
            weights: (k,) update weights ``tempering * inlier share / sigma^2`` [1/m^2].
            sys_index: (k,) constellation index (one clock each).
            n_systems: Number of constellations.
            prior_cov_m2: (3, 3) position covariance of the prior set.
            posterior_cov_m2: (3, 3) position covariance of the posterior set.
            fault_biases_m: (k, M) the hidden faults' part of ``biases_m`` (None: none);
                it moves :attr:`fault_offsets_m`.

        Returns:
            (M, 3) offsets after the update [m].
        """
        biases = _array(biases_m)
        faults = (np.empty((biases.shape[0], 0)) if fault_biases_m is None
                  else _array(fault_biases_m))
        self.offsets_m, self.fault_offsets_m = bias_kernels.update_offsets(
            _array(self.offsets_m), _array(self.fault_offsets_m), biases, faults,
            _array(line_of_sight), _array(weights),
            np.ascontiguousarray(sys_index, dtype=np.int64), int(n_systems),
            _array(prior_cov_m2), _array(posterior_cov_m2), COV_FLOOR_M2)
        return self.offsets_m
