"""GNSS-camera fusion with the KL-divergence mixture-of-experts weights (paper §5).

For the K camera images between two GNSS epochs, each image j gives a distribution Q_j over
the particles (:func:`camera_fusion`). Its weight minimises ``KL(alpha_j Q_j || P)`` against the
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

import math
from dataclasses import dataclass

import numpy as np

from .camera import propagate_match_state
from .kernels import camera as camera_kernels
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


def camera_fusion(particles: np.ndarray, matches_m: np.ndarray, log_p: np.ndarray,
                  temperature_m: float, gate_m: float | None, kl_threshold_nats: float,
                  elsewhere_prob: float | None = None) -> FusionResult:
    """The camera distributions of K matches and their mixture, for every posterior set.

    Each match k gives a distribution over the particles of each set s: the softmax of
    ``-distance / T`` (3D distance as in the paper: a geotagged database image carries its
    height, which GNSS in a street canyon observes poorly) over the N particles and the
    "elsewhere" cell, whose logit ``-R / T + log N`` weighs it like N particles at the gate
    distance R (so the test does not depend on N). Against the GNSS distribution, which
    puts ``elsewhere_prob`` on the cell and ``(1 - elsewhere_prob) P`` on the particles,
    its weight is ``alpha_k = softmax_k(-KL(Q_k || P) - 1)``; the mixture is
    ``Q* = sum_k alpha_k Q_k`` over the particles. A set whose smallest KL exceeds
    ``kl_threshold_nats`` excludes the camera (``log_q_mix`` 0). One compiled pass per
    match and set (``core.kernels.camera``).

    Args:
        particles: (S, N, >= 3) particles of the S sets, east, north, up first [m].
        matches_m: (K, 3) matched positions at the epoch (or (3,) for one) [m].
        log_p: (S, N) normalised log GNSS distribution of each set.
        temperature_m: Softmax temperature T [m].
        gate_m: Gate distance R [m]; None for the paper's plain softmax over the particles
            (no "elsewhere" cell).
        kl_threshold_nats: Exclude the camera of a set when every KL(Q_k || P) exceeds it.
        elsewhere_prob: GNSS probability of the "elsewhere" cell (needed with a gate).

    Returns:
        The fusion result: (S, N) log Q*, (K, S) alpha and KL, (S,) exclusion.

    Raises:
        ValueError: Shapes that do not fit, no match, or a gate without
            ``elsewhere_prob``.
    """
    particles = np.asarray(particles, dtype=float)
    matches = np.ascontiguousarray(np.atleast_2d(np.asarray(matches_m, dtype=float))[:, :3])
    log_p = np.ascontiguousarray(log_p, dtype=float)
    if particles.ndim != 3 or particles.shape[-1] < 3:
        raise ValueError(f'particles must be (S, N, >= 3), not {particles.shape}')
    if log_p.shape != particles.shape[:2]:
        raise ValueError(f'log_p is {log_p.shape} for particles {particles.shape[:2]}')
    if matches.shape[0] == 0 or matches.shape[1] != 3:
        raise ValueError(f'matches must be (K >= 1, 3), not {matches.shape}')
    n_sets, n = log_p.shape
    has_cell = gate_m is not None
    if has_cell and elsewhere_prob is None:
        raise ValueError('a gate needs elsewhere_prob (the GNSS mass of the elsewhere cell)')
    cell_logit = -float(gate_m) / temperature_m + math.log(n) if has_cell else 0.0
    log_inside = math.log1p(-elsewhere_prob) if has_cell else 0.0
    log_elsewhere = math.log(elsewhere_prob) if has_cell else 0.0
    k = matches.shape[0]
    log_q_mix = np.empty((n_sets, n))
    alpha = np.empty((k, n_sets))
    kl = np.empty((k, n_sets))
    excluded = np.empty(n_sets, dtype=np.bool_)
    # Coordinates as strided (S, N) views: one kernel signature for any particle array.
    camera_kernels.fuse(particles[..., 0], particles[..., 1], particles[..., 2], matches,
                        log_p, 1.0 / temperature_m, cell_logit, log_inside, log_elsewhere,
                        has_cell, float(kl_threshold_nats), log_q_mix, alpha, kl, excluded)
    return FusionResult(log_q_mix=log_q_mix, alpha=alpha, kl_nats=kl, excluded=excluded)
