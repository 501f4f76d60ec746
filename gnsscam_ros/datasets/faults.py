"""Pseudorange fault injection into any drive (real data included), seeded.

A fault episode adds one bias to several satellites for tens of seconds: what a
multipath or NLOS event the receiver did not flag, or a satellite fault, does to the
pseudoranges. The bias is a step (constant over the episode, the default) or a ramp
(growing linearly from 0 at the episode's start to its full value at its end: a slowly
drifting satellite clock or a growing multipath delay, the fault a snapshot test notices
last). The emulated drive has its own faults (``datasets.emulated``); this module
puts faults of the same kind into real data (smartLoc), whose own errors are left as they
are, so that integrity is measured on real data with faults on top.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..core.types import Drive

SECOND_NS = 1_000_000_000
#: Bias profiles of an episode: constant, or linear from 0 to the full bias.
STEP, RAMP = 'step', 'ramp'
PROFILES = (STEP, RAMP)


@dataclass(frozen=True)
class FaultEpisodes:
    """How faults are drawn.

    Attributes:
        episodes: Number of fault episodes over the drive.
        satellites: (min, max) satellites biased in one episode.
        bias_m: (min, max) magnitude of the bias of one satellite [m] (sign random).
        duration_s: (min, max) duration of one episode [s].
        profile: ``'step'`` (the bias over the whole episode) or ``'ramp'`` (the bias grows
            linearly from 0 at the start to its full value at the end of the episode).
    """

    episodes: int = 8
    satellites: tuple[int, int] = (2, 5)
    bias_m: tuple[float, float] = (20.0, 200.0)
    duration_s: tuple[float, float] = (10.0, 40.0)
    profile: str = STEP

    def __post_init__(self):
        lo, hi = self.satellites
        if self.episodes < 0 or not 1 <= lo <= hi:
            raise ValueError('episodes must be >= 0 and 1 <= satellites[0] <= satellites[1]')
        if not 0.0 <= self.bias_m[0] <= self.bias_m[1]:
            raise ValueError('bias_m must be (min, max) with 0 <= min <= max')
        if not 0.0 < self.duration_s[0] <= self.duration_s[1]:
            raise ValueError('duration_s must be (min, max) with 0 < min <= max')
        if self.profile not in PROFILES:
            raise ValueError(f'profile must be one of {PROFILES}, got {self.profile!r}')


def inject_pseudorange_faults(drive: Drive, seed: int, faults: FaultEpisodes | None = None
                              ) -> Drive:
    """A copy of ``drive`` with fault episodes added to its pseudoranges.

    Episodes start uniformly over the drive; each picks its satellites among those in view
    at its start (by system and number, so a satellite keeps its bias while it stays in
    view) and adds one bias per satellite for the whole episode (a step, or a ramp up to
    it: ``faults.profile``). The draws do not depend on the profile: the same seed puts a
    step and a ramp on the same satellites at the same times.

    Args:
        drive: The drive (unchanged).
        seed: Seed of the fault draw.
        faults: How faults are drawn (default :class:`FaultEpisodes`).

    Returns:
        The faulty drive; ``info['injected_faults']`` lists the episodes and
        ``info['faulty_measurements']`` counts the biased pseudoranges.
    """
    faults = faults or FaultEpisodes()
    rng = np.random.default_rng(seed)
    if not drive.gnss or faults.episodes == 0:
        return replace(drive, info={**drive.info, 'injected_faults': [],
                                    'faulty_measurements': 0})
    t0, t1 = drive.gnss[0].stamp_ns, drive.gnss[-1].stamp_ns
    stamps = np.array([e.stamp_ns for e in drive.gnss])
    record, biased = [], {}
    for _ in range(faults.episodes):
        start = int(rng.uniform(t0, t1))
        duration_ns = int(rng.uniform(*faults.duration_s) * SECOND_NS)
        first = drive.gnss[min(int(np.searchsorted(stamps, start)), len(stamps) - 1)]
        keys = list(zip(first.system.tolist(), first.sv_id.tolist()))
        count = min(int(rng.integers(faults.satellites[0], faults.satellites[1] + 1)),
                    len(keys))
        chosen = [keys[i] for i in rng.choice(len(keys), size=count, replace=False)]
        bias = rng.uniform(*faults.bias_m, count) * rng.choice([-1.0, 1.0], count)
        for key, b in zip(chosen, bias):
            biased.setdefault(key, []).append((start, start + duration_ns, float(b)))
        record.append({'start_ns': start, 'duration_s': duration_ns / SECOND_NS,
                       'satellites': [list(k) for k in chosen], 'bias_m': bias.tolist(),
                       'profile': faults.profile})
    epochs, n_faulty = [], 0
    for epoch in drive.gnss:
        add = np.zeros(epoch.n_sv)
        for i, key in enumerate(zip(epoch.system.tolist(), epoch.sv_id.tolist())):
            for a, b, value in biased.get(key, ()):
                if a <= epoch.stamp_ns < b:
                    # ramp: the share of the episode elapsed, 0 at its start.
                    add[i] += value * ((epoch.stamp_ns - a) / (b - a)
                                       if faults.profile == RAMP else 1.0)
        n_faulty += int(np.count_nonzero(add))
        epochs.append(replace(epoch, pr_m=epoch.pr_m + add))
    return replace(drive, name=f'{drive.name}-faults-s{seed}', gnss=epochs,
                   info={**drive.info, 'injected_faults': record,
                         'faulty_measurements': n_faulty})
