"""GNSS-camera fusion with the KL-divergence mixture-of-experts weights (paper §5).

For the K camera images between two GNSS epochs, each image j gives a distribution Q_j over
the particles (:func:`camera_log_q`). Its weight minimises ``KL(alpha_j Q_j || P)`` against the
GNSS distribution P over the same particles:

    alpha_j = exp(k_j),  k_j = sum_i Q_j log(P / Q_j) / sum_i Q_j - 1 = -KL(Q_j || P) - 1

normalised over j, and the mixture ``Q* = sum_j alpha*_j Q_j`` multiplies the GNSS
likelihood (joint log-likelihood ``log P + log Q*``).

A softmax over the particles alone sees only *relative* distances: a match 60 m from a
tight cloud gives almost the same Q as one 5 m away, and no divergence could tell them
apart. The domain is therefore the S particles plus one cell for "elsewhere in the map":
the cell weighs like the whole cloud placed at the gate distance R, so the camera's mass
lands there when the match is farther than R from the particles, and the GNSS
distribution puts only ``elsewhere_prob`` there. The paper's formula for alpha_j is
applied on that domain.

Normalisation gives the cameras full weight even when every one of them disagrees with
GNSS. So when the smallest divergence of the epoch exceeds ``kl_threshold_nats`` the
camera is excluded for that epoch (and the caller reports it) instead of being forced into
the estimate. With every image far from the cloud, KL -> log(1 / elsewhere_prob).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import logsumexp

from .camera import propagate_match_state
from .types import OdometrySeries

#: Most camera images one epoch fuses (the newest of its interval). The fusion holds
#: images x motion samples x particles arrays, so this bounds what an epoch costs (the
#: memory budget of ``core.config`` assumes it): a 10 Hz camera between 1 Hz GNSS epochs
#: fits; of a faster one the newest images, whose move to the epoch is the shortest.
MAX_CAMERA_MATCHES = 16


@dataclass(frozen=True)
class CameraMeasurement:
    """One camera image's best database match, moved to the GNSS epoch.

    Attributes:
        stamp_ns: Image time [ns].
        position_enu_m: (3,) matched position at the GNSS epoch, map frame [m].
        score: Retrieval similarity score of the match.
        frame_id: Identifier of the image (for diagnostics and evaluation).
    """

    stamp_ns: int
    position_enu_m: np.ndarray
    score: float = float('nan')
    frame_id: int = -1


def match_at_epoch(match_enu_m: np.ndarray, speed_mps: float, accel_mps2: float,
                   yaw_rad: float, dt_s: float) -> np.ndarray:
    """Move a matched position from the image time to the GNSS epoch.

    The vehicle moves along its heading, ``x + v dt + a dt^2 / 2`` (paper eq. for the
    camera state) with v and a the odometry speed and acceleration along ``yaw_rad``.
    """
    heading = np.array([np.cos(yaw_rad), np.sin(yaw_rad), 0.0])
    return propagate_match_state(match_enu_m, speed_mps * heading, accel_mps2 * heading, dt_s)


def measurements_at_epoch(matches: list[CameraMeasurement], odometry: OdometrySeries | None,
                          t_prev_ns: int, t_epoch_ns: int,
                          yaw_prev_rad: float) -> list[CameraMeasurement]:
    """The camera matches of ``(t_prev_ns, t_epoch_ns]``, each moved to the GNSS epoch.

    Speed, acceleration and heading at the image time come from the odometry: the heading
    is the previous epoch's estimate turned by the integrated yaw rate.

    Args:
        matches: Best matches with their image stamps (positions at the image time).
        odometry: Speed and yaw-rate series (None: the vehicle is taken as standing).
        t_prev_ns: Previous GNSS epoch [ns].
        t_epoch_ns: This GNSS epoch [ns].
        yaw_prev_rad: Heading estimate at the previous epoch [rad].

    Returns:
        The matches inside the interval, positions moved to ``t_epoch_ns``.
    """
    inside = [m for m in matches if t_prev_ns < m.stamp_ns <= t_epoch_ns]
    if not inside:
        return []
    if odometry is None or len(odometry) == 0:
        return [CameraMeasurement(m.stamp_ns, np.asarray(m.position_enu_m, float), m.score,
                                  m.frame_id) for m in inside]
    t_odo = odometry.stamp_ns.astype(float) * 1e-9
    stamps = np.array([m.stamp_ns for m in inside], dtype=float) * 1e-9
    speed = np.interp(stamps, t_odo, odometry.speed_mps)
    accel = np.interp(stamps, t_odo, np.gradient(odometry.speed_mps, t_odo)) if len(
        odometry) > 1 else np.zeros_like(stamps)
    # Heading at each image: the previous estimate plus the yaw rate integrated since.
    t_prev_s = t_prev_ns * 1e-9
    grid = np.concatenate(([t_prev_s], stamps))
    rate = np.interp(grid, t_odo, odometry.yaw_rate_rps)
    yaw = yaw_prev_rad + np.concatenate(
        ([0.0], np.cumsum(0.5 * (rate[1:] + rate[:-1]) * np.diff(grid))))[1:]
    out = []
    for m, v, a, psi, t in zip(inside, speed, accel, yaw, stamps):
        dt_s = t_epoch_ns * 1e-9 - t
        out.append(CameraMeasurement(m.stamp_ns, match_at_epoch(m.position_enu_m, v, a, psi,
                                                                dt_s), m.score, m.frame_id))
    return out


def camera_log_q(positions_m: np.ndarray, match_enu_m: np.ndarray, temperature_m: float,
                 gate_m: float | None = None) -> np.ndarray:
    """Per-set log softmax of ``-distance / T`` over the particles, for one or K matches.

    The distance is Euclidean in 3D as in the paper: a geotagged database image carries
    its height, which GNSS in a street canyon observes poorly.

    Args:
        positions_m: (M, N, 3) particle positions [m].
        match_enu_m: (3,) matched position at the epoch, or (K, 3) for K matches [m].
        temperature_m: Softmax temperature T [m].
        gate_m: Gate distance R [m]; None for the paper's plain softmax over particles.

    Returns:
        (M, N + 1) log Q with the "elsewhere" cell last, or (M, N) without a gate; with K
        matches a leading K axis. Each row sums to one in probability. The cell weighs as
        much as N particles at the gate distance (logit ``-R / T + log N``), so the test
        does not depend on N.
    """
    pos = np.asarray(positions_m, dtype=float)[..., :3]
    match = np.asarray(match_enu_m, dtype=float)
    matches = match.reshape(-1, match.shape[-1])[:, :3]
    m, n = pos.shape[0], pos.shape[1]
    # Squared distances |p|^2 - 2 p.c + |c|^2 as one matrix product for all K matches (the
    # K x M x N array is the costly part at N = 10,000); coordinates relative to the cloud
    # centre keep the cancellation harmless (|p|^2 is the cloud's spread, not the map's).
    centre = pos[:, 0, :].mean(axis=0)
    flat = pos.reshape(-1, 3) - centre
    rel = matches - centre
    d2 = rel @ (-2.0 * flat.T)
    d2 += np.einsum('ij,ij->i', flat, flat)[None, :]
    d2 += np.einsum('ij,ij->i', rel, rel)[:, None]
    np.maximum(d2, 0.0, out=d2)
    logits = np.sqrt(d2, out=d2).reshape(len(matches), m, n)
    logits *= -1.0 / temperature_m
    if gate_m is not None:
        logits = np.concatenate(
            [logits, np.full(logits.shape[:-1] + (1,), -gate_m / temperature_m + np.log(n))],
            axis=-1)
    top = logits.max(axis=-1, keepdims=True)
    log_norm = top + np.log(np.exp(logits - top).sum(axis=-1, keepdims=True))
    logits -= log_norm
    return logits if match.ndim > 1 else logits[0]


@dataclass(frozen=True)
class FusionResult:
    """The camera mixture of one epoch, per posterior set.

    Attributes:
        log_q_mix: (M, N) log Q* (zeros where the camera is excluded).
        alpha: (K, M) normalised mixture weights alpha*_j.
        kl_nats: (K, M) KL(Q_j || P).
        excluded: (M,) whether the camera was excluded for that set.
    """

    log_q_mix: np.ndarray
    alpha: np.ndarray
    kl_nats: np.ndarray
    excluded: np.ndarray


def fuse_camera(log_p: np.ndarray, log_q: np.ndarray, kl_threshold_nats: float,
                elsewhere_prob: float | None = None) -> FusionResult:
    """Mixture-of-experts weights and the camera mixture for every posterior set.

    Args:
        log_p: (M, N) normalised log GNSS distribution over the particles of each set.
        log_q: (K, M, N) normalised log camera distributions, or (K, M, N + 1) with the
            "elsewhere" cell last (see :func:`camera_log_q`).
        kl_threshold_nats: Exclude the camera of a set when every KL(Q_j || P) exceeds it.
        elsewhere_prob: GNSS probability of the "elsewhere" cell (needed with that cell).

    Returns:
        The fusion result; ``log_q_mix`` covers the N particles only.
    """
    n = log_p.shape[-1]
    if log_q.shape[-1] == n + 1:
        if elsewhere_prob is None:
            raise ValueError('log_q has an elsewhere cell: give elsewhere_prob')
        log_p = np.concatenate([log_p + np.log1p(-elsewhere_prob),
                                np.full(log_p.shape[:-1] + (1,), np.log(elsewhere_prob))],
                               axis=-1)
    elif log_q.shape[-1] != n:
        raise ValueError(f'log_q has {log_q.shape[-1]} cells for {n} particles')
    q = np.exp(log_q)
    # k_j = sum_i Q log(P/Q) / sum_i Q - 1 (sum_i Q = 1 for a normalised Q_j).
    kl = (q * (log_q - log_p[None])).sum(-1)
    k = -kl / q.sum(-1) - 1.0
    alpha = np.exp(k - logsumexp(k, axis=0, keepdims=True))       # normalised over j
    # log sum_j alpha_j Q_j from the Q already at hand; where every Q_j underflows (a
    # particle kilometres from every match) the log-sum-exp does it exactly.
    mix = np.einsum('km,kmn->mn', alpha, q[..., :n])
    with np.errstate(divide='ignore'):
        log_q_mix = np.log(mix)
    tiny = mix < 1e-280
    if tiny.any():
        exact = logsumexp(log_q[..., :n] + np.log(np.maximum(alpha, 1e-300))[..., None],
                          axis=0)
        log_q_mix[tiny] = exact[tiny]
    excluded = kl.min(axis=0) > kl_threshold_nats
    log_q_mix[excluded] = 0.0
    return FusionResult(log_q_mix=log_q_mix, alpha=alpha, kl_nats=kl, excluded=excluded)
