"""Protection level, bias hypotheses and unknown motion: known answers and properties."""
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from oracles import projected_weights
from synthetic import FRAME, epoch_at, sky

from gnsscam_ros.core import integrity
from gnsscam_ros.core.bias import (BiasHypotheses, BiasModel, beyond_cloud, hidden_fault_sizes,
                                   leverages, with_hidden_faults)
from gnsscam_ros.core.filter import UPDATED, FilterConfig, ParticleFilter
from gnsscam_ros.core.motion import (ADDED, RESET, DeadReckoningState, MotionAccumulator)
from gnsscam_ros.core.particles import MotionIncrement
from gnsscam_ros.core.verdict import integrity_verdict

SECOND = 1_000_000_000
EXCERPT = Path(__file__).parent / 'data' / 'smartloc_excerpt'


# ============================================================ bound and q_max
@pytest.mark.parametrize('method', [integrity.EXACT, integrity.APPROX])
@pytest.mark.parametrize('eps', [0.01, 0.05, 0.09])
def test_max_empirical_risk_is_where_the_bound_meets_the_target(method, eps):
    target = 0.1
    q = integrity.max_empirical_risk(target, eps, method)
    assert 0.0 < q < target
    assert integrity.upper_risk(q, eps, method) == pytest.approx(target, abs=1e-9)
    assert integrity.upper_risk(q * 1.01, eps, method) > target


def test_exact_floor_and_no_certification_below_it():
    # With R_M = 0 the exact bound is 1 - exp(-eps) > 0: it never collapses to 0...
    eps = integrity.divergence_budget(0.0, 10, 0.1)
    assert integrity.upper_risk(0.0, eps) == pytest.approx(1 - np.exp(-eps))
    assert integrity.certifiable_target(10, 0.1) == pytest.approx(0.375, abs=1e-3)
    # ...so M = 10 can never certify 0.1: q_max = 0 and the level is infinite.
    assert integrity.max_empirical_risk(0.1, eps) == 0.0
    cloud = integrity.PosteriorSet(np.zeros((1, 5, 3)), np.full((1, 5), -np.log(5)),
                                   np.zeros(10, int), np.zeros((10, 3)))
    assert cloud.protection_level(np.zeros(3), 0.0) == np.inf
    # The paper's approximation does collapse to 0 at R_M = 0 (reproduction only).
    assert integrity.upper_risk(0.0, eps, integrity.APPROX) == 0.0


def test_default_configuration_can_certify():
    cfg = FilterConfig()
    assert cfg.inverse_bernoulli == integrity.EXACT
    assert integrity.certifiable_target(cfg.n_posteriors, cfg.risk_delta) < cfg.target_risk
    # Even with a KL of 1 nat per epoch there is room: q_max > 0.
    eps = integrity.divergence_budget(1.0, cfg.n_posteriors, cfg.risk_delta)
    assert integrity.max_empirical_risk(cfg.target_risk, eps) > 0.0


