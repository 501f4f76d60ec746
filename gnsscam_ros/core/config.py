"""Filter parameters: one source for each parameter's default, meaning, unit and range.

The parameters come in parts, small frozen dataclasses (their metadata machinery:
:mod:`.parameters`): the particle set
(:class:`ParticleSetConfig`), the motion model (:class:`MotionConfig`), GNSS and its
likelihood (:class:`GnssConfig`), the bias hypotheses (:class:`BiasConfig`), the camera
(:class:`CameraConfig`) and integrity (:class:`IntegrityConfig`). Each field carries its
metadata (:func:`parameter`: doc, unit, range or choices); from it come the parts'
validation, their ``Attributes:`` docstrings, the fusion node's parameter descriptors and
the comments of ``config/fusion_node.yaml`` (:func:`render_yaml_block`; a test checks
that the file is current).

:class:`FilterConfig` composes the parts. Its flat names (``n_particles``,
``alert_limit_m``, ...) are the public parameter names, unique across the parts: the node
parameters, ``FilterConfig(alert_limit_m=25.0)``, ``config.n_particles`` and
``dataclasses.replace(config, alert_limit_m=16.0)`` all use them.

Besides each parameter's own range, :class:`FilterConfig` checks what the sizes cost
together: the estimated peak memory of one epoch (:func:`epoch_memory_bytes`) must be
within ``EPOCH_MEMORY_BUDGET_BYTES``. The satellites an epoch uses are part of that cost:
a configuration uses up to ``gnss.MAX_EPOCH_SATELLITES`` of them, fewer (the strongest) when its
sizes would exceed the budget with that many (``FilterConfig.satellite_limit``), and is
refused when not even ``MIN_SATELLITE_LIMIT`` fit. So a node refuses such a configuration
at start-up (or a change to it while running) instead of dying in the middle of an epoch,
and no message can make an epoch exceed the budget.

Run as ``python -m gnsscam_ros.core.config config/fusion_node.yaml`` to rewrite the
generated block of that file after changing a parameter here.
"""
from __future__ import annotations

import dataclasses
import operator
import sys
import textwrap
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .bias import BIAS_LEARNED, BIAS_MODELS, BIAS_NONE, BiasModel
from .gnss import LIKELIHOODS, MAX_EPOCH_SATELLITES, ROBUST
from .integrity import EXACT, INVERSE_METHODS
from .memory_budget import (EPOCH_MEMORY_BUDGET_BYTES, MIN_SATELLITE_LIMIT,  # noqa: F401
                            epoch_memory_bytes)
from .parameters import (ParameterSpec, Range, field_specs as _field_specs,  # noqa: F401
                         invalid as _invalid, parameter, problems as _problems)

#: Values of the ``error_model`` parameter.
ERROR_ADAPTIVE = 'adaptive'
ERROR_STATED = 'stated'
ERROR_MODELS = (ERROR_ADAPTIVE, ERROR_STATED)


class _Part:
    """Base of the parts: validation from the field metadata."""

    def __post_init__(self):
        problems = _problems(_field_specs(type(self)),
                             {f.name: getattr(self, f.name) for f in dataclasses.fields(self)})
        if problems:
            raise _invalid(problems)


def _part(cls):
    """Make ``cls`` a frozen part whose ``Attributes:`` docstring comes from its fields."""
    cls = dataclass(frozen=True)(cls)
    lines = ['', '    Attributes:']
    for spec in _field_specs(cls):
        text = f'{spec.name}: {spec.description}'
        if spec.constraint:
            text += f' Admissible: {spec.constraint}.'
        lines += textwrap.wrap(text, 92, initial_indent=' ' * 8, subsequent_indent=' ' * 12,
                               break_long_words=False, break_on_hyphens=False)
    cls.__doc__ = (cls.__doc__ or '').rstrip() + '\n' + '\n'.join(lines) + '\n'
    return cls


