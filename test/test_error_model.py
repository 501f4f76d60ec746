"""The learned pseudorange error model (core.error_model): known answers of the EM fit,
the window, the signal classes, and what the filter takes from it (not the stated
variances)."""
from dataclasses import replace

import numpy as np
import oracles
import pytest
from synthetic import FRAME, epoch_at

from gnsscam_ros.core import error_model
from gnsscam_ros.core.error_model import (CN0_EDGES_DBHZ, MIN_WINDOW_RESIDUALS, N_CLASSES,
                                          UNKNOWN_CLASS, AdaptiveErrorModel, ErrorPriors,
                                          signal_class)
from gnsscam_ros.core.filter import FilterConfig, ParticleFilter
from gnsscam_ros.core.kernels import mixture as mixture_kernels
from gnsscam_ros.core.particles import MotionIncrement

S = 1_000_000_000


def feed(model, residuals, cn0, epochs, per_epoch, period_s=0.5, start_s=0.0):
    """Feed ``residuals`` (all of one C/N0) to ``model`` in epochs with no unknowns (so no
    inflation for the fix's own fit)."""
    for k in range(epochs):
        r = residuals[k * per_epoch:(k + 1) * per_epoch]
        model.observe(int((start_s + k * period_s) * S), r, np.full(r.shape, cn0), 0)


@pytest.mark.parametrize('n_classes', [1, N_CLASSES])
def test_the_compiled_em_iterations_are_the_numpy_oracle(n_classes):
    """Residuals of a core and a delayed component over the classes (one of them
    empty), weighted, three iterations from a fit away from the answer."""
    rng = np.random.default_rng(n_classes)
    n = 900
    r = np.where(rng.random(n) < 0.3, rng.normal(25.0, 12.0, n), rng.normal(0.0, 3.0, n))
    w = rng.uniform(0.5, 1.5, n)
    cls = rng.integers(0, max(n_classes - 1, 1), n).astype(np.int64)
    ones = np.ones(n_classes)
    fit = (4.0 * ones, 0.1 * ones, 5.0 * ones, 20.0 * ones)
    prior = (5.0 * ones, 0.2 * ones, 0.0 * ones, 30.0 * ones)
    expected = fit
    for _ in range(3):
        expected = oracles.em_step(r, w, cls, n_classes, expected, prior, 30.0, 0.5)
    got = mixture_kernels.em_fit(r, w, cls, n_classes, *fit, *prior, 30.0, 0.5, 3)
    for value, oracle in zip(got, expected):
        np.testing.assert_allclose(value, oracle, rtol=1e-12)
    assert got[1][0] > 0.2 and got[2][0] > 10.0      # the fit moved towards the data


def test_the_refit_is_the_pooled_fit_then_the_classes_towards_it_to_the_bit():
    """One call for an epoch's two fits: the same arithmetic as two em_fit calls with
    numpy's class prior between them (the pooled spreads shaped about their
    sample-weighted mean), on classes of which some are empty."""
    rng = np.random.default_rng(7)
    n = 700
    r = np.where(rng.random(n) < 0.3, rng.normal(25.0, 12.0, n), rng.normal(0.0, 3.0, n))
    w = np.ones(n)
    cls = rng.choice([0, 2, 3, 6], n).astype(np.int64)
    one, ones = np.ones(1), np.ones(N_CLASSES)
    pooled = (4.0 * one, 0.1 * one, 5.0 * one, 20.0 * one)
    pooled_prior = (5.0 * one, 0.3 * one, 0.0 * one, 30.0 * one)
    fit = (3.0 * ones, 0.2 * ones, 1.0 * ones, 25.0 * ones)
    shape = ErrorPriors().shape()
    got_pooled, got_fit, counts = mixture_kernels.refit(
        r, w, cls, N_CLASSES, pooled, pooled_prior, 12.0, fit, shape, 6.0, 0.3, 3)
    want_pooled = mixture_kernels.em_fit(r, w, np.zeros(n, dtype=np.int64), 1, *pooled,
                                         *pooled_prior, 12.0, 0.3, 3)
    want_counts = np.bincount(cls, minlength=N_CLASSES).astype(float)
    shaped = shape / ((want_counts * shape).sum() / max(want_counts.sum(), 1.0))
    s0, pi, mu, s1 = want_pooled
    centre = (s0 * shaped, pi.repeat(N_CLASSES), mu.repeat(N_CLASSES), s1 * shaped)
    want_fit = mixture_kernels.em_fit(r, w, cls, N_CLASSES, *fit, *centre, 6.0, 0.3, 3)
    np.testing.assert_array_equal(counts, want_counts)
    for got, want in zip(got_pooled + got_fit, want_pooled + want_fit, strict=True):
        np.testing.assert_array_equal(got, want)
    assert not np.array_equal(got_fit[0], fit[0])        # the fit moved


