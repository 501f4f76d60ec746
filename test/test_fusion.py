"""KL-divergence mixture-of-experts weights (paper §5) and camera exclusion.

``camera_fusion`` runs the compiled kernel (``core.kernels.camera``); the numpy forms it
replaced (``oracles.camera_log_q`` and ``oracles.fuse_camera``) are the reference.
"""
import numpy as np
import pytest
from oracles import camera_log_q, fuse_camera
from scipy.optimize import minimize_scalar
from scipy.special import logsumexp

from gnsscam_ros.core.fusion import camera_fusion, match_at_epoch


def normalised(logits):
    return logits - logsumexp(logits, axis=-1, keepdims=True)


def test_alpha_minimises_the_paper_objective(rng):
    n = 300
    positions = rng.normal(scale=5.0, size=(1, n, 3))
    matches = rng.normal(scale=6.0, size=(4, 3))
    log_p = normalised(rng.normal(size=(1, n)))
    result = camera_fusion(positions, matches, log_p, 5.0, None, kl_threshold_nats=1e9)
    log_q = camera_log_q(positions, matches, 5.0)
    raw = []
    for j in range(4):
        q, p = np.exp(log_q[j, 0]), np.exp(log_p[0])

        def objective(log_alpha):
            a = np.exp(log_alpha)
            return np.sum(a * q * np.log(a * q / p))

        best = minimize_scalar(objective, bounds=(-30, 5), method='bounded',
                               options={'xatol': 1e-10})
        raw.append(np.exp(best.x))
    raw = np.array(raw)
    np.testing.assert_allclose(result.alpha[:, 0], raw / raw.sum(), rtol=1e-5)
    kl = np.sum(np.exp(log_q[:, 0]) * (log_q[:, 0] - log_p[0]), axis=1)
    np.testing.assert_allclose(result.kl_nats[:, 0], kl, rtol=1e-12, atol=1e-12)


def test_consistent_camera_outweighs_inconsistent_one(rng):
    positions = rng.normal(scale=5.0, size=(1, 2000, 3))            # GNSS cloud at origin
    log_p = normalised(-0.5 * (positions[..., :2] ** 2).sum(-1) / 25.0)
    matches = np.array([[1.0, 0.0, 0.0], [40.0, 0.0, 0.0]])
    result = camera_fusion(positions, matches, log_p, 5.0, 20.0, kl_threshold_nats=5.0,
                           elsewhere_prob=1e-3)
    assert result.alpha[0, 0] > 0.9 and not result.excluded[0]
    # The mixture pulls the cloud towards the consistent match only.
    w = np.exp(log_p + result.log_q_mix)
    w /= w.sum()
    assert abs(w @ positions[0, :, 0] - 1.0) < 2.0


def test_camera_excluded_when_every_image_disagrees(rng):
    positions = rng.normal(scale=3.0, size=(2, 1000, 3))
    log_p = normalised(-0.5 * (positions[..., :2] ** 2).sum(-1) / 9.0)
    far = np.array([[60.0, y, 0.0] for y in (-5.0, 5.0)])
    result = camera_fusion(positions, far, log_p, 5.0, 20.0, kl_threshold_nats=5.0,
                           elsewhere_prob=1e-3)
    # Normalised weights would still sum to one: exclusion is what keeps it out.
    np.testing.assert_allclose(result.alpha.sum(axis=0), 1.0)
    assert result.excluded.all()
    np.testing.assert_array_equal(result.log_q_mix, 0.0)
    # Without the elsewhere cell (the paper's plain softmax) the same far matches look
    # consistent: relative distances alone cannot reveal them.
    assert not camera_fusion(positions, far, log_p, 5.0, None, 5.0).excluded.any()


def test_match_moved_to_epoch_along_heading():
    out = match_at_epoch(np.array([10.0, 0.0, 0.0]), 10.0, 1.0, np.pi / 2, 0.5)
    np.testing.assert_allclose(out, [10.0, 10.0 * 0.5 + 0.5 * 1.0 * 0.25, 0.0])


@pytest.mark.parametrize('temperature', [1.0, 5.0, 20.0])
def test_oracle_camera_log_q_is_normalised_per_set(rng, temperature):
    positions = rng.normal(scale=50.0, size=(3, 100, 3))
    log_q = camera_log_q(positions, np.zeros(3), temperature)
    np.testing.assert_allclose(logsumexp(log_q, axis=1), 0.0, atol=1e-12)


def test_fusion_far_from_the_origin_is_the_direct_softmax(rng):
    # A cloud 2 km from the map origin and matches around it, one 5 km off: the mixture
    # equals the one of the direct softmax (distances from the coordinates as given).
    offset = np.array([1500.0, -1300.0, 40.0])
    positions = offset + rng.normal(scale=10.0, size=(3, 500, 3))
    matches = offset + rng.normal(scale=10.0, size=(4, 3))
    matches[2, 0] += 5000.0
    log_p = normalised(rng.normal(size=(3, 500)))
    mixed = camera_fusion(positions, matches, log_p, 5.0, 20.0, 5.0, 1e-3)
    d = np.linalg.norm(positions[None] - matches[:, None, None, :], axis=-1)
    logits = np.concatenate([-d / 5.0, np.full((4, 3, 1), -20.0 / 5.0 + np.log(500))], -1)
    q = np.exp(normalised(logits))[..., :500]
    direct = np.log(np.einsum('km,kmn->mn', mixed.alpha, q))
    keep = ~mixed.excluded
    assert keep.any()
    np.testing.assert_allclose(mixed.log_q_mix[keep], direct[keep], rtol=0, atol=1e-9)
    # A particle kilometres from every match: every Q_j underflows, the mixture stays
    # finite (the exact log-sum-exp for those particles).
    lonely = positions.copy()
    lonely[:, 1:, 0] += 20_000.0
    far = camera_fusion(lonely, matches[[0, 1]], log_p, 5.0, 20.0, 1e9, 1e-3)
    assert np.isfinite(far.log_q_mix).all() and far.log_q_mix[:, 1:].max() < -1000.0