# ---------------------------------------------------------------------------- the parts
@_part
class ParticleSetConfig(_Part):
    """The particle sets: sizes, initialisation, heading acquisition and resampling."""

    n_particles: int = parameter(
        4000, 'Particles per posterior N. Where the geometry is poor the estimate improves '
        'with N; the epoch costs about N. The sizes together (this, acquisition_particles, '
        'n_posteriors, n_motion_samples) must fit the 2 GiB memory budget of an epoch '
        '(core.config.epoch_memory_bytes; large ones use fewer satellites, too large ones '
        'are refused).', low=2, high=10_000_000,
        provenance='Not fitted: a cost, set to what a 10 ms epoch affords with margin (6.8 '
                   'ms at the default configuration when chosen, 6.1 ms now: '
                   'docs/results/bench.json). Measured '
                   'with filter seeds 1-10 (none of the reported seeds 11-20): GLONASS alone '
                   'on the smartLoc drive, RMSE 0.51, 0.50, 0.49, 0.46 of the robust WLS at '
                   'N = 1000, 2000, 3000, 5000.')
    n_posteriors: int = parameter(
        200, 'Posteriors M behind the risk bound and the protection level. With the exact '
        'inverse Bernoulli the bound can never fall below '
        '``1 - exp(-log((M + 1) / delta) / M)``: 0.375 for M = 10, 0.037 for M = 200 '
        '(delta = 0.1). Bias hypotheses make extra posteriors cheap (no likelihood).',
        low=1, high=10_000)
    n_motion_samples: int = parameter(
        10, 'Motion samples drawn around the odometry and weighed by the measurements (the '
        'estimate is the best of them); posterior j uses sample ``j mod n_motion_samples`` '
        "and its own bias hypothesis. With ``bias_model = 'none'`` every posterior has its "
        'own sample (this is ignored).', low=1, high=10_000)
    resample_ess_fraction: float = parameter(
        0.5, 'Resample when the effective sample size falls below this fraction of N.',
        low=0.0, high=1.0)
    init_position_sd_m: float = parameter(
        30.0, 'Horizontal spread of the initial set around the first fix.', 'm', low=0.0)
    init_vertical_sd_m: float = parameter(
        60.0, 'Vertical spread of the initial set; snapshot heights in a street canyon are '
        'tens of metres off, so this is wider than the horizontal one.', 'm', low=0.0)
    heading_acquisition_m: float = parameter(
        100.0, 'The heading is unknown at start and observable only once the vehicle has '
        'moved well beyond the GNSS errors. Until it has travelled this far the set holds '
        '``acquisition_particles`` particles (when that is more than ``n_particles``), so '
        'that the 4D (position, height, heading) search is covered densely and does not '
        'lock onto a wrong heading by sampling luck.', 'm', low=0.0)
    acquisition_particles: int = parameter(
        10_000, 'Set size during heading acquisition; 0 or fewer than ``n_particles``: no '
        'enlargement. An absolute count, not a multiple of N: how many particles cover the '
        'search (the initial spread times the heading circle) depends on that volume, not '
        'on the working size, so a large N gains nothing from an enlargement and would pay '
        'ten times its epoch cost for the first 100 m.', low=0, high=10_000_000)