def test_a_residual_of_kilometres_is_the_wide_components_not_the_cores():
    # Both densities underflow 5 km out; the responsibility is their ratio, which does
    # not: the residuals go to the wide component and the core keeps its metres, in the
    # first iteration already (as 0 / 0 they went to the core, whose spread read 500 m
    # for an iteration: the epoch's model, the EM being warm-started a few at a time).
    rng = np.random.default_rng(3)
    r = np.concatenate([rng.normal(0.0, 3.0, 500), np.full(5, 5000.0)])
    one = np.ones(1)
    fit = (3.0 * one, 0.2 * one, 0.0 * one, 20.0 * one)
    s0, pi, mu, s1 = mixture_kernels.em_fit(r, np.ones(r.shape[0]), np.zeros(r.shape[0],
                                            dtype=np.int64), 1, *fit, *fit, 30.0, 0.3, 1)
    assert 2.5 < s0[0] < 3.5
    assert s1[0] > 500.0 and mu[0] > 20.0


def test_signal_classes_follow_the_cn0_bins_and_unknown_has_its_own():
    cn0 = np.array([np.nan, 10.0, 25.0, 27.0, 44.9, 45.0, 60.0])
    assert signal_class(cn0).tolist() == [UNKNOWN_CLASS, 0, 1, 1, 4, 5, 5]
    assert N_CLASSES == len(CN0_EDGES_DBHZ) + 2


def test_em_recovers_the_parameters_of_a_synthetic_mixture():
    # 70 % line of sight N(0, 3^2), 30 % NLOS N(40, 15^2): 6,000 residuals over 60 s.
    rng = np.random.default_rng(4)
    n = 6000
    nlos = rng.random(n) < 0.3
    r = np.where(nlos, rng.normal(40.0, 15.0, n), rng.normal(0.0, 3.0, n))
    model = AdaptiveErrorModel(window_s=120.0)
    feed(model, r, 47.0, epochs=120, per_epoch=50)
    cls = int(signal_class(np.array([47.0]))[0])
    fit = model.fit
    assert fit.core_sd_m[cls] == pytest.approx(3.0, rel=0.08)
    assert fit.wide_share[cls] == pytest.approx(0.3, abs=0.03)
    assert fit.wide_mean_m[cls] == pytest.approx(40.0, abs=2.0)
    assert fit.wide_sd_m[cls] == pytest.approx(15.0, rel=0.1)
    # A class without data keeps the pooled fit, widened by the C/N0 law for weak signals.
    weak = int(signal_class(np.array([22.0]))[0])
    assert fit.samples[weak] == 0
    assert fit.core_sd_m[weak] > 2.0 * fit.core_sd_m[cls]


def test_the_fit_follows_the_window_and_forgets_what_left_it():
    rng = np.random.default_rng(5)
    model = AdaptiveErrorModel(window_s=30.0)
    feed(model, rng.normal(0.0, 2.0, 3000), 47.0, epochs=60, per_epoch=50)
    cls = int(signal_class(np.array([47.0]))[0])
    quiet = model.fit.core_sd_m[cls]
    # The sky gets worse: 60 s of errors three times as large; the first 30 s leave.
    feed(model, rng.normal(0.0, 6.0, 6000), 47.0, epochs=120, per_epoch=50, start_s=30.0)
    assert model.samples <= 61 * 50
    assert quiet == pytest.approx(2.0, rel=0.1)
    assert model.fit.core_sd_m[cls] == pytest.approx(6.0, rel=0.15)


