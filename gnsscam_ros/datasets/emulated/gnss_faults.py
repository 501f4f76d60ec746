"""Pseudorange faults of the emulated drive: episodes, faulty satellites and biases.

Fault episodes of U(``fault_episode_s``) seconds are separated by exponential gaps so that
about ``fault_fraction`` of the epochs after ``fault_free_start_s`` are faulty. In each
episode ``faults`` of the tracked satellites (uniformly at random) get a bias constant over
the episode, ``sign * clip(|N(bias_m, (fault_sigma_frac bias_m)^2)|, *fault_clip_m)`` with
a random sign. If a faulty satellite stops being tracked during its episode, another one
takes its place, so that every epoch of the episode has exactly ``faults`` faulty
satellites. The draws do not depend on ``faults``: the same seed gives the same episodes,
and the faulty sets for growing ``faults`` are nested.
"""
from __future__ import annotations

import numpy as np

from .config import EmulationConfig
from .constellation import Constellation


def _fault_episodes(rng: np.random.Generator, t_ep: np.ndarray, rate_hz: float,
                    fraction: float, cfg: EmulationConfig) -> list[tuple[int, int]]:
    """Random fault episodes ``[start, stop)`` (epoch indices) covering ~``fraction``.

    Episode durations are U(fault_episode_s) seconds; the fault-free gaps between them are
    exponential with mean ``mean_episode * (1 - fraction) / fraction`` (at least one epoch),
    the first gap starting at ``fault_free_start_s``.
    """
    if fraction <= 0.0:
        return []
    mean_ep = 0.5 * sum(cfg.fault_episode_s) * rate_hz
    mean_gap = mean_ep * (1.0 - fraction) / max(fraction, 1e-9)
    k = int(np.searchsorted(t_ep, cfg.fault_free_start_s))
    out = []
    while True:
        k += max(1, int(round(rng.exponential(mean_gap)))) if mean_gap > 0 else 0
        n = max(1, int(round(rng.uniform(*cfg.fault_episode_s) * rate_hz)))
        if k >= len(t_ep):
            return out
        out.append((k, min(k + n, len(t_ep))))
        k += n


def inject_faults(rng: np.random.Generator, sel: np.ndarray, const: Constellation,
                  t_ep: np.ndarray, stamps_ns: np.ndarray, faults: int, bias_m: float,
                  rate_hz: float, fraction: float, cfg: EmulationConfig):
    """Draw the fault episodes and the bias of every faulty (epoch, satellite).

    Args:
        rng: The drive's ``'faults'`` stream.
        sel: (n, n_sv) tracked satellite indices per epoch (into ``const``).
        const: The constellation.
        t_ep: (n,) epoch times from the start [s].
        stamps_ns: (n,) epoch stamps [ns].
        faults: Faulty satellites per faulty epoch (0: no faults).
        bias_m: Mean fault magnitude [m].
        rate_hz: Epoch rate [Hz].
        fraction: Target fraction of faulty epochs.
        cfg: Parameters.

    Returns:
        ``(fault (n, n_sv) [m], records, episodes)``: the bias added to each pseudorange,
        one record per faulty (epoch, satellite) and the ``[start, stop)`` epoch ranges.
    """
    fault = np.zeros(sel.shape)
    fault_records = []
    episodes = _fault_episodes(rng, t_ep, rate_hz, fraction, cfg) if faults else []
    for e, (k0, k1) in enumerate(episodes):
        # Draws do not depend on ``faults``: the same seed gives the same episodes, and the
        # faulty satellites for f faults are the first f of the same random order.
        order = [int(i) for i in sel[k0][rng.permutation(cfg.n_sv)]]
        mag = np.clip(np.abs(rng.normal(bias_m, cfg.fault_sigma_frac * bias_m, 2 * cfg.n_sv)),
                      *cfg.fault_clip_m)
        biases = rng.choice([-1.0, 1.0], 2 * cfg.n_sv) * mag
        # Satellite -> bias: rank in ``order``; replacements take the spare draws 12, 13, ...
        bias_of = {i: biases[r] for r, i in enumerate(order)}
        for k in range(k0, k1):
            present = [int(i) for i in sel[k]]
            ranked = [i for i in order if i in present]
            ranked += [i for i in present if i not in order]
            for i in ranked[:faults]:
                if i not in bias_of:
                    order.append(i)
                    bias_of[i] = biases[(len(order) - 1) % len(biases)]
                j = present.index(i)
                fault[k, j] = bias_of[i]
                fault_records.append({
                    'epoch': k, 'stamp_ns': int(stamps_ns[k]), 'index': j,
                    'system': int(const.system[i]), 'sv_id': int(const.sv_id[i]),
                    'bias_m': float(bias_of[i]), 'episode': e})
    return fault, fault_records, episodes