@_part
class MotionConfig(_Part):
    """Motion model: process noise, odometry perturbations, motion while unknown."""

    propagation_var_m2_per_m: float = parameter(
        0.05, 'Horizontal position process noise per axis per metre travelled: what the '
        'odometry does not describe (wheel slip, scale, lever arm) grows with the distance, '
        'not with time (0.05 m^2/m is 0.3 m^2/s at a city speed of 6 m/s).', 'm^2/m', low=0.0,
        provenance='Chosen among 0.025, 0.05 and 0.1 on the first half of the smartLoc Berlin '
                   'drive (filter seeds 11-14); reported on the second half and on every '
                   'other drive.')
    vertical_propagation_var_m2_per_m: float = parameter(
        0.05, "Height process noise per metre travelled; a road vehicle's height changes "
        'slowly and GNSS observes it poorly.', 'm^2/m', low=0.0)
    propagation_var_m2: float = parameter(
        0.01, 'Position process noise per axis per second, horizontal and vertical, on top '
        'of the travelled share: a vehicle at rest does not drift, this only keeps its '
        'particle set diverse (0.3 m in 10 s of rest).', 'm^2/s', low=0.0)
    yaw_propagation_var_rad2: float = parameter(
        3e-4, 'Heading process noise per second.', 'rad^2/s', low=0.0)
    motion_perturbation_scale: float = parameter(
        3.0, 'Inflation of the odometry noise for the motion samples.', low=0.0)
    max_speed_mps: float = parameter(
        40.0, 'Fastest the vehicle may move while its motion is unknown (dead reckoning '
        'lost or reset): the set spreads by this speed times the gap.', 'm/s', low=0.0)
    max_yaw_rate_rps: float = parameter(
        1.0, 'Fastest heading change while the motion is unknown.', 'rad/s', low=0.0)

    def position_process_var_m2(self, dt_s: float, travelled_m: float) -> np.ndarray:
        """(3,) east, north, up process noise variance of one step [m^2]: the travelled
        share plus the time share (dead-reckoning gaps are added by the filter)."""
        per_m = np.array([self.propagation_var_m2_per_m, self.propagation_var_m2_per_m,
                          self.vertical_propagation_var_m2_per_m])
        return per_m * abs(float(travelled_m)) + self.propagation_var_m2 * float(dt_s)


@_part
class GnssConfig(_Part):
    """GNSS measurements: satellite checks, variances, receiver clock and likelihood."""

    min_satellites: int = parameter(
        4, 'Fewest satellites for an update (position and clock need 4); at most the '
        'satellites an epoch uses (``gnss.MAX_EPOCH_SATELLITES``).', low=4,
        high=MAX_EPOCH_SATELLITES)
    elevation_mask_deg: float = parameter(
        0.0, 'Satellites below this elevation are dropped.', 'deg', low=-90.0, high=90.0)
    cn0_mask_dbhz: float = parameter(
        0.0, 'Satellites below this C/N0 are dropped.', 'dB-Hz', low=0.0, high=100.0)
    error_model: str = parameter(
        ERROR_ADAPTIVE, "'adaptive' (the pseudorange error mixture, a line-of-sight core and "
        'an NLOS / multipath component per C/N0 class, is learned online by EM from the '
        "residuals of each epoch's robust snapshot solution over error_window_s; the stated "
        "variances are not used; core.error_model) or 'stated' (the receiver's variances, "
        'measurement_var_m2 and the outlier constants below).', choices=ERROR_MODELS)
    error_window_s: float = parameter(
        60.0, 'Sliding window of residuals from which the adaptive error model is learned '
        '(the horizon of the adaptive mixtures of libRSF); it keeps at least the last 300 '
        'residuals (core.error_model.MIN_WINDOW_RESIDUALS), so that a slow stream is '
        'learned from its data.', 's', low=1.0)
    measurement_var_m2: float = parameter(
        10.0, "Pseudorange variance (paper Table 1: 10; error_model 'stated').", 'm^2',
        low=0.0, low_open=True)
    use_reported_variance: bool = parameter(
        True, "Use max(measurement_var_m2, the receiver's variance) (error_model "
        "'stated').")
    clock_kernel_max_m: float = parameter(
        3.0, "Cap on how much the prior's spread widens the clock's inlier kernel. NLOS "
        'errors are positive; a kernel wide enough to take them in biases the clock, and '
        'through it the height, by tens of metres.', 'm', low=0.0)
    error_correlation_time_s: float = parameter(
        10.0, 'Correlation time tau of the persisting part of the GNSS errors (a first-order '
        'Gauss-Markov process): an epoch dt after the last is worth c = tanh(dt / (2 tau)) '
        'of an independent one in the likelihood, whatever the GNSS rate, or '
        '1 / ((1 - s) + s / c) with s the persisting share measured from the snapshot '
        "solutions (core.persistence; 1 until measured); the 'learned' bias hypotheses' "
        'memory until the error model has measured its own; 0 = every epoch independent. '
        'A measured correlation time would make the likelihood bolder where errors '
        'decorrelate fast, and a wrong lock likelier; this fixed value keeps it.', 's',
        low=0.0,
        provenance='Chosen among 2.5, 10 and 30 s on the first half of the smartLoc Berlin '
        'drive (filter seeds 1-3); reported on its second half and the robustness variants.')
    likelihood: str = parameter(
        ROBUST, "'particle_raim' (the paper's mixture) or 'robust' (Gaussian with an "
        'outlier floor).', choices=LIKELIHOODS)
    dirichlet_alpha: float = parameter(
        1.01, 'Dirichlet prior concentration in the EM pooling (particle_raim).', low=1.0)
    outlier_prob: float = parameter(
        0.3, 'Outlier probability of the robust likelihood.', low=0.0, high=1.0,
        low_open=True, high_open=True)
    outlier_range_m: float = parameter(
        300.0, "Width of the robust likelihood's uniform outlier density.", 'm', low=0.0,
        low_open=True)