def test_a_slow_stream_is_learned_from_its_data_not_from_the_prior(monkeypatch):
    # A static station at 30 s epochs: a 60 s window holds two epochs (20 residuals of
    # a 1 m core against the prior's 30 pseudo-samples of a 5 m one). The window keeps
    # the last MIN_WINDOW_RESIDUALS, and still follows a change of the errors.
    cls = int(signal_class(np.array([47.0]))[0])

    def slow_stream():
        rng = np.random.default_rng(6)
        model = AdaptiveErrorModel(window_s=60.0)
        feed(model, rng.normal(0.0, 1.0, 400), 47.0, epochs=40, per_epoch=10,
             period_s=30.0)
        return model, rng

    model, rng = slow_stream()
    assert model.samples == MIN_WINDOW_RESIDUALS
    assert model.fit.core_sd_m[cls] == pytest.approx(1.0, rel=0.15)
    feed(model, rng.normal(0.0, 3.0, 400), 47.0, epochs=40, per_epoch=10, period_s=30.0,
         start_s=1200.0)
    assert model.fit.core_sd_m[cls] == pytest.approx(3.0, rel=0.15)
    # The time window alone stays near the prior.
    monkeypatch.setattr(error_model, 'MIN_WINDOW_RESIDUALS', 0)
    alone, _ = slow_stream()
    assert alone.samples == 30
    assert alone.fit.core_sd_m[cls] > 2.0


def test_fix_residuals_are_inflated_for_what_the_fix_absorbed():
    # Ten line-of-sight residuals of a fix with five unknowns: each is sqrt(10 / 5) larger.
    model = AdaptiveErrorModel(priors=ErrorPriors(wide_share=1e-3))
    r = np.linspace(-3.0, 3.0, 10)
    model.observe(0, r, np.full(10, 47.0), 5)
    stored = model._residual_m[:model.samples]
    np.testing.assert_allclose(np.abs(stored), np.abs(r) * np.sqrt(2.0), rtol=2e-3)
    # No redundancy: nothing is learned.
    model.observe(S, r[:5], np.full(5, 47.0), 5)
    assert model.samples == 10


def _drive(filt, var_scale, n=12):
    results = []
    for i in range(n):
        epoch = epoch_at(np.array([8.0 * i, 0.0, 0.0]), clock_m=5000.0, stamp_ns=i * S)
        rng = np.random.default_rng(i)
        epoch = replace(epoch, pr_m=epoch.pr_m + rng.normal(0.0, 3.0, epoch.n_sv),
                        var_m2=epoch.var_m2 * var_scale,
                        cn0_dbhz=np.linspace(30.0, 50.0, epoch.n_sv))
        motion = None if i == 0 else MotionIncrement(1.0, 8.0, 0.0, 0.01, 1e-6)
        results.append(filt.step(epoch, motion))
    return results


@pytest.mark.parametrize('scale', [0.25, 4.0])
def test_the_adaptive_filter_does_not_depend_on_the_stated_variances(scale):
    def run(error_model, var_scale):
        config = FilterConfig(n_particles=300, acquisition_particles=600, n_posteriors=20,
                              heading_acquisition_m=20.0, error_model=error_model)
        return _drive(ParticleFilter(config, frame=FRAME, rng=np.random.default_rng(1)),
                      var_scale)

    same = run('adaptive', 1.0), run('adaptive', scale)
    for a, b in zip(*same):
        np.testing.assert_array_equal(a.position_enu_m, b.position_enu_m)
        assert a.protection_level_m == b.protection_level_m
    # The stated model takes them (the check above could fail): x4 lifts them above its
    # floor (measurement_var_m2).
    stated = run('stated', 1.0), run('stated', 4.0)
    assert any(not np.array_equal(a.position_enu_m, b.position_enu_m)
               for a, b in zip(*stated))


@pytest.mark.parametrize('rate_hz', [1.0, 5.0])
def test_the_correlation_time_of_gauss_markov_errors_is_recovered_at_any_rate(rate_hz):
    # Twelve satellites, each a Gauss-Markov error of 3 m with tau = 5 s, for 120 s.
    rng = np.random.default_rng(8)
    tau, dt, k = 5.0, 1.0 / rate_hz, 12
    phi = np.exp(-dt / tau)
    model = AdaptiveErrorModel(window_s=120.0, prior_correlation_time_s=30.0)
    assert model.correlation_time_s == 30.0                     # the prior before data
    assert not model.correlation_measured
    e = rng.normal(0.0, 3.0, k)
    for i in range(int(120 * rate_hz)):
        e = phi * e + np.sqrt(1.0 - phi * phi) * rng.normal(0.0, 3.0, k)
        model.observe(int(i * dt * S), e, np.full(k, 47.0), 0, np.arange(k))
    assert model.correlation_measured
    assert model.correlation_time_s == pytest.approx(tau, rel=0.25)