def random_case(rng, s, n, k, far=False, underflow=False, spread_m=5.0):
    """Particles (S, N, 4) about a point 2 km from the origin, K matches around it (one
    5 km off with ``far``), a normalised log P; with ``underflow`` some particles sit
    20 km from every match (every Q_j underflows there)."""
    centre = np.array([1500.0, -1300.0, 40.0])
    particles = np.empty((s, n, 4))
    particles[..., :3] = centre + rng.normal(scale=spread_m, size=(s, n, 3))
    particles[..., 3] = rng.uniform(-np.pi, np.pi, (s, n))
    matches = centre + rng.normal(scale=10.0, size=(k, 3))
    if far:
        matches[0, 0] += 5000.0
    if underflow:
        particles[:, -7:, 0] += 20_000.0
    log_p = normalised(rng.normal(scale=3.0, size=(s, n)))
    return particles, matches, log_p


@pytest.mark.parametrize('k,far,underflow,gate', [
    (1, False, False, 20.0), (4, True, False, 20.0), (4, False, True, 20.0),
    (16, False, False, 20.0), (16, True, True, 20.0), (3, True, True, None),
    (10, False, False, 20.0)])
def test_kernel_equals_the_numpy_oracle(rng, k, far, underflow, gate):
    for s, n in ((1, 1), (3, 7), (5, 400)):
        particles, matches, log_p = random_case(rng, s, n, k, far, underflow and n > 7)
        got = camera_fusion(particles, matches, log_p, 5.0, gate, 5.0, 1e-3)
        ref = fuse_camera(log_p, camera_log_q(particles, matches, 5.0, gate), 5.0,
                          None if gate is None else 1e-3)
        assert got.log_q_mix.shape == (s, n) and got.alpha.shape == (k, s)
        np.testing.assert_array_equal(got.excluded, ref.excluded)
        np.testing.assert_allclose(got.log_q_mix, ref.log_q_mix, rtol=0, atol=1e-9)
        np.testing.assert_allclose(got.alpha, ref.alpha, rtol=0, atol=1e-10)
        np.testing.assert_allclose(got.kl_nats, ref.kl_nats, rtol=1e-10, atol=1e-9)


def test_kernel_excludes_like_the_oracle_around_the_threshold(rng):
    # Far matches put the divergences near log(1 / elsewhere_prob) = 6.9: thresholds
    # on both sides of the sets' smallest KL exclude exactly the same sets.
    particles, matches, log_p = random_case(rng, 8, 300, 3)
    matches += [25.0, 0.0, 0.0]
    ref_kl = fuse_camera(log_p, camera_log_q(particles, matches, 5.0, 20.0), 1e9,
                         1e-3).kl_nats.min(axis=0)
    for threshold in np.sort(ref_kl)[:-1] + np.diff(np.sort(ref_kl)) / 2:
        got = camera_fusion(particles, matches, log_p, 5.0, 20.0, threshold, 1e-3)
        np.testing.assert_array_equal(got.excluded, ref_kl > threshold)
        assert 0 < got.excluded.sum() < 8
        np.testing.assert_array_equal(got.log_q_mix[got.excluded], 0.0)


def test_fusion_rejects_what_does_not_fit(rng):
    particles, matches, log_p = random_case(rng, 2, 10, 2)
    with pytest.raises(ValueError, match='elsewhere_prob'):
        camera_fusion(particles, matches, log_p, 5.0, 20.0, 5.0)
    with pytest.raises(ValueError, match='log_p'):
        camera_fusion(particles, matches, log_p[:, :5], 5.0, 20.0, 5.0, 1e-3)
    with pytest.raises(ValueError, match='matches'):
        camera_fusion(particles, np.zeros((0, 3)), log_p, 5.0, 20.0, 5.0, 1e-3)
    # One match may come as (3,).
    one = camera_fusion(particles, matches[0], log_p, 5.0, 20.0, 5.0, 1e-3)
    np.testing.assert_allclose(one.log_q_mix, camera_fusion(
        particles, matches[:1], log_p, 5.0, 20.0, 5.0, 1e-3).log_q_mix)


def test_measurements_moved_to_epoch_with_odometry():
    from gnsscam_ros.core.fusion import CameraMeasurement, measurements_at_epoch
    from gnsscam_ros.core.types import OdometrySeries
    t = np.arange(0, 21) * 100_000_000                            # 10 Hz over 2 s
    odo = OdometrySeries(t, np.full(21, 10.0), np.zeros(21), np.zeros(21), np.zeros(21))
    matches = [CameraMeasurement(500_000_000, np.array([0.0, 0.0, 0.0]), 0.5, 7),
               CameraMeasurement(1_500_000_000, np.array([1.0, 0.0, 0.0]), 0.4, 8)]
    out = measurements_at_epoch(matches, odo, 0, 1_000_000_000, yaw_prev_rad=np.pi / 2)
    assert [m.frame_id for m in out] == [7]
    np.testing.assert_allclose(out[0].position_enu_m, [0.0, 5.0, 0.0], atol=1e-9)