@_part
class BiasConfig(_Part):
    """Bias hypotheses of the posteriors behind the risk bound (``core.bias``)."""

    bias_model: str = parameter(
        BIAS_LEARNED, "'learned' (each posterior carries a Gauss-Markov pseudorange bias per "
        'satellite with the standard deviation of its signal class in the learned error '
        "model, propagated into the estimate; core.bias, core.error_model), 'cn0' (the "
        'same, its size from C/N0 and the constants below, which were calibrated on the '
        "smartLoc drive: kept for comparison) or 'none' (posteriors differ by motion "
        'perturbations only, as in the paper).',
        choices=BIAS_MODELS)
    bias_floor_m: float = parameter(
        2.0, 'Smallest bias standard deviation at high C/N0.', 'm', low=0.0)
    bias_residual_scale: float = parameter(
        0.23, 'Bias standard deviation at high C/N0 per metre of smoothed residual RMS at '
        'the estimate.', low=0.0,
        provenance='Calibrated on smartLoc (filter seed 2): see docs/integrity.md.')
    bias_cn0_knee_dbhz: float = parameter(
        41.6, 'Below this C/N0 the bias grows 10 dB per decade.', 'dB-Hz', low=0.0)
    bias_correlation_time_s: float = parameter(
        50.0, "Correlation time of the 'cn0' biases (smartLoc: about 50 s; the 'learned' "
        'ones take error_correlation_time_s).', 's', low=0.0)
    bias_beyond_cloud: bool = parameter(
        True, "The bound does not count twice what the particle set holds: the "
        "Gauss-Markov part of the 'learned' and 'cn0' offsets adds only what exceeds the "
        "set's own spread (the likelihood is tempered for persisting errors, so that "
        'spread already stands for them), the hidden faults add in full (core.bias.'
        'beyond_cloud), once the learned error model has measured how long the errors '
        'persist (until then, and with epochs too far apart to measure it, every offset '
        'counts in full). False: every offset in full, on top of the spread.',
        provenance='Chosen on the smartLoc Berlin drive, filter seeds 1-3 (unchanged, GPS '
        'only, GLONASS only, joined 120 s in, GNSS at 1 Hz, injected faults): median PL '
        '2.00-3.36x the error in full, 1.85-2.79x beyond the cloud, MI rate 0-0.031 and '
        '0-0.034; reported on the robustness matrix (seeds 11-20) and every other drive. '
        'The wait for a measured correlation was added after the RINEX station NYA1 (GPS + '
        'Galileo + BeiDou, 30 s epochs), a reported drive, gave an MI rate of 0.121 '
        'without it: that station is in-sample for the wait.')
    hidden_fault_core_sds: float = parameter(
        1.0, "Size of the hidden fault each 'learned' hypothesis also carries on one "
        'satellite, in core standard deviations of its residual: the bias c sigma / '
        'sqrt(1 - h) that leaves its own residual within c of its noise (sigma the core '
        'of its signal class, h its leverage; core.bias). It matters where the satellites '
        'are few; 0 = none.', low=0.0,
        provenance='Chosen among 1, 1.5 and 3 on the first half of the smartLoc Berlin '
        'drive, unchanged and GLONASS only (filter seeds 1-3), as the smallest level whose '
        'MI rate met 0.10 (GLONASS only: MI 0.055 / 0.043 / 0.021, median PL 1.96 / 2.18 / '
        '2.56x the error); reported on the robustness matrix (seeds 11-20) and every other '
        'drive.')

    @property
    def model(self) -> BiasModel:
        """The bias model of these parameters."""
        return BiasModel(floor_m=self.bias_floor_m, residual_scale=self.bias_residual_scale,
                         cn0_knee_dbhz=self.bias_cn0_knee_dbhz,
                         correlation_time_s=self.bias_correlation_time_s)