def test_epochs_too_far_apart_leave_the_correlation_unmeasured():
    """30 s epochs (a static RINEX file) give no pair at the correlation lag: the model
    says so, and the filter then counts every bias offset in full (core.filter)."""
    rng = np.random.default_rng(9)
    model = AdaptiveErrorModel(window_s=600.0, prior_correlation_time_s=10.0)
    for i in range(40):
        model.observe(int(i * 30 * S), rng.normal(0.0, 3.0, 12), np.full(12, 47.0), 0,
                      np.arange(12))
    assert model.samples > 0 and not model.correlation_measured
    assert model.correlation_time_s == 10.0


def _weak_class_core(rate_hz: float) -> float:
    """The learned core of the weak class after 60 s of one city drive, its residuals
    taken at ``rate_hz``: ten strong satellites (3 m) and two weak ones whose errors
    (12 m) persist with tau = 10 s, the same realisation at every rate (decimated from
    10 Hz, as the robustness matrix decimates a drive)."""
    rng = np.random.default_rng(10)
    dt, tau = 0.1, 10.0
    phi = np.exp(-dt / tau)
    sd = np.r_[np.full(10, 3.0), 12.0, 12.0]
    cn0 = np.r_[np.full(10, 47.0), 27.0, 27.0]
    e = rng.normal(0.0, 1.0, 12) * sd
    model = AdaptiveErrorModel(window_s=60.0)
    step = int(round(1.0 / (rate_hz * dt)))
    for i in range(600):
        e = phi * e + np.sqrt(1.0 - phi * phi) * rng.normal(0.0, 1.0, 12) * sd
        if i % step == 0:
            model.observe(int(i * dt * S), e, cn0, 0, np.arange(12))
    return float(model.fit.core_sd_m[signal_class(np.array([27.0]))[0]])


def test_the_same_drive_at_1_and_5_hz_learns_the_same_error_model(monkeypatch):
    """The prior weighs the same seconds of residuals at every rate: a 1 Hz stream's
    weak class is as wide as at 5 Hz. Counted in epochs (the prior at 30 pseudo-samples
    at every rate) the 1 Hz class stays narrower, near the prior, by more."""
    fast, slow = _weak_class_core(5.0), _weak_class_core(1.0)
    assert slow == pytest.approx(fast, rel=0.05)
    monkeypatch.setattr(error_model, 'RECEIVER_INTERVALS_S', (0.2,))
    counted_fast, counted_slow = _weak_class_core(5.0), _weak_class_core(1.0)
    assert counted_fast == fast                 # 5 Hz: the prior is 30 either way
    assert abs(counted_slow - fast) > 2.0 * abs(slow - fast)
    assert counted_slow < slow


def test_the_streams_interval_is_a_receivers_rate_and_a_sparse_stream_keeps_the_prior():
    rng = np.random.default_rng(11)
    model = AdaptiveErrorModel()
    assert model.prior_strength(30.0) == 30.0               # before any interval
    # A 5 Hz receiver's jittered stamps, an epoch lost now and then: exactly 5 Hz.
    stamps = np.cumsum(rng.choice([0.15, 0.2, 0.25, 0.4], size=60, p=[0.2, 0.5, 0.2, 0.1]))
    for t in stamps:
        model.observe(int(t * S), rng.normal(0.0, 3.0, 12), np.full(12, 47.0), 0)
    assert model.epoch_interval_s == 0.2 and model.prior_strength(30.0) == 30.0
    for rate_hz, strength in ((2.0, 12.0), (1.0, 6.0)):
        model = AdaptiveErrorModel()
        for i in range(20):
            model.observe(int(i / rate_hz * S), rng.normal(0.0, 3.0, 12), np.full(12, 47.0), 0)
        assert model.prior_strength(30.0) == pytest.approx(strength)
    # 30 s epochs cannot be paired at the correlation lag: the count prior stays.
    model = AdaptiveErrorModel()
    for i in range(20):
        model.observe(int(i * 30 * S), rng.normal(0.0, 3.0, 12), np.full(12, 47.0), 0)
    assert model.epoch_interval_s is None and model.prior_strength(30.0) == 30.0
