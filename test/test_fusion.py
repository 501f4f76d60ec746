"""KL-divergence mixture-of-experts weights (paper §5) and camera exclusion."""
import numpy as np
import pytest
from scipy.optimize import minimize_scalar
from scipy.special import logsumexp

from gnsscam_ros.core.fusion import camera_log_q, fuse_camera, match_at_epoch


def normalised(logits):
    return logits - logsumexp(logits, axis=-1, keepdims=True)


def test_alpha_minimises_the_paper_objective(rng):
    n = 300
    log_p = normalised(rng.normal(size=(1, n)))
    log_q = normalised(rng.normal(scale=2.0, size=(4, 1, n)))
    result = fuse_camera(log_p, log_q, kl_threshold_nats=1e9)
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
    np.testing.assert_allclose(result.kl_nats[:, 0], kl)


def test_consistent_camera_outweighs_inconsistent_one(rng):
    positions = rng.normal(scale=5.0, size=(1, 2000, 3))            # GNSS cloud at origin
    log_p = normalised(-0.5 * (positions[..., :2] ** 2).sum(-1) / 25.0)
    good = camera_log_q(positions, np.array([1.0, 0.0, 0.0]), 5.0, gate_m=20.0)
    bad = camera_log_q(positions, np.array([40.0, 0.0, 0.0]), 5.0, gate_m=20.0)
    result = fuse_camera(log_p, np.stack([good, bad]), kl_threshold_nats=5.0,
                         elsewhere_prob=1e-3)
    assert result.alpha[0, 0] > 0.9 and not result.excluded[0]
    # The mixture pulls the cloud towards the consistent match only.
    w = np.exp(log_p + result.log_q_mix)
    w /= w.sum()
    assert abs(w @ positions[0, :, 0] - 1.0) < 2.0


def test_camera_excluded_when_every_image_disagrees(rng):
    positions = rng.normal(scale=3.0, size=(2, 1000, 3))
    log_p = normalised(-0.5 * (positions[..., :2] ** 2).sum(-1) / 9.0)
    far = [camera_log_q(positions, np.array([60.0, y, 0.0]), 5.0, gate_m=20.0)
           for y in (-5.0, 5.0)]
    result = fuse_camera(log_p, np.stack(far), kl_threshold_nats=5.0, elsewhere_prob=1e-3)
    # Normalised weights would still sum to one: exclusion is what keeps it out.
    np.testing.assert_allclose(result.alpha.sum(axis=0), 1.0)
    assert result.excluded.all()
    np.testing.assert_array_equal(result.log_q_mix, 0.0)
    # Without the elsewhere cell (the paper's plain softmax) the same far matches look
    # consistent: relative distances alone cannot reveal them.
    plain = [camera_log_q(positions, np.array([60.0, y, 0.0]), 5.0) for y in (-5.0, 5.0)]
    assert not fuse_camera(log_p, np.stack(plain), kl_threshold_nats=5.0).excluded.any()


def test_match_moved_to_epoch_along_heading():
    out = match_at_epoch(np.array([10.0, 0.0, 0.0]), 10.0, 1.0, np.pi / 2, 0.5)
    np.testing.assert_allclose(out, [10.0, 10.0 * 0.5 + 0.5 * 1.0 * 0.25, 0.0])


@pytest.mark.parametrize('temperature', [1.0, 5.0, 20.0])
def test_camera_log_q_is_normalised_per_set(rng, temperature):
    positions = rng.normal(scale=50.0, size=(3, 100, 3))
    log_q = camera_log_q(positions, np.zeros(3), temperature)
    np.testing.assert_allclose(logsumexp(log_q, axis=1), 0.0, atol=1e-12)


def test_camera_log_q_of_k_matches_is_the_direct_softmax_far_from_the_origin(rng):
    # A cloud 2 km from the map origin and matches around it, one 5 km off: the batched
    # distances (one matrix product) equal the direct ones, and so does the mixture.
    offset = np.array([1500.0, -1300.0, 40.0])
    positions = offset + rng.normal(scale=10.0, size=(3, 500, 3))
    matches = offset + rng.normal(scale=10.0, size=(4, 3))
    matches[2, 0] += 5000.0
    batched = camera_log_q(positions, matches, 5.0, gate_m=20.0)
    assert batched.shape == (4, 3, 501)
    for k, match in enumerate(matches):
        d = np.linalg.norm(positions - match, axis=-1)
        logits = np.concatenate([-d / 5.0, np.full((3, 1), -20.0 / 5.0 + np.log(500))], -1)
        np.testing.assert_allclose(batched[k], normalised(logits), rtol=0, atol=1e-9)
        np.testing.assert_allclose(camera_log_q(positions, match, 5.0, 20.0), batched[k],
                                   rtol=0, atol=1e-12)
    log_p = normalised(rng.normal(size=(3, 500)))
    mixed = fuse_camera(log_p, batched, 5.0, 1e-3)
    q = np.exp(batched[..., :500])
    direct = np.log(np.einsum('km,kmn->mn', mixed.alpha, q))
    np.testing.assert_allclose(mixed.log_q_mix[~mixed.excluded], direct[~mixed.excluded],
                               rtol=1e-12)
    # A particle kilometres from every match: every Q_j underflows, the mixture stays finite.
    lonely = positions.copy()
    lonely[:, 0] += 20_000.0
    far = fuse_camera(log_p, camera_log_q(lonely, matches[[0, 1]], 5.0, 20.0), 1e9, 1e-3)
    assert np.isfinite(far.log_q_mix).all()


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