@_part
class CameraConfig(_Part):
    """Camera fusion (``core.fusion``)."""

    use_camera: bool = parameter(
        True, 'Fuse camera matches when they are given (false = Particle RAIM only).')
    camera_temperature_m: float = parameter(
        5.0, 'Softmax temperature of the camera distribution.', 'm', low=0.0, low_open=True)
    camera_gate_m: float = parameter(
        20.0, 'Beyond this distance from a match a particle is no more likely under the '
        'camera than the rest of the map (the "elsewhere" cell).', 'm', low=0.0,
        low_open=True)
    camera_elsewhere_prob: float = parameter(
        1e-3, 'GNSS probability that the vehicle is outside the cloud.', low=0.0, high=1.0,
        low_open=True, high_open=True)
    camera_kl_threshold_nats: float = parameter(
        5.0, "The camera is excluded for an epoch when every image's KL(Q_j || P) against "
        'the GNSS distribution exceeds this; with every match beyond the gate KL tends to '
        'log(1 / camera_elsewhere_prob) = 6.9.', 'nats', low=0.0, low_open=True)


@_part
class IntegrityConfig(_Part):
    """Integrity: alert limits, target risk, the bound's confidence and settling."""

    alert_limit_m: float = parameter(
        8.0, 'Alert limit of the integrity flag.', 'm', low=0.0, low_open=True)
    extra_alert_limits_m: tuple = parameter(
        (), 'Further alert limits whose risk is computed (evaluation only).', 'm',
        node=False)
    target_risk: float = parameter(
        0.1, 'Integrity is insufficient when the risk bound exceeds this.', low=0.0,
        high=1.0, low_open=True, high_open=True)
    risk_delta: float = parameter(
        0.1, 'Confidence parameter delta of the bound.', low=0.0, high=1.0, low_open=True)
    inverse_bernoulli: str = parameter(
        EXACT, "'exact' (bisection) or 'approx' (the paper's closed form, which collapses "
        'to 0 when no posterior mass is hazardous: reproduction only).',
        choices=INVERSE_METHODS)
    horizontal_risk: bool = parameter(
        True, 'Alert limits on horizontal error (true) or 3D error.')
    integrity_settling_s: float = parameter(
        30.0, 'Integrity is not certified before the heading is acquired (at the start, and '
        'again after a dead-reckoning gap long enough to lose it) and this long after: the '
        'set starts on a snapshot fix, which carries the whole effect of the biases, while '
        "the bias hypotheses start from none and need the filter's own memory to grow into "
        'it (measured: the level fell below the error at the end of acquisition on the '
        'emulated drive).', 's', low=0.0)

    consistency_suspect_nats: float = parameter(
        2.0, 'The cloud counts as inconsistent with the measurements (ERROR, the protection '
        'level covering the snapshot solution) while the CUSUM of the log likelihood ratio '
        '"cloud moved onto the snapshot solution" against "cloud" is at least this '
        '(core.consistency): odds of e^2 = 7 to 1; and the snapshot solution is beyond '
        "the cloud's own protection level.", 'nats', low=0.0, low_open=True)
    consistency_recover_nats: float = parameter(
        6.0, 'At this statistic (odds of 400 to 1), with the snapshot solution beyond the '
        "cloud's own protection level, the filter recovers: recovery_share of the cloud "
        'moves onto the snapshot solution and integrity settles again.', 'nats',
        low=0.0, low_open=True)
    recovery_share: float = parameter(
        0.5, 'Share of the cloud moved onto the snapshot solution at a recovery.', low=0.0,
        high=1.0, low_open=True)

    @property
    def alert_limits_m(self) -> np.ndarray:
        """The flag's alert limit first, then the extra ones."""
        extra = [a for a in self.extra_alert_limits_m if a != self.alert_limit_m]
        return np.array([self.alert_limit_m, *extra], dtype=float)


