"""GNSS pseudoranges of the emulated drive, with their error decomposition.

Per epoch ``n_sv`` (12) satellites above the mask are tracked (kept while visible, at most
``max_gps`` GPS so that GLONASS always has enough). Pseudorange of satellite j at epoch k
(metres)::

    pr = rho_kj + b_k + isb * [j is GLONASS] + n_kj + nlos_kj + f_kj

* ``rho_kj``: geometric range from the light-time equation (satellite at transmission
  time, Earth rotation during the flight included; :mod:`.constellation`). The satellite
  position is reported at transmission in the ECEF frame of transmission, so a user must
  apply ``sagnac_corrected`` to recover ``rho``.
* ``b_k``: receiver clock bias, ``b0 ~ U(-3e5, 3e5)`` m, drift ``d0 ~ U(-50, 50)`` m/s,
  both random walks (0.3 m/sqrt(s), 0.05 m/s/sqrt(s)). ``isb ~ N(0, 15^2)`` m, constant.
* ``n_kj ~ N(0, 10 m^2)`` white (``var_m2`` = 10).
* ``nlos_kj`` (only with ``nlos`` and the line of sight blocked by a building):
  ``5 + 55 * Phi(x_j(t))`` m, where ``x_j`` is a unit-variance Gauss-Markov process of
  satellite j with correlation time 30 s and ``Phi`` the standard normal CDF, i.e.
  uniform on [5, 60] m and correlated in time; its C/N0 is lowered by U(6, 14) dB.
  LOS C/N0 is ``30 + 20 sin(el) + N(0, 1.5^2)`` dB-Hz.
* ``f_kj`` (only with ``faults > 0``): injected fault biases (:mod:`.gnss_faults`).

(The figures are the :class:`.config.EmulationConfig` defaults.)
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import lfilter
from scipy.special import ndtr

from ...core.types import GLONASS, GPS
from ..city import los_blocked
from .config import EmulationConfig, stream_rng
from .constellation import visible_constellation
from .gnss_faults import inject_faults
from .scenario import Scenario


@dataclass(frozen=True)
class GnssSynthesis:
    """The simulated GNSS epochs of a whole drive and their error terms.

    Per-satellite arrays are (n, n_sv), aligned with each epoch's tracked satellites.

    Attributes:
        t_s: (n,) epoch times from the start of the drive [s].
        rx_ecef_m: (n, 3) true receiver (antenna) positions [m].
        system: (n, n_sv) system ids.
        sv_id: (n, n_sv) satellite ids within their system.
        sv_pos_ecef_m: (n, n_sv, 3) satellite positions at transmission [m].
        elevation_deg: (n, n_sv) elevations [deg].
        cn0_dbhz: (n, n_sv) carrier-to-noise density [dB-Hz].
        pr_m: (n, n_sv) pseudoranges [m].
        geometric_range_m: (n, n_sv) ``rho`` [m].
        clock_bias_m: (n,) receiver clock bias ``b`` [m].
        clock_drift_mps: (n,) receiver clock drift [m/s].
        isb_glonass_m: GLONASS-minus-GPS inter-system bias [m].
        clock_m: (n, n_sv) clock term of each pseudorange (bias plus ISB) [m].
        noise_m: (n, n_sv) white noise [m].
        blocked: (n, n_sv) line of sight blocked by a building.
        nlos_m: (n, n_sv) NLOS excess delay [m].
        fault_m: (n, n_sv) injected fault bias [m].
        fault_records: One dict per faulty (epoch, satellite).
        fault_episodes: ``[start, stop)`` epoch ranges of the fault episodes.
    """

    t_s: np.ndarray
    rx_ecef_m: np.ndarray
    system: np.ndarray
    sv_id: np.ndarray
    sv_pos_ecef_m: np.ndarray
    elevation_deg: np.ndarray
    cn0_dbhz: np.ndarray
    pr_m: np.ndarray
    geometric_range_m: np.ndarray
    clock_bias_m: np.ndarray
    clock_drift_mps: np.ndarray
    isb_glonass_m: float
    clock_m: np.ndarray
    noise_m: np.ndarray
    blocked: np.ndarray
    nlos_m: np.ndarray
    fault_m: np.ndarray
    fault_records: list
    fault_episodes: list


def _select(el_deg: np.ndarray, system: np.ndarray, cfg: EmulationConfig) -> np.ndarray:
    """Pick ``n_sv`` tracked satellites per epoch (kept while above the mask).

    Args:
        el_deg: (n, S) elevations.
        system: (S,) system ids.
        cfg: Parameters.

    Returns:
        (n, n_sv) satellite indices per epoch, sorted by (system, sv index).
    """
    out = np.empty((el_deg.shape[0], cfg.n_sv), dtype=np.int64)
    tracked: list[int] = []
    is_gps = system == GPS
    for k, el in enumerate(el_deg):
        vis = el > cfg.elevation_mask_deg
        keep = [i for i in tracked if vis[i]]
        n_gps = int(sum(is_gps[i] for i in keep))
        cand = [int(i) for i in np.argsort(-el) if vis[i] and i not in keep]
        for i in cand:                      # highest first, respecting the GPS cap
            if len(keep) == cfg.n_sv:
                break
            if is_gps[i] and n_gps >= cfg.max_gps:
                continue
            keep.append(i)
            n_gps += int(is_gps[i])
        for i in cand:                      # relax the cap if still short
            if len(keep) == cfg.n_sv:
                break
            if i not in keep:
                keep.append(i)
        if len(keep) < cfg.n_sv:
            raise RuntimeError(f'only {len(keep)} satellites above the mask at epoch {k}')
        tracked = keep
        out[k] = np.sort(keep)
    return out


def _receiver_clock(rng: np.random.Generator, n_ep: int, dt_s: float,
                    cfg: EmulationConfig) -> tuple[np.ndarray, np.ndarray, float]:
    """Receiver clock bias and drift (2-state random walk) and the GLONASS ISB.

    Returns:
        ``(bias (n_ep,) [m], drift (n_ep,) [m/s], isb [m])``.
    """
    b0 = rng.uniform(-cfg.clock_bias0_m, cfg.clock_bias0_m)
    d0 = rng.uniform(-cfg.clock_drift0_mps, cfg.clock_drift0_mps)
    isb = rng.normal(0.0, cfg.isb_std_m)
    drift = d0 + np.concatenate(
        [[0.0], np.cumsum(rng.normal(0.0, cfg.clock_drift_rw_mps * np.sqrt(dt_s), n_ep - 1))])
    clock = b0 + np.concatenate([[0.0], np.cumsum(
        drift[:-1] * dt_s + rng.normal(0.0, cfg.clock_bias_rw_m * np.sqrt(dt_s), n_ep - 1))])
    return clock, drift, isb


def _nlos_delays(rng: np.random.Generator, n_ep: int, n_sat: int, dt_s: float,
                 cfg: EmulationConfig) -> np.ndarray:
    """(n_ep, n_sat) NLOS excess delay of every satellite, were it blocked [m]."""
    phi = np.exp(-dt_s / cfg.nlos_corr_time_s)
    w = rng.normal(0.0, 1.0, (n_ep, n_sat))
    w[1:] *= np.sqrt(1.0 - phi ** 2)     # x_0 ~ N(0, 1): stationary from the first epoch
    x = lfilter([1.0], [1.0, -phi], w, axis=0)
    lo, hi = cfg.nlos_range_m
    return lo + (hi - lo) * ndtr(x)


def synthesize_gnss(sc: Scenario, rate_hz: float, nlos: bool, faults: int, bias_m: float,
                    fault_fraction: float) -> GnssSynthesis:
    """The GNSS epochs of the whole drive of ``sc`` (see the module docstring).

    Args:
        sc: The drive's scenario (seed, parameters, truth, city).
        rate_hz: Epoch rate [Hz].
        nlos: Add NLOS errors on blocked satellites.
        faults: Faulty satellites per faulty epoch (0: none).
        bias_m: Mean fault magnitude [m].
        fault_fraction: Target fraction of faulty epochs.

    Returns:
        Every epoch from the start to the end of the drive.
    """
    seed, cfg = sc.seed, sc.config
    t_ep = np.arange(int(np.floor(sc.duration_s * rate_hz + 1e-9)) + 1) / rate_hz
    n_ep = len(t_ep)
    rx_enu = sc.pose_at(t_ep).enu_m
    rx_ecef = sc.frame.enu_to_ecef(rx_enu)
    sky = visible_constellation(stream_rng(seed, 'constellation'), sc.t0_ns, t_ep, rx_ecef,
                                sc.frame, cfg)
    const = sky.const
    sel = _select(sky.el_deg, const.system, cfg)                       # (n_ep, 12)
    rows = np.arange(n_ep)[:, None]
    sys_sel, id_sel = const.system[sel], const.sv_id[sel]
    rho_sel, el_sel = sky.rho[rows, sel], sky.el_deg[rows, sel]
    blocked = np.stack([los_blocked(sc.city, rx_enu[k], sky.los[k, sel[k]])
                        for k in range(n_ep)])

    dt_ep = 1.0 / rate_hz
    clock, drift, isb = _receiver_clock(stream_rng(seed, 'clock'), n_ep, dt_ep, cfg)
    clock_sel = clock[:, None] + np.where(sys_sel == GLONASS, isb, 0.0)

    rng = stream_rng(seed, 'noise')
    noise = rng.normal(0.0, np.sqrt(cfg.pr_var_m2), (n_ep, cfg.n_sv))
    cn0 = 30.0 + 20.0 * np.sin(np.radians(el_sel)) + rng.normal(0.0, 1.5, (n_ep, cfg.n_sv))
    cn0_drop = rng.uniform(*cfg.nlos_cn0_drop_db, (n_ep, cfg.n_sv))

    nlos_all = _nlos_delays(stream_rng(seed, 'nlos'), n_ep, len(const.system), dt_ep, cfg)
    nlos_err = np.where(blocked, nlos_all[rows, sel], 0.0) if nlos else np.zeros_like(rho_sel)
    if nlos:
        cn0 = np.where(blocked, cn0 - cn0_drop, cn0)

    fault, records, episodes = inject_faults(
        stream_rng(seed, 'faults'), sel, const, t_ep, sc.stamps_ns(t_ep), faults, bias_m,
        rate_hz, fault_fraction, cfg)

    pr = rho_sel + clock_sel + noise + nlos_err + fault
    return GnssSynthesis(
        t_s=t_ep, rx_ecef_m=rx_ecef, system=sys_sel, sv_id=id_sel,
        sv_pos_ecef_m=sky.sv_tx[rows, sel], elevation_deg=el_sel, cn0_dbhz=cn0, pr_m=pr,
        geometric_range_m=rho_sel, clock_bias_m=clock, clock_drift_mps=drift,
        isb_glonass_m=isb, clock_m=clock_sel, noise_m=noise, blocked=blocked,
        nlos_m=nlos_err, fault_m=fault, fault_records=records, fault_episodes=episodes)