# ============================================================ protection level
def gaussian_set(sigma_m, n=200_000, m=4, seed=0):
    rng = np.random.default_rng(seed)
    pos = rng.normal(0.0, sigma_m, (m, n // m, 3))
    log_w = np.full((m, n // m), -np.log(n // m))
    return integrity.PosteriorSet(pos, log_w, np.arange(m), np.zeros((m, 3)))


@pytest.mark.parametrize('q_max', [0.011, 0.03, 0.1])
def test_protection_level_of_a_gaussian_cloud_is_the_closed_form(q_max):
    # Horizontal distance of an isotropic 2D Gaussian: P(d >= r) = exp(-r^2 / (2 s^2)).
    sigma = 3.0
    level = gaussian_set(sigma).protection_level(np.zeros(3), q_max)
    assert level == pytest.approx(sigma * np.sqrt(-2 * np.log(q_max)), rel=0.02)


def test_protection_level_is_the_crossing_of_a_monotone_bound():
    cfg = FilterConfig()
    cloud = gaussian_set(4.0, n=40_000, m=cfg.n_posteriors)
    centre = np.array([0.5, -0.3, 0.0])
    eps = integrity.divergence_budget(0.2, cfg.n_posteriors, cfg.risk_delta)
    radii = np.linspace(0.0, 30.0, 121)
    bound = integrity.upper_risk(cloud.hazard_mass(centre, radii), eps)
    assert np.all(np.diff(bound) <= 1e-12)                   # non-increasing in r
    level = cloud.protection_level(centre, integrity.max_empirical_risk(0.1, eps))
    above, below = level * 1.0001 + 1e-9, level * 0.99
    assert integrity.upper_risk(cloud.hazard_mass(centre, [above]), eps)[0] <= 0.1
    assert integrity.upper_risk(cloud.hazard_mass(centre, [below]), eps)[0] > 0.1


@pytest.mark.slow
@settings(max_examples=60, deadline=None)
@given(st.integers(1, 50), st.floats(0.001, 0.3), st.integers(0, 10_000))
def test_protection_level_matches_a_full_sort(n_samples, q_max, seed):
    """The partitioned search equals the plain weighted quantile of all M * N distances."""
    rng = np.random.default_rng(seed)
    pos = rng.normal(0.0, 5.0, (n_samples, 300, 3))
    log_w = np.log(rng.dirichlet(np.full(300, 0.3), n_samples))
    log_w -= np.log(np.exp(log_w).sum(1, keepdims=True))
    m = 3 * n_samples
    cloud = integrity.PosteriorSet(pos, log_w, np.arange(m) % n_samples,
                                   rng.normal(0.0, 3.0, (m, 3)))
    dist, w = cloud.distances(np.zeros(3))
    d, w = dist.ravel(), w.ravel() / m
    order = np.argsort(d)
    d, w = d[order], w[order]
    tail = np.cumsum(w[::-1])[::-1]
    k = int(np.searchsorted(-tail, -q_max))
    assert cloud.protection_level(np.zeros(3), q_max) == (d[k - 1] if k else 0.0)


def test_offsets_displace_the_posteriors():
    sharp = integrity.PosteriorSet(np.zeros((1, 10, 3)), np.full((1, 10), -np.log(10)),
                                   np.zeros(4, int), np.array([[3.0, 4.0, 0.0]] * 4))
    assert sharp.hazard_mass(np.zeros(3), [4.99, 5.01]) == pytest.approx([1.0, 0.0])
    mean, cov = sharp.pooled_moments()
    assert mean == pytest.approx([-3.0, -4.0, 0.0]) and cov == pytest.approx(np.zeros((3, 3)))


# ============================================================ bias hypotheses
def geometry(k=8, seed=3):
    rng = np.random.default_rng(seed)
    az, el = rng.uniform(0, 2 * np.pi, k), rng.uniform(0.3, 1.3, k)
    return np.stack([np.cos(el) * np.sin(az), np.cos(el) * np.cos(az), np.sin(el)], 1)


def test_projected_weights_remove_each_clock():
    sys_index = np.array([0, 0, 0, 1, 1, 1])
    wp = projected_weights(np.array([1.0, 2.0, 0.5, 1.0, 1.0, 3.0]), sys_index, 2)
    for s in range(2):
        assert wp @ (sys_index == s).astype(float) == pytest.approx(np.zeros(6), abs=1e-12)


def test_a_constant_bias_converges_to_the_least_squares_offset():
    """Repeated updates with a constant bias move the offset to what weighted least squares
    with a clock per constellation would make of that bias."""
    los = geometry()
    k = los.shape[0]
    sys_index = np.array([0] * 5 + [1] * 3)
    weights = np.full(k, 0.1)
    bias = np.zeros((k, 1))
    bias[2, 0] = 20.0
    hyp = BiasHypotheses(BiasModel(1.0, 0.0, 40.0, 50.0), 1, np.random.default_rng(0))
    g = -los
    wp = projected_weights(weights, sys_index, 2)
    info = g.T @ wp @ g
    q = np.eye(3) * 20.0
    post = np.linalg.inv(info)                          # steady state of P+ = (P- + Q)^-1..
    for _ in range(30):
        post = np.linalg.inv(np.linalg.inv(post + q) + info)
    for _ in range(2000):
        hyp.update(bias, los, weights, sys_index, 2, post + q, post)
    onehot = np.eye(2)[sys_index]
    design = np.hstack([g, onehot])
    solution = np.linalg.lstsq(design * np.sqrt(weights)[:, None],
                               bias[:, 0] * np.sqrt(weights), rcond=None)[0]
    assert hyp.offsets_m[0] == pytest.approx(solution[:3], rel=1e-3)


def test_leverages_are_the_share_of_its_own_bias_the_estimate_absorbs():
    """The hat matrix's diagonal: a bias b on one satellite leaves (1 - h) b in its own
    least-squares residual; the leverages add up to the unknowns; a satellite of weight 0
    has none, and with as many satellites as unknowns each has 1."""
    los = geometry()
    k = los.shape[0]
    sys_index = np.array([0] * 5 + [1] * 3)
    weights = np.linspace(0.05, 0.2, k)
    h = leverages(los, weights, sys_index, 2)
    design = np.hstack([-los, np.eye(2)[sys_index]])
    for i in range(k):
        bias = np.zeros(k)
        bias[i] = 10.0
        sol = np.linalg.lstsq(design * np.sqrt(weights)[:, None], bias * np.sqrt(weights),
                              rcond=None)[0]
        assert (bias - design @ sol)[i] == pytest.approx((1.0 - h[i]) * 10.0, rel=1e-9)
    assert h.sum() == pytest.approx(5.0, rel=1e-9)
    weights[0] = 0.0
    assert leverages(los, weights, sys_index, 2)[0] == pytest.approx(0.0, abs=1e-12)
    one_clock = leverages(los[:4], np.full(4, 0.1), np.zeros(4, int), 1)
    assert one_clock == pytest.approx(np.ones(4), abs=1e-9)


def test_hidden_faults_leave_their_residual_within_c_of_its_noise():
    core = np.array([2.0, 5.0, 5.0, 8.0])
    lev = np.array([0.0, 0.75, 0.96, 1.0])
    sizes = hidden_fault_sizes(core, lev, 1.5, np.full(4, 60.0))
    assert sizes[:3] == pytest.approx([3.0, 15.0, 37.5])
    # (1 - h) b against the residual's spread sigma sqrt(1 - h): c exactly.
    assert ((1 - lev[:3]) * sizes[:3] / (core[:3] * np.sqrt(1 - lev[:3]))
            == pytest.approx([1.5] * 3))
    assert sizes[3] == 60.0                 # no redundancy: the error model's largest error
    biases = np.zeros((3, 7))
    faulted = with_hidden_faults(biases, np.array([1.0, 2.0, 3.0]))
    # Hypothesis m: satellite m mod 3, +size in the first round, -size in the second.
    expected = np.zeros((3, 7))
    for m in range(7):
        expected[m % 3, m] = (1.0 if (m // 3) % 2 == 0 else -1.0) * (m % 3 + 1.0)
    assert faulted == pytest.approx(expected)
    assert not biases.any()                  # a copy


def test_hidden_faults_widen_the_level_where_satellites_are_few():
    """One satellite's unseen bias moves a five-satellite solution much more than a
    twelve-satellite one: the level grows there, and little with twelve (2 m noise,
    static, one clock)."""
    def level(n_sv, core_sds):
        rng = np.random.default_rng(5)
        filt = ParticleFilter(small_config(hidden_fault_core_sds=core_sds), frame=FRAME,
                              rng=np.random.default_rng(0))
        sv = sky(n_sv, seed=2)
        out = []
        for i in range(40):
            epoch = epoch_at(np.zeros(3), clock_m=100.0, sv_ecef=sv, stamp_ns=i * SECOND)
            epoch = replace(epoch, pr_m=epoch.pr_m + rng.normal(0.0, 2.0, n_sv))
            out.append(filt.step(epoch, None if i == 0 else MotionIncrement.stationary(1.0)))
        return float(np.median([r.protection_level_m for r in out[20:]]))
    few = level(5, 1.0), level(5, 0.0)
    many = level(12, 1.0), level(12, 0.0)
    # Measured: 16.0 against 5.7 m with five, 1.80 against 1.53 m with twelve.
    assert few[0] > 2.0 * few[1], few
    assert many[0] < 1.3 * many[1], many


def test_the_offsets_shrink_only_once_the_persistence_is_measured():
    """Static, 12 satellites of 3 m Gauss-Markov errors: at 1 s epochs the error model
    measures how long the errors persist and the level is narrower beyond the cloud; at
    30 s epochs it cannot, and the level is the one with every offset in full, to the
    bit."""
    def levels(dt_s, beyond):
        rng = np.random.default_rng(5)
        filt = ParticleFilter(small_config(bias_beyond_cloud=beyond), frame=FRAME,
                              rng=np.random.default_rng(0))
        sv = sky(12, seed=2)
        error = rng.normal(0.0, 3.0, 12)
        phi = np.exp(-dt_s / 5.0)
        out = []
        for i in range(60):
            error = phi * error + np.sqrt(1.0 - phi * phi) * rng.normal(0.0, 3.0, 12)
            epoch = epoch_at(np.zeros(3), clock_m=100.0, sv_ecef=sv,
                             stamp_ns=int(i * dt_s * SECOND))
            epoch = replace(epoch, pr_m=epoch.pr_m + error)
            out.append(filt.step(epoch, None if i == 0
                                 else MotionIncrement.stationary(dt_s)).protection_level_m)
        return np.array(out[20:]), filt.errors.correlation_measured
    sparse, measured = levels(30.0, True)
    assert not measured
    np.testing.assert_array_equal(sparse, levels(30.0, False)[0])
    dense, measured = levels(1.0, True)
    full = levels(1.0, False)[0]
    assert measured and (dense <= full + 1e-9).all() and np.median(dense) < np.median(full)


def test_information_from_elsewhere_shrinks_the_offsets():
    los = geometry()
    k = los.shape[0]
    sys_index = np.zeros(k, int)
    weights = np.full(k, 0.1)
    bias = np.random.default_rng(1).normal(0, 10, (k, 50))
    g = -los
    info = g.T @ projected_weights(weights, sys_index, 1) @ g
    prior = np.eye(3) * 4.0
    alone = BiasHypotheses(BiasModel(1.0, 0.0, 40.0, 50.0), 50, np.random.default_rng(0))
    alone.update(bias, los, weights, sys_index, 1, prior,
                 np.linalg.inv(np.linalg.inv(prior) + info))
    helped = BiasHypotheses(BiasModel(1.0, 0.0, 40.0, 50.0), 50, np.random.default_rng(0))
    helped.update(bias, los, weights, sys_index, 1, prior,
                  np.linalg.inv(np.linalg.inv(prior) + info + np.eye(3) * 5.0))
    assert (np.linalg.norm(helped.offsets_m, axis=1)
            < np.linalg.norm(alone.offsets_m, axis=1)).all()


def test_beyond_cloud_keeps_the_faults_and_what_exceeds_the_spread():
    """Known answers: the Gauss-Markov part's second moment becomes ``(O - C)_+``, the
    hidden-fault part is kept as it is, the vertical is left alone in the horizontal
    case."""
    rng = np.random.default_rng(4)
    m = 4000
    gm = rng.standard_normal((m, 3)) * np.array([5.0, 2.0, 7.0])     # O = diag(25, 4, 49)
    faults = np.zeros((m, 3))
    faults[::10, 0] = 12.0
    offsets = gm + faults
    moment = gm[:, :2].T @ gm[:, :2] / m
    cloud = np.diag([9.0, 9.0, 1.0])
    out = beyond_cloud(offsets, faults, cloud, 2)
    kept = out - faults
    np.testing.assert_allclose(kept[:, :2].T @ kept[:, :2] / m,
                               np.diag(np.maximum(np.diag(moment) - 9.0, 0.0)), atol=0.05)
    np.testing.assert_array_equal(out[:, 2], offsets[:, 2])
    # The shrink keeps each hypothesis's direction along a principal axis.
    assert np.all(np.sign(kept[:, 0]) == np.sign(gm[:, 0]))
    # 4 m^2 < 9 m^2 (the sample moment is not exactly diagonal: millimetres remain).
    np.testing.assert_allclose(kept[:, 1], 0.0, atol=0.01)
    # No cloud: everything stays; a cloud wider than every offset: only the faults stay.
    np.testing.assert_allclose(beyond_cloud(offsets, faults, np.zeros((3, 3)), 3), offsets)
    np.testing.assert_allclose(beyond_cloud(offsets, faults, np.eye(3) * 100.0, 3), faults,
                               atol=1e-9)
    # No Gauss-Markov part at all: nothing to shrink.
    np.testing.assert_array_equal(beyond_cloud(faults, faults, cloud, 2), faults)


def test_fault_offsets_are_the_update_of_the_faults_alone():
    """The update is linear in the biases: the fault part of the offsets is what the
    faults alone would have moved, the rest what the Gauss-Markov biases alone would."""
    los = geometry()
    k = los.shape[0]
    sys_index = np.zeros(k, int)
    weights = np.full(k, 0.1)
    rng = np.random.default_rng(6)
    prior = np.eye(3) * 4.0
    posterior = np.eye(3) * 2.0
    model = BiasModel(1.0, 0.0, 40.0, 50.0)
    both, gm_only, faults_only = (BiasHypotheses(model, 30, np.random.default_rng(0))
                                  for _ in range(3))
    for _ in range(3):
        gm = rng.normal(0.0, 5.0, (k, 30))
        faults = with_hidden_faults(np.zeros((k, 30)), np.full(k, 9.0))
        both.update(gm + faults, los, weights, sys_index, 1, prior, posterior, faults)
        gm_only.update(gm, los, weights, sys_index, 1, prior, posterior)
        faults_only.update(faults, los, weights, sys_index, 1, prior, posterior)
    np.testing.assert_allclose(both.fault_offsets_m, faults_only.offsets_m, atol=1e-9)
    np.testing.assert_allclose(both.offsets_m - both.fault_offsets_m, gm_only.offsets_m,
                               atol=1e-9)
    assert np.abs(both.fault_offsets_m).max() > 1.0
    np.testing.assert_array_equal(gm_only.fault_offsets_m, 0.0)


def test_biases_are_gauss_markov_with_the_model_size():
    model = BiasModel(floor_m=3.0, residual_scale=0.0, cn0_knee_dbhz=40.0,
                      correlation_time_s=10.0)
    hyp = BiasHypotheses(model, 20_000, np.random.default_rng(2))
    keys, cn0 = np.array([1001, 4005]), np.array([60.0, 30.0])
    b0 = hyp.biases_at(0, keys, cn0)
    assert b0.std(axis=1) == pytest.approx(model.sigma_m(cn0, 0.0), rel=0.03)
    assert model.sigma_m(cn0, 0.0) == pytest.approx([3.0 * np.sqrt(1.01), 3.0 * np.sqrt(11)],
                                                    rel=1e-3)
    b1 = hyp.biases_at(10 * SECOND, keys, cn0)
    corr = [np.corrcoef(b0[i], b1[i])[0, 1] for i in range(2)]
    assert corr == pytest.approx([np.exp(-1.0)] * 2, abs=0.03)
    assert b1.std(axis=1) == pytest.approx(model.sigma_m(cn0, 0.0), rel=0.03)
    # A larger residual RMS scales the hypotheses up, never below the floor.
    assert model.sigma_m(cn0[:1], 100.0)[0] == pytest.approx(0.0 + 3.0 * np.sqrt(1.01))
    wider = BiasModel(3.0, 0.2, 40.0, 10.0)
    assert wider.sigma_m(cn0[:1], 100.0)[0] == pytest.approx(20.0 * np.sqrt(1.01))


def test_all_satellites_at_once_are_the_one_by_one_advance_bit_for_bit():
    """New satellites, ones seen before, a repeated stamp, one back after a gap: the
    vectorised advance gives the values of the one-by-one rule (which an epoch listing a
    satellite twice still takes)."""
    model = BiasModel(2.0, 0.2, 40.0, 20.0)
    fast = BiasHypotheses(model, 7, np.random.default_rng(3))
    slow = BiasHypotheses(model, 7, np.random.default_rng(3))
    rng = np.random.default_rng(4)
    for stamp_s, keys in [(0.0, [11, 12, 13]), (1.0, [12, 13, 14]), (1.0, [12, 15]),
                          (2.5, [11, 12, 13, 14, 15]), (400.0, [11, 16])]:
        keys = np.array(keys)
        cn0 = rng.uniform(25.0, 50.0, keys.size)
        stamp = int(stamp_s * SECOND) + 1_718_000_000 * SECOND
        got = fast.biases_at(stamp, keys, cn0)
        sigma = model.sigma_m(cn0, 0.0)
        want = slow._advance_one_by_one(stamp, keys.tolist(), sigma,
                                        slow.rng.standard_normal((keys.size, 7)),
                                        model.correlation_time_s)
        np.testing.assert_array_equal(got, want)


# ============================================================ motion loss and resets
def state(t_s, x, var=None):
    return DeadReckoningState(int(t_s * SECOND), x, 0.0, 0.0, 8.0, 0.0, 0.01, 1e-6,
                              0.01 * t_s if var is None else var, 1e-6 * t_s)


def test_a_restarted_dead_reckoner_is_a_reset_not_a_jump():
    acc = MotionAccumulator(max_speed_mps=40.0)
    assert [acc.add(state(t, 8.0 * t)) for t in (0, 1, 2)] == [ADDED] * 3
    # imu_node restarted: the new run starts at its origin with zero variance.
    assert acc.add(state(3, 0.0, var=0.0)) == RESET
    assert acc.add(state(4, 8.0, var=0.01)) == ADDED
    assert acc.resets == 1
    motion = acc.increment(1 * SECOND, 4 * SECOND)
    assert motion.distance_m == pytest.approx(16.0)          # 1-2 and 3-4 s
    assert motion.unknown_s == pytest.approx(1.0)            # 2-3 s is not motion
    # A jump faster than the maximum speed is a reset as well.
    assert acc.add(state(5, 8.0 + 500.0, var=0.02)) == RESET


def run_static(filt, epochs, motion_of):
    out = []
    for i in range(epochs):
        epoch = epoch_at(np.zeros(3), clock_m=100.0, stamp_ns=i * SECOND)
        out.append(filt.step(epoch, None if i == 0 else motion_of(i)))
    return out


def small_config(**kw):
    base = dict(n_particles=400, acquisition_particles=0, init_position_sd_m=5.0,
                init_vertical_sd_m=5.0, n_posteriors=100, alert_limit_m=25.0,
                error_correlation_time_s=1.0, heading_acquisition_m=0.0,
                integrity_settling_s=10.0)
    base.update(kw)
    return FilterConfig(**base)


@pytest.mark.slow
def test_a_tight_consistent_cloud_is_certified_with_the_defaults():
    filt = ParticleFilter(small_config(), frame=FRAME, rng=np.random.default_rng(0))
    results = run_static(filt, 30, lambda i: MotionIncrement.stationary(1.0))
    last = results[-1]
    verdict = integrity_verdict(last, filt.config)
    assert last.status == UPDATED and verdict.ok and verdict.reasons == ()
    assert 0.0 < last.protection_level_m <= 25.0
    assert last.risk.risk_bound[0] <= 0.1
    assert np.linalg.norm(last.position_enu_m[:2]) < last.protection_level_m


def test_unknown_motion_grows_the_level_and_is_never_ok():
    filt = ParticleFilter(small_config(), frame=FRAME, rng=np.random.default_rng(0))
    known = run_static(filt, 20, lambda i: MotionIncrement.stationary(1.0))
    lost = [filt.step(epoch_at(np.zeros(3), clock_m=100.0, stamp_ns=(20 + i) * SECOND),
                      None) for i in range(5)]
    assert integrity_verdict(known[-1], filt.config).ok
    verdicts = [integrity_verdict(r, filt.config) for r in lost]
    assert all(r.status == UPDATED and not v.ok and r.motion_unknown_s == 1.0
               and 'motion unknown' in v.reasons[0] for r, v in zip(lost, verdicts))
    assert lost[-1].protection_level_m > 2.0 * known[-1].protection_level_m


# ============================================================ real data end to end
@pytest.mark.slow
def test_protection_level_bounds_the_error_on_the_real_excerpt():
    """The committed smartLoc excerpt (real Berlin data): every updated epoch has a finite
    level, and once converged it bounds the error in at least 90 % of the epochs."""
    from gnsscam_ros.datasets.smartloc import load_smartloc_args
    from gnsscam_ros.evaluation.runner import run_filter
    drive = load_smartloc_args(EXCERPT)
    record = run_filter(drive, FilterConfig(), seed=1)
    level = record.protection_level_m
    assert level.size > 50 and np.isfinite(level).all()
    diff = record.estimate_enu_m - record.truth_enu_m
    error = np.hypot(diff[:, 0], diff[:, 1])
    later = slice(len(error) // 3, None)
    assert np.mean(error[later] > level[later]) <= 0.10
    # OK at an alert limit of 50 m: the error is then within it.
    ok = level <= 50.0
    assert ok[later].any() and (error[ok] <= 50.0).all()


def test_injected_faults_bias_the_chosen_satellites_for_their_episode():
    from gnsscam_ros.datasets.faults import FaultEpisodes, inject_pseudorange_faults
    from gnsscam_ros.datasets.smartloc import load_smartloc_args
    drive = load_smartloc_args(EXCERPT)
    spec = FaultEpisodes(episodes=3, satellites=(2, 2), bias_m=(50.0, 50.0),
                         duration_s=(10.0, 10.0))
    faulty = inject_pseudorange_faults(drive, seed=4, faults=spec)
    assert faulty.gnss[0].pr_m is not drive.gnss[0].pr_m          # a copy, input intact
    diffs = [f.pr_m - e.pr_m for f, e in zip(faulty.gnss, drive.gnss)]
    added = np.concatenate(diffs)
    assert int(np.count_nonzero(added)) == faulty.info['faulty_measurements'] > 0
    episodes = faulty.info['injected_faults']
    assert all(len(x['satellites']) == 2 and x['duration_s'] == 10.0 for x in episodes)
    for e, d in zip(faulty.gnss, diffs):
        expected = np.zeros(e.n_sv)
        for x in episodes:
            if x['start_ns'] <= e.stamp_ns < x['start_ns'] + 10 * SECOND:
                for (sys_id, sv), bias in zip(x['satellites'], x['bias_m']):
                    expected[(e.system == sys_id) & (e.sv_id == sv)] += bias
        np.testing.assert_allclose(d, expected, atol=1e-6)
    # The same seed draws the same faults.
    again = inject_pseudorange_faults(drive, seed=4, faults=spec)
    assert again.info['injected_faults'] == faulty.info['injected_faults']


def test_distances_equal_the_direct_formula():
    rng = np.random.default_rng(5)
    pos = rng.normal(0.0, 20.0, (4, 50, 3)) + [3000.0, -2000.0, 40.0]
    cloud = integrity.PosteriorSet(pos, np.full((4, 50), -np.log(50)), np.arange(10) % 4,
                                   rng.normal(0.0, 8.0, (10, 3)))
    centre = np.array([3001.0, -1999.0, 41.0])
    dist, _ = cloud.distances(centre)
    direct = np.linalg.norm((pos[cloud.motion_index] - cloud.offsets_m[:, None, :]
                             - centre)[..., :2], axis=-1)
    np.testing.assert_allclose(dist, direct, rtol=1e-5, atol=1e-4)


def test_level_is_invariant_to_the_order_of_tied_particles():
    # Resampled sets hold many copies of few particles: the level is a distance value
    # whose strict tail fits, so any order of the copies gives the same level and masses.
    rng = np.random.default_rng(8)
    few = rng.normal(0.0, 4.0, (2, 30, 3))
    pos = few[:, rng.integers(0, 30, 600)]
    log_w = np.full((2, 600), -np.log(600))
    offsets = rng.normal(0.0, 1.0, (6, 3))
    cloud = integrity.PosteriorSet(pos, log_w, np.arange(6) % 2, offsets)
    order = rng.permutation(600)
    shuffled = integrity.PosteriorSet(pos[:, order], log_w, np.arange(6) % 2, offsets)
    for q_max in (0.013, 0.05, 0.2):
        masses, level = cloud.risk_and_level(np.zeros(3), [4.0, 8.0], q_max)
        again = shuffled.risk_and_level(np.zeros(3), [4.0, 8.0], q_max)
        assert again[1] == level
        np.testing.assert_allclose(again[0], masses, rtol=0, atol=1e-14)
        dist, _ = cloud.distances(np.zeros(3))
        assert level in set(dist.ravel())