def _gib(n_bytes: float) -> str:
    return f'{n_bytes / 2 ** 30:,.1f} GiB'


# -------------------------------------------------------------------------- composition
@dataclass(frozen=True, init=False)
class FilterConfig:
    """Filter parameters: the parts, read and set through their flat names.

    ``FilterConfig(n_particles=300, alert_limit_m=25.0)`` sets parameters by flat name
    (the rest keep their defaults); parts may be given whole
    (``FilterConfig(camera=CameraConfig(use_camera=False))``), flat names override them.
    ``config.n_particles`` reads a parameter, ``config.particle_set`` its part, and
    ``dataclasses.replace(config, alert_limit_m=16.0)`` makes a validated copy. Every
    parameter's meaning, unit and range: :meth:`parameter_specs` (or the part classes'
    docstrings); the fusion node declares every one with ``node_parameter`` set under its
    flat name.

    Raises:
        ValueError: An inadmissible value; the message names every one. Sizes that are
            admissible one by one but together need more than
            ``EPOCH_MEMORY_BUDGET_BYTES`` per epoch even with ``MIN_SATELLITE_LIMIT``
            satellites are refused with the estimate.
        TypeError: An unknown name, or a part of the wrong class.
    """

    particle_set: ParticleSetConfig = field(default_factory=ParticleSetConfig)
    motion: MotionConfig = field(default_factory=MotionConfig)
    gnss: GnssConfig = field(default_factory=GnssConfig)
    bias_hypotheses: BiasConfig = field(default_factory=BiasConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    integrity: IntegrityConfig = field(default_factory=IntegrityConfig)

    def __init__(self, **values):
        unknown = set(values) - set(_PART_OF) - {name for name, _ in PARTS}
        if unknown:
            raise TypeError(f'FilterConfig got unexpected parameters: {sorted(unknown)}')
        merged, problems = {}, []
        for name, cls in PARTS:
            base = values.get(name)
            if base is None:
                base = cls()
            elif not isinstance(base, cls):
                raise TypeError(f'FilterConfig part {name} must be a {cls.__name__}')
            own = {f.name: values.get(f.name, getattr(base, f.name))
                   for f in dataclasses.fields(cls)}
            problems += _problems(_field_specs(cls), own)
            merged[name] = (cls, own)
        if problems:
            raise _invalid(problems)
        for name, (cls, own) in merged.items():
            object.__setattr__(self, name, cls(**own))
        # Not a field: derived from the sizes (equality, hashing and replace() see the
        # parameters only).
        object.__setattr__(self, '_satellite_limit', self._fitting_satellites())
        if self._satellite_limit is None:
            fewest = max(MIN_SATELLITE_LIMIT, self.min_satellites)
            raise _invalid([
                f'an epoch would need an estimated {_gib(self.epoch_memory_bytes(fewest))} '
                f'of memory (n_particles {self.n_particles}, acquisition_particles '
                f'{self.acquisition_particles}, n_posteriors {self.n_posteriors}, '
                f'{self.motion_sample_count} motion samples, {fewest} satellites), more '
                f'than the {_gib(EPOCH_MEMORY_BUDGET_BYTES)} budget'])

    def _fitting_satellites(self) -> int | None:
        """The most satellites (up to MAX_EPOCH_SATELLITES) whose epoch fits the budget, or None
        when not even the fewest this configuration needs do."""
        fewest = max(MIN_SATELLITE_LIMIT, self.min_satellites)
        for k in range(MAX_EPOCH_SATELLITES, fewest - 1, -1):
            if self.epoch_memory_bytes(k) <= EPOCH_MEMORY_BUDGET_BYTES:
                return k
        return None

    @classmethod
    def from_flat(cls, values: dict) -> 'FilterConfig':
        """The configuration of ``{flat name: value}`` (missing ones at their defaults)."""
        return cls(**values)

    @classmethod
    def parameter_specs(cls) -> tuple[ParameterSpec, ...]:
        """Every parameter (node parameters and evaluation-only ones), in part order."""
        return _SPECS

    def as_flat(self) -> dict:
        """``{flat name: value}`` of every parameter (JSON records, copies)."""
        return {spec.name: getattr(self, spec.name) for spec in _SPECS}

    def as_parameters(self) -> dict:
        """``{name: value}`` of the fusion node parameters (``as_flat`` without the
        evaluation-only ones)."""
        return {spec.name: getattr(self, spec.name) for spec in _SPECS if spec.node_parameter}

    @property
    def alert_limits_m(self) -> np.ndarray:
        """The flag's alert limit first, then the extra ones."""
        return self.integrity.alert_limits_m

    @property
    def motion_sample_count(self) -> int:
        """Motion samples weighed per epoch (every posterior's own without bias model)."""
        if self.bias_model == BIAS_NONE:
            return self.n_posteriors
        return min(self.n_motion_samples, self.n_posteriors)

    @property
    def satellite_limit(self) -> int:
        """Most satellites an epoch uses (the strongest by C/N0): ``gnss.MAX_EPOCH_SATELLITES``,
        or fewer when these sizes would need more than ``EPOCH_MEMORY_BUDGET_BYTES`` with
        that many (never fewer than ``MIN_SATELLITE_LIMIT``: such sizes are refused)."""
        return self._satellite_limit

    def epoch_memory_bytes(self, satellites: int | None = None) -> int:
        """Estimated peak memory of one epoch with these sizes [bytes]
        (:func:`epoch_memory_bytes`) with ``satellites`` (default: ``satellite_limit``)
        and the most camera images an epoch fuses."""
        k = self.satellite_limit if satellites is None else satellites
        return epoch_memory_bytes(self.n_particles, self.acquisition_particles,
                                  self.n_posteriors, self.motion_sample_count, k)

    @property
    def bias(self) -> BiasModel:
        """The bias model of the bias hypotheses: ``bias_hypotheses.model``, with the
        correlation time of the GNSS errors (``error_correlation_time_s``) for the
        'learned' hypotheses (which take the error model's measured one once it has
        it)."""
        model = self.bias_hypotheses.model
        if self.bias_model == BIAS_LEARNED:
            model = dataclasses.replace(model, correlation_time_s=self.error_correlation_time_s)
        return model


#: ``(attribute of FilterConfig, part class)`` in parameter order.
PARTS = tuple((f.name, f.default_factory) for f in dataclasses.fields(FilterConfig))
_SPECS = tuple(spec for name, cls in PARTS for spec in _field_specs(cls, name))
#: Flat name -> attribute of its part in FilterConfig.
_PART_OF = {spec.name: spec.part for spec in _SPECS}


def _add_flat_properties() -> None:
    """Read access by flat name: ``config.n_particles`` is ``config.particle_set.n_particles``."""
    taken = set(dir(FilterConfig))
    if len(_PART_OF) != len(_SPECS) or taken & set(_PART_OF):
        clash = sorted(taken & set(_PART_OF)) or 'a name in two parts'
        raise RuntimeError(f'FilterConfig parameter names must be unique: {clash}')
    for spec in _SPECS:
        setattr(FilterConfig, spec.name,
                property(operator.attrgetter(f'{spec.part}.{spec.name}'),
                         doc=spec.description))


_add_flat_properties()


# ------------------------------------------------------------------------ the YAML file
#: The lines around the generated block of ``config/fusion_node.yaml``.
YAML_BEGIN = ('    # ---- Filter parameters (FilterConfig). Generated from '
              'gnsscam_ros/core/config.py:')
YAML_BEGIN_2 = ('    # ---- edit there, then run python -m gnsscam_ros.core.config '
                'config/fusion_node.yaml')
YAML_END = "    # ---- fusion_node's own parameters ----"
_WIDTH = 99
_INDENT = '    '


def yaml_value(value) -> str:
    """``value`` as a YAML scalar or flow sequence that loads back as the same value."""
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, str):
        return '"' + value.replace('\\', '\\\\').replace('"', '\\"') + '"'
    if isinstance(value, float):
        if not np.isfinite(value):
            return '.nan' if np.isnan(value) else ('.inf' if value > 0 else '-.inf')
        text = repr(value)
        # YAML 1.1 (PyYAML) reads 1e-05 as a string: it wants a dot in the mantissa.
        if 'e' in text and '.' not in text:
            text = text.replace('e', '.0e')
        return text
    if isinstance(value, (tuple, list)):
        return '[' + ', '.join(yaml_value(v) for v in value) + ']'
    return str(value)


