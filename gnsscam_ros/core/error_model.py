"""The pseudorange error model, learned online from the residuals at the estimate.

Receivers and preprocessing chains state variances on scales that differ by factors of
2-10, or state none; in a street canyon the errors are not Gaussian either: a
line-of-sight core of a few metres and NLOS / multipath errors of tens of metres, more of
them the weaker the signal. So the filter does not take the stated variances; it learns
the error distribution from what the measurements do, in the spirit of the adaptive
mixtures of Pfeifer and Protzel (libRSF: a Gaussian mixture whose weights and spreads are
estimated from the residuals over a sliding window):

* every satellite falls into a **signal class** by its C/N0 (bins ``CN0_EDGES_DBHZ``;
  satellites without C/N0 form a class of their own);
* per class, the residuals of the last ``window_s`` seconds (at least the last
  :data:`MIN_WINDOW_RESIDUALS`, so that a slow stream is learned from data too) are a
  two-component mixture
  ``(1 - pi) N(r; 0, s0^2) + pi N(r; mu, s1^2)``: a line-of-sight core centred on zero
  (the per-constellation receiver clock takes the common offset) and a wide component
  for NLOS and multipath with a mean ``mu >= 0`` (a reflected signal arrives late);
* weights and spreads move towards their maximum a posteriori estimates by EM, a few
  iterations per epoch started from the last epoch's fit (incremental EM; not always
  converged, see ``EM_ITERATIONS``). The priors keep a class with
  few samples near the pooled fit of all classes shaped by the SIGMA-epsilon law of code
  tracking (Hartinger and Brunner 1999: variance proportional to ``10^(-C/N0 / 10)``),
  and the pooled fit near physical scales (:class:`ErrorPriors`): conventions of the
  problem class (code noise of metres, NLOS errors of tens of metres), not values fitted
  to a data set. Before any residual the model is that prior, so the first fix is
  weighted by C/N0 too, never by the stated variances. The priors weigh the same
  seconds of residuals at every GNSS rate (their pseudo-samples are stated at 5 Hz and
  scaled to the stream's interval, :meth:`AdaptiveErrorModel.prior_strength`): the
  errors persist for seconds, so what a window knows grows with its duration, and the
  same drive at 1, 2 and 5 Hz is learned alike.

The residuals are those of the epoch's own robust snapshot solution (so that a filter
locked onto a wrong place cannot teach the model that place), after its clock per
constellation, inflated by ``sqrt(V / (V - p))`` (``V`` the expected number of
line-of-sight satellites under the current fit, ``p`` unknowns): the fix absorbs part of
the errors of the satellites it rests on, their residuals alone would understate them.

How long the line-of-sight errors persist is learned alongside
(:attr:`AdaptiveErrorModel.correlation_time_s`): the correlation of each satellite's
residual with its own about ``CORRELATION_LAG_S`` earlier, over the window, read as that
of a first-order Gauss-Markov process, ``tau = -lag / ln rho``. The lag is in seconds,
not epochs, so the estimate does not depend on the GNSS rate.

The same fit drives the GNSS likelihood (the mixture of each satellite's class,
:meth:`AdaptiveErrorModel.satellite_model`), the bias hypotheses behind the protection
level (the core spread, and how long errors persist), and the weights of the snapshot
solutions the consistency test compares with (:meth:`AdaptiveErrorModel.total_sigma_m`,
:mod:`core.consistency`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .kernels import mixture as mixture_kernels
from .kernels import residuals as residual_kernels

#: C/N0 bin edges of the signal classes [dB-Hz]: 5 dB-Hz bins over the range where code
#: tracking errors change most (below 25 a signal is mostly reflected, above 45 mostly
#: direct). A generic discretisation, not a fit.
CN0_EDGES_DBHZ = np.array([25.0, 30.0, 35.0, 40.0, 45.0])
#: C/N0 of each class for the prior's shape [dB-Hz]: the bin centres (the unknown class
#: at the reference).
CLASS_CN0_DBHZ = np.array([22.5, 27.5, 32.5, 37.5, 42.5, 47.5, 45.0])
#: Reference C/N0 of the prior's shape [dB-Hz].
REFERENCE_CN0_DBHZ = 45.0
#: Class of the satellites whose C/N0 is unknown.
UNKNOWN_CLASS = CN0_EDGES_DBHZ.shape[0] + 1
N_CLASSES = UNKNOWN_CLASS + 1
#: EM iterations per epoch (warm-started: the fit moves by one epoch's data at a time).
#: Three do not converge the fit where the window's data change fast (on Berlin at 5 Hz
#: a class's core read 4.4 m where ten or fifty iterations give 15 m); fits run to
#: convergence (ten) widened the PL and failed one robustness cell (docs/robustness.md,
#: "The error model's EM"), so the warm-started three stay.
EM_ITERATIONS = 3
#: Most residuals the window holds (60 s of 60 satellites at 5 Hz fit).
MAX_SAMPLES = 20_000
#: Epoch intervals of receivers [s] the prior's weight is scaled to
#: (:meth:`AdaptiveErrorModel.prior_strength`); the first is the one the priors'
#: pseudo-samples are stated at (5 Hz).
RECEIVER_INTERVALS_S = (0.2, 0.5, 1.0, 2.0)
#: Last epoch intervals of the stream whose median is its interval.
INTERVAL_EPOCHS = 50
#: Lag at which the time correlation is measured [s]; a pair may be half of it off.
CORRELATION_LAG_S = 2.0
#: Residuals beyond this many core standard deviations of their class are clipped there
#: for the correlation: a large NLOS error persists, but must not decide it alone.
CORRELATION_CLIP_SD = 3.0
#: Pairs before the measured correlation time replaces the prior one.
CORRELATION_MIN_PAIRS = 50
#: Shortest correlation time reported [s].
MIN_CORRELATION_TIME_S = 0.1


def signal_class(cn0_dbhz: np.ndarray) -> np.ndarray:
    """Signal class of each satellite (0 .. N_CLASSES - 1) from its C/N0 [dB-Hz]."""
    cn0 = np.asarray(cn0_dbhz, dtype=float)
    # A non-finite C/N0 lands anywhere here (NaN sorts last) and is UNKNOWN_CLASS below.
    classes = CN0_EDGES_DBHZ.searchsorted(cn0, side='right')
    return np.where(np.isfinite(cn0), classes, UNKNOWN_CLASS).astype(np.int64)


@dataclass(frozen=True)
class ErrorPriors:
    """Weak priors of the mixture (conventions of GNSS code ranging in a city).

    Attributes:
        core_sd_m: Line-of-sight code error standard deviation before any data [m].
        wide_sd_m: NLOS / multipath error standard deviation before any data [m].
        wide_share: Share of NLOS / multipath residuals before any data.
        pooled_strength: Pseudo-samples of the pooled fit's prior, at 5 Hz (scaled to the
            stream's interval: :meth:`AdaptiveErrorModel.prior_strength`).
        class_strength: Pseudo-samples by which a class is drawn to the pooled fit, at
            5 Hz (likewise).
        min_core_sd_m: Smallest core spread: code noise never vanishes (0.3 m: a good
            receiver's code tracking) [m].
        max_shape: Largest factor of the SIGMA-epsilon shape (at the lowest C/N0).
    """

    core_sd_m: float = 5.0
    wide_sd_m: float = 30.0
    wide_share: float = 0.3
    pooled_strength: float = 30.0
    class_strength: float = 30.0
    min_core_sd_m: float = 0.3
    max_shape: float = 10.0

    def shape(self) -> np.ndarray:
        """(N_CLASSES,) spread of each class relative to the reference C/N0: standard
        deviation proportional to ``10^(-C/N0 / 20)``, at most ``max_shape``."""
        return np.minimum(10.0 ** (-(CLASS_CN0_DBHZ - REFERENCE_CN0_DBHZ) / 20.0),
                          self.max_shape)


#: Fewest residuals the window keeps, however old: ten times the prior's pseudo-samples
#: (``ErrorPriors.pooled_strength``), so that the data outweigh the prior. A 60 s window
#: of a 30 s static station holds two epochs (some 20 residuals against 30 pseudo-samples
#: of a 5 m core: the fit stayed near the prior, twice the station's errors); at 1 Hz and
#: above a drive's 60 s hold more than this and the window is the time window. After a
#: GNSS outage the last residuals before it stay until new ones replace them: the same
#: receiver's older errors say more than the prior does.
MIN_WINDOW_RESIDUALS = int(10 * ErrorPriors.pooled_strength)


@dataclass(frozen=True)
class MixtureFit:
    """Per-class mixture parameters, arrays of shape (N_CLASSES,).

    Attributes:
        core_sd_m: Line-of-sight core standard deviation s0 [m].
        wide_share: Weight pi of the NLOS / multipath component.
        wide_mean_m: Its mean mu [m].
        wide_sd_m: Its standard deviation s1 [m].
        samples: Residuals of the class in the window (the pooled fit: all).
    """

    core_sd_m: np.ndarray
    wide_share: np.ndarray
    wide_mean_m: np.ndarray
    wide_sd_m: np.ndarray
    samples: np.ndarray

    def total_sd_m(self) -> np.ndarray:
        """Standard deviation of the whole mixture per class [m]."""
        pi, mu = self.wide_share, self.wide_mean_m
        mean = pi * mu
        second = (1.0 - pi) * self.core_sd_m ** 2 + pi * (self.wide_sd_m ** 2 + mu ** 2)
        return np.sqrt(np.maximum(second - mean ** 2, 0.0))


def _at_interval(pseudo_samples: float, interval_s: float | None) -> float:
    """Pseudo-samples stated at 5 Hz, at an epoch interval (None: a sparse stream, as
    stated); :meth:`AdaptiveErrorModel.prior_strength`."""
    if interval_s is None:
        return pseudo_samples
    return pseudo_samples * RECEIVER_INTERVALS_S[0] / interval_s


class AdaptiveErrorModel:
    """Pseudorange error mixture per signal class over a sliding window.

    Args:
        window_s: Length of the window of residuals [s].
        prior_correlation_time_s: Correlation time before enough residual pairs [s].
        priors: The mixture's priors.
    """

    def __init__(self, window_s: float = 60.0, prior_correlation_time_s: float = 10.0,
                 priors: ErrorPriors = ErrorPriors()):
        self.window_s = float(window_s)
        self.prior_correlation_time_s = float(prior_correlation_time_s)
        self.priors = priors
        # The priors' C/N0 shape of the class spreads (a constant of the priors).
        self._shape = priors.shape()
        # The residuals of the last two lags: stamps [ns], satellite keys and residuals
        # [m], rows ``_lagged_first .. _lagged_end`` of three buffers in time order that
        # grow as needed (core.kernels.residuals).
        self._lagged = (np.empty(256, dtype=np.int64), np.empty(256, dtype=np.int64),
                        np.empty(256))
        self._lagged_first = self._lagged_end = 0
        # Sums of the lagged pairs, forgotten over the window: xy, xx, yy, lag, count.
        self._pairs = np.zeros(5)
        self._pairs_stamp_ns: int | None = None
        self._stamp_ns = np.zeros(MAX_SAMPLES, dtype=np.int64)
        self._class = np.zeros(MAX_SAMPLES, dtype=np.int64)
        self._residual_m = np.zeros(MAX_SAMPLES)
        self._count = 0
        # Constants of every refit: unit weights and the pooled prior's centre.
        self._ones = np.ones(MAX_SAMPLES)
        self._pooled_prior = tuple(np.array([v]) for v in (
            priors.core_sd_m, priors.wide_share, 0.0, priors.wide_sd_m))
        self.pooled = self._prior_fit(1)
        self.fit = self._prior_fit(N_CLASSES)
        # The classes of the last C/N0 values asked about: an epoch asks about the same
        # satellites four times (its likelihood, its snapshot weights, its residuals, its
        # bias hypotheses), each a few microseconds of small numpy calls.
        self._classes_of: tuple[tuple, np.ndarray] | None = None
        # The stream's last epoch intervals [s] and the last stamp (the prior's weight).
        self._intervals: list[float] = []
        self._last_stamp_ns: int | None = None

    def _prior_fit(self, n: int) -> MixtureFit:
        p = self.priors
        shape = self._shape if n == N_CLASSES else np.ones(n)
        return MixtureFit(core_sd_m=p.core_sd_m * shape, wide_share=np.full(n, p.wide_share),
                          wide_mean_m=np.zeros(n), wide_sd_m=p.wide_sd_m * shape,
                          samples=np.zeros(n))

    @property
    def samples(self) -> int:
        """Residuals in the window."""
        return self._count

    def observe(self, stamp_ns: int, residual_m: np.ndarray, cn0_dbhz: np.ndarray,
                n_unknowns: int, keys: np.ndarray | None = None) -> None:
        """Add one epoch's residuals at the estimate and refit the mixture.

        Args:
            stamp_ns: Epoch time [ns].
            residual_m: (k,) clock-corrected residuals of a fix [m].
            cn0_dbhz: (k,) C/N0 of the satellites [dB-Hz] (NaN: unknown).
            n_unknowns: Position and clock unknowns the fix took from them.
            keys: (k,) one key per satellite across epochs, for the time correlation
                (None: not measured).
        """
        if self._last_stamp_ns is not None and stamp_ns > self._last_stamp_ns:
            self._intervals.append((stamp_ns - self._last_stamp_ns) * 1e-9)
            del self._intervals[:-INTERVAL_EPOCHS]
        self._last_stamp_ns = stamp_ns
        r = np.asarray(residual_m, dtype=float)
        cn0 = np.asarray(cn0_dbhz, dtype=float)
        keep = np.isfinite(r)
        if not keep.all():
            r, cn0 = r[keep], cn0[keep]
            keys = None if keys is None else np.asarray(keys)[keep]
        cls = self._classes(cn0)
        # The fix rests on the line-of-sight satellites: their count, not all, says how
        # much of their errors it absorbed (each residual's probability of the core, as
        # the EM's E-step gives it).
        f = self.fit
        line_of_sight = mixture_kernels.line_of_sight(r, cls, f.core_sd_m, f.wide_share,
                                                      f.wide_mean_m, f.wide_sd_m)
        if line_of_sight <= n_unknowns + 1.0:
            return                         # too little redundancy to say anything
        r = r * math.sqrt(line_of_sight / (line_of_sight - n_unknowns))
        if keys is not None:
            self._observe_pairs(stamp_ns, np.asarray(keys), r,
                                CORRELATION_CLIP_SD * f.core_sd_m[cls])
        self._append(stamp_ns, r, cls)
        self._refit()

    def _observe_pairs(self, stamp_ns: int, keys: np.ndarray, r: np.ndarray,
                       clip: np.ndarray) -> None:
        """Pair each satellite's residual (clipped to ``+-clip``) with its own about
        ``CORRELATION_LAG_S`` earlier and fold the pairs into the sums."""
        decay = 1.0
        if self._pairs_stamp_ns is not None:
            dt_s = max((stamp_ns - self._pairs_stamp_ns) * 1e-9, 0.0)
            decay = math.exp(-dt_s / self.window_s)
        self._pairs_stamp_ns = stamp_ns
        first, end, k = self._lagged_first, self._lagged_end, keys.shape[0]
        size = self._lagged[0].shape[0]
        if end + k > size:
            # No room after the rows: to the front of buffers at least twice what they and
            # the epoch's rows need.
            count, size = end - first, max(size, 2 * (end - first + k))
            self._lagged = tuple(np.concatenate((buffer[first:end],
                                                 np.empty(size - count, buffer.dtype)))
                                 for buffer in self._lagged)
            first, end = 0, count
        # Older than two lags is forgotten; the stamp closest to one lag back pairs, if
        # it is within half a lag of it. Stamps rise (the filter refuses an epoch not
        # after the last): the rows are in time order.
        self._lagged_first, self._lagged_end, _ = residual_kernels.lagged_pairs(
            *self._lagged, first, end, stamp_ns, np.ascontiguousarray(keys, dtype=np.int64),
            r, int(CORRELATION_LAG_S * 1e9), clip, self._pairs, decay)

    @property
    def correlation_measured(self) -> bool:
        """The window holds enough residual pairs ``CORRELATION_LAG_S`` apart for
        :attr:`correlation_time_s` to be measured, not the prior (never, when the epochs
        are further apart than that lag allows)."""
        _, xx, yy, _, count = self._pairs
        return bool(count >= CORRELATION_MIN_PAIRS and xx > 0.0 and yy > 0.0)

    @property
    def correlation_time_s(self) -> float:
        """How long the errors persist [s]: ``-lag / ln rho`` of the residual pairs in the
        window (the prior until :attr:`correlation_measured`), between
        ``MIN_CORRELATION_TIME_S`` and the window."""
        xy, xx, yy, lag, count = self._pairs
        if not self.correlation_measured:
            return self.prior_correlation_time_s
        rho = xy / np.sqrt(xx * yy)
        if rho <= 0.0:
            return MIN_CORRELATION_TIME_S
        if rho >= 1.0:
            return self.window_s
        # np.clip's result on one value, without its dispatch.
        return float(min(max(-(lag / count) / np.log(rho), MIN_CORRELATION_TIME_S),
                         self.window_s))

    def _append(self, stamp_ns: int, r: np.ndarray, cls: np.ndarray) -> None:
        n = self._count
        k = min(r.shape[0], MAX_SAMPLES)
        # Drop what left the window (and, if still full, the oldest), then append; while
        # the window holds fewer than MIN_WINDOW_RESIDUALS, the newest of the older ones
        # stay. Stamps rise (the filter refuses an epoch not after the last), so what
        # stays is a suffix of the buffer: from the first stamp within the window, and
        # moved to the front by slices (a bisection and a copy, no mask over the window).
        first = int(self._stamp_ns[:n].searchsorted(stamp_ns - int(self.window_s * 1e9)))
        first = min(first, max(0, n - max(0, MIN_WINDOW_RESIDUALS - k)))
        first = max(first, n + k - MAX_SAMPLES)
        m = n - first
        if first:
            for arr in (self._stamp_ns, self._class, self._residual_m):
                arr[:m] = arr[first:n]
        self._stamp_ns[m:m + k] = stamp_ns
        self._class[m:m + k] = cls[-k:]
        self._residual_m[m:m + k] = r[-k:]
        self._count = m + k

    @property
    def epoch_interval_s(self) -> float | None:
        """The stream's epoch interval [s]: the median of its last intervals, taken as the
        nearest of the receivers' intervals (:data:`RECEIVER_INTERVALS_S`: jitter and a
        lost epoch must not move the prior); the first of them until an interval is seen.
        None for a stream too sparse to pair its residuals at ``CORRELATION_LAG_S``."""
        if not self._intervals:
            return RECEIVER_INTERVALS_S[0]
        # The median of a few dozen floats in Python, as numpy's (the mean of the middle
        # two of an even count): np.median's dispatch took 17 us of a 1 ms epoch.
        ordered = sorted(self._intervals)
        half = len(ordered) // 2
        median = (ordered[half] if len(ordered) % 2
                  else (ordered[half - 1] + ordered[half]) / 2.0)
        if median > 1.5 * CORRELATION_LAG_S:
            return None
        steps = [abs(math.log(interval / max(median, 1e-9)))
                 for interval in RECEIVER_INTERVALS_S]
        return RECEIVER_INTERVALS_S[steps.index(min(steps))]

    def prior_strength(self, pseudo_samples: float) -> float:
        """Pseudo-samples of a prior stated at 5 Hz, at the stream's interval: the same
        seconds of residuals (30 at 5 Hz, 12 at 2 Hz, 6 at 1 Hz).

        The window counts each residual as one sample, and the prior weighs against that
        count; but the errors persist for seconds (``correlation_time_s``), so what the
        window knows grows with its duration, not with its epochs. With the count prior a
        1 Hz stream held its weak classes near the prior's core where the same drive at
        5 Hz fitted one twice as wide, and the level missed (docs/robustness.md). A
        stream too sparse to pair its residuals at ``CORRELATION_LAG_S`` (a static
        station at 30 s) has nothing that says how long its errors persist, and keeps
        the count prior: its errors persist for hours, and each epoch is little news.
        The interval is snapped to a receiver's rate so that the jitter of a 5 Hz stream
        leaves its prior at exactly 30: the warm-started EM is path dependent, and a
        prior of 20-24 in the first refits of the file as it is sent it to its other fit.
        """
        return _at_interval(pseudo_samples, self.epoch_interval_s)

    def _refit(self) -> None:
        n = self._count
        p = self.priors
        interval = self.epoch_interval_s              # once: a median of the last intervals
        pooled, fit, counts = mixture_kernels.refit(
            self._residual_m[:n], self._ones[:n], self._class[:n], N_CLASSES,
            self._fit_arrays(self.pooled), self._pooled_prior,
            _at_interval(p.pooled_strength, interval), self._fit_arrays(self.fit),
            self._shape, _at_interval(p.class_strength, interval), p.min_core_sd_m,
            EM_ITERATIONS)
        self.pooled = MixtureFit(*pooled, samples=np.array([float(n)]))
        self.fit = MixtureFit(*fit, samples=counts)

    @staticmethod
    def _fit_arrays(fit: MixtureFit) -> tuple[np.ndarray, ...]:
        return (fit.core_sd_m, fit.wide_share, fit.wide_mean_m, fit.wide_sd_m)

    def _classes(self, cn0_dbhz: np.ndarray) -> np.ndarray:
        """:func:`signal_class` of ``cn0_dbhz`` (read-only), computed once for the same
        values asked about in a row."""
        cn0 = np.asarray(cn0_dbhz, dtype=float)
        key = (cn0.shape, cn0.tobytes())
        if self._classes_of is None or self._classes_of[0] != key:
            classes = signal_class(cn0)
            classes.flags.writeable = False
            self._classes_of = (key, classes)
        return self._classes_of[1]

    def satellite_model(self, cn0_dbhz: np.ndarray) -> tuple[np.ndarray, ...]:
        """The mixture of each satellite's class: ``(core sd [m], wide share, wide mean
        [m], wide sd [m])``, arrays (k,)."""
        cls = self._classes(cn0_dbhz)
        f = self.fit
        return (f.core_sd_m[cls], f.wide_share[cls], f.wide_mean_m[cls], f.wide_sd_m[cls])

    def total_sigma_m(self, cn0_dbhz: np.ndarray) -> np.ndarray:
        """Standard deviation of each satellite's whole error (core and wide) [m]: the
        weights of a snapshot solution."""
        return self.fit.total_sd_m()[self._classes(cn0_dbhz)]

    def reset(self) -> None:
        """Forget the window (a new drive or a reset filter)."""
        self.__init__(self.window_s, self.prior_correlation_time_s, self.priors)