def comment_lines(text: str, keep: str = '') -> list[str]:
    """``text`` as wrapped comment lines; ``keep`` (a part of it) is not broken."""
    glued = keep.replace(' ', '\0')
    lines = textwrap.wrap(text.replace(keep, glued) if keep else text, _WIDTH,
                          initial_indent=_INDENT + '# ', subsequent_indent=_INDENT + '# ',
                          break_long_words=False, break_on_hyphens=False)
    return [line.replace('\0', ' ') for line in lines]


def render_yaml_block() -> str:
    """The filter parameters of ``config/fusion_node.yaml``: per part a heading, per
    parameter a comment (meaning, unit, default, admissible values) and its default."""
    lines = [YAML_BEGIN, YAML_BEGIN_2]
    for part, cls in PARTS:
        specs = [s for s in _field_specs(cls, part) if s.node_parameter]
        title = (cls.__doc__ or '').strip().splitlines()[0].rstrip('.')
        lines += [''] + comment_lines(f'== {title} (FilterConfig.{part})')
        for spec in specs:
            text = f'{spec.description} Default: {yaml_value(spec.default)}'
            text += f'; {spec.constraint}.' if spec.constraint else '.'
            lines += comment_lines(text, spec.constraint)
            lines.append(f'{_INDENT}{spec.name}: {yaml_value(spec.default)}')
    return '\n'.join(lines) + '\n\n'


def update_yaml(text: str) -> str:
    """``text`` (``config/fusion_node.yaml``) with its generated block rendered anew.

    Raises:
        ValueError: The markers around the block are missing.
    """
    start = text.find(YAML_BEGIN)
    end = text.find(YAML_END)
    if start < 0 or end < start:
        raise ValueError(f'the generated block must start with {YAML_BEGIN.strip()!r} and '
                         f'end before {YAML_END.strip()!r}')
    return text[:start] + render_yaml_block() + text[end:]


def main(argv: list[str] | None = None) -> int:
    """Rewrite the generated block of the YAML files given (``config/fusion_node.yaml``)."""
    paths = sys.argv[1:] if argv is None else argv
    if not paths:
        print('usage: python -m gnsscam_ros.core.config config/fusion_node.yaml',
              file=sys.stderr)
        return 2
    for name in paths:
        path = Path(name)
        old = path.read_text(encoding='utf-8')
        new = update_yaml(old)
        if new != old:
            path.write_text(new, encoding='utf-8')
            print(f'{path}: updated')
        else:
            print(f'{path}: up to date')
    return 0


if __name__ == '__main__':
    sys.exit(main())
