"""The persisting share of the snapshot solutions' error (core.persistence): known answers
for white and Gauss-Markov errors, independence of the GNSS rate and of the vehicle's
motion, and what the filter's tempering takes from it."""
from dataclasses import replace

import numpy as np
import oracles
import pytest
from synthetic import FRAME, epoch_at

from gnsscam_ros.core.filter import FilterConfig, ParticleFilter
from gnsscam_ros.core.particles import MotionIncrement
from gnsscam_ros.core.persistence import (LONG_LAG_S, MIN_PAIRS, PAIR_TOLERANCE, SHORT_LAG_S,
                                          SnapshotPersistence, persisting_worth,
                                          tempering_exponent)

S = 1_000_000_000


def gauss_markov(rng, n, dt_s, tau_s, sd_m):
    """(n, 2) first-order Gauss-Markov errors (tau 0: white)."""
    phi = np.exp(-dt_s / tau_s) if tau_s > 0 else 0.0
    e = np.empty((n, 2))
    e[0] = rng.normal(0.0, sd_m, 2)
    for k in range(1, n):
        e[k] = phi * e[k - 1] + rng.normal(0.0, sd_m * np.sqrt(1.0 - phi * phi), 2)
    return e


def share_of(errors_m, dt_s, speed_mps=0.0, window_s=60.0):
    """Feed snapshot solutions (truth on a straight line plus the errors) and the exact
    motion; return the measured share."""
    model = SnapshotPersistence(window_s)
    step = np.array([speed_mps * dt_s, 0.0])
    truth = np.zeros(2)
    for k, e in enumerate(errors_m):
        if k:
            model.move(step)
            truth = truth + step
        model.observe(int(k * dt_s * S), truth + e)
    return model.persistent_share


def expected_share(tau_s):
    """1 - gamma(short) / gamma(long) of a Gauss-Markov error."""
    return 1.0 - (1.0 - np.exp(-SHORT_LAG_S / tau_s)) / (1.0 - np.exp(-LONG_LAG_S / tau_s))


def test_white_errors_do_not_persist_and_gauss_markov_ones_do_by_their_correlation_time():
    rng = np.random.default_rng(3)
    white = [share_of(gauss_markov(rng, 300, 0.2, 0.0, 3.0), 0.2) for _ in range(5)]
    assert np.mean(white) < 0.1
    for tau in (3.0, 10.0, 30.0):
        got = [share_of(gauss_markov(rng, 300, 0.2, tau, 10.0), 0.2) for _ in range(5)]
        assert np.mean(got) == pytest.approx(expected_share(tau), abs=0.12), tau
    # The share orders the correlation times.
    assert expected_share(3.0) < expected_share(10.0) < expected_share(30.0)


def test_the_share_does_not_depend_on_the_gnss_rate_or_on_the_motion():
    rng = np.random.default_rng(8)
    # One error process sampled at 10 Hz, presented at 5 Hz and 1 Hz, over 60 s.
    fine = gauss_markov(rng, 600, 0.1, 10.0, 10.0)
    at_5hz = np.mean([share_of(fine[o::2], 0.2, speed_mps=12.0) for o in range(2)])
    at_1hz = np.mean([share_of(fine[o::10], 1.0, speed_mps=12.0) for o in range(10)])
    assert at_5hz == pytest.approx(at_1hz, abs=0.1)
    # Driving at 12 m/s or standing gives the same share: the motion is taken out.
    assert share_of(fine[::2], 0.2, speed_mps=12.0) == pytest.approx(
        share_of(fine[::2], 0.2), abs=1e-9)


def test_until_enough_pairs_everything_persists():
    rng = np.random.default_rng(1)
    # At 1 Hz the first pair at the long lag comes (1 - PAIR_TOLERANCE) LONG_LAG_S in.
    n = int(np.ceil((1.0 - PAIR_TOLERANCE) * LONG_LAG_S)) + MIN_PAIRS - 1
    assert share_of(gauss_markov(rng, n, 1.0, 0.0, 3.0), 1.0) == 1.0
    assert share_of(gauss_markov(rng, n + 10, 1.0, 0.0, 3.0), 1.0) < 0.5
    assert SnapshotPersistence().persistent_share == 1.0


def test_one_nlos_jump_does_not_decide_the_share():
    rng = np.random.default_rng(5)
    e = gauss_markov(rng, 300, 0.2, 0.0, 3.0)
    e[150] += 80.0                                  # one snapshot 80 m off
    assert share_of(e, 0.2) < 0.15


def tempering_after(errors_m, dt_s=1.0):
    """The filter's tempering exponent after the share has learned from ``errors_m``."""
    pf = ParticleFilter(FilterConfig(n_particles=200), frame=FRAME,
                        rng=np.random.default_rng(0))
    for k, e in enumerate(errors_m):
        pf.persistence.observe(int(k * dt_s * S), e)
    return tempering_exponent(pf.persistence.persistent_share,
                              persisting_worth(dt_s, pf.config.error_correlation_time_s))


def test_the_tempering_counts_white_errors_as_new_and_persisting_ones_as_before():
    rng = np.random.default_rng(2)
    cfg = FilterConfig()
    correlated = np.tanh(1.0 / (2.0 * cfg.error_correlation_time_s))
    # Before any snapshot: the tempering of a fully correlated error.
    assert tempering_after(np.zeros((0, 2))) == pytest.approx(correlated)
    white = tempering_after(gauss_markov(rng, 60, 1.0, 0.0, 3.0))
    slow = tempering_after(gauss_markov(rng, 60, 1.0, 60.0, 10.0))
    assert white > 4.0 * correlated                 # several times bolder
    assert slow == pytest.approx(correlated, rel=0.3)


def test_a_filter_on_white_errors_learns_a_share_below_one():
    # The whole chain: epochs of a receiver at rest with white pseudorange noise.
    pf = ParticleFilter(FilterConfig(n_particles=300), frame=FRAME,
                        rng=np.random.default_rng(4))
    rng = np.random.default_rng(6)
    for k in range(90):
        epoch = epoch_at(np.zeros(3), stamp_ns=k * S)
        epoch = replace(epoch, pr_m=epoch.pr_m + rng.normal(0.0, 3.0, epoch.pr_m.shape))
        pf.step(epoch, MotionIncrement(1.0, 0.0, 0.0, 1e-3, 1e-6) if k else None)
    assert pf.persistence.persistent_share < 0.5


def test_a_poisoned_motion_or_snapshot_leaves_the_share_finite():
    rng = np.random.default_rng(9)
    model = SnapshotPersistence()
    for k, e in enumerate(gauss_markov(rng, 120, 1.0, 0.0, 3.0)):
        model.observe(k * S, e)
    assert model.persistent_share < 0.5
    model.observe(121 * S, np.array([np.nan, 0.0]))           # left out
    assert model.persistent_share < 0.5
    model.move(np.array([1e300, 0.0]))                        # absurd but finite: one
    model.observe(122 * S, np.zeros(2))                       # outlier among medians
    assert 0.0 <= model.persistent_share < 0.5
    model.move(np.array([np.inf, 0.0]))                       # the window starts again
    model.observe(123 * S, np.zeros(2))
    assert model.persistent_share == 1.0


def test_the_compiled_semivariogram_is_the_numpy_oracle():
    # Irregular stamps (gaps, jitter, 5 Hz and 0.2 Hz), offsets with an inf and a NaN:
    # the same pairs and the same median to the bit.
    rng = np.random.default_rng(0)
    for trial in range(400):
        n = int(rng.integers(0, 80))
        dt = (rng.choice([200_000_000, 10**9, 10**9, 5 * 10**9], size=n)
              + rng.integers(-300_000_000, 300_000_000, size=n) * (trial % 2))
        t = np.cumsum(np.maximum(dt, 1)).astype(np.int64)
        d = rng.normal(scale=3.0, size=(n, 2)).cumsum(axis=0) * 0.3 + rng.normal(size=(n, 2))
        if n and trial % 7 == 0:
            d[rng.integers(n)] = np.inf
        if n and trial % 11 == 0:
            d[rng.integers(n), 0] = np.nan
        both = SnapshotPersistence._median_increments_m2(t, d)
        for lag, got in ((SHORT_LAG_S, both[:2]), (LONG_LAG_S, both[2:])):
            want = oracles.median_increment_m2(t, d, lag, PAIR_TOLERANCE)
            assert got[1] == want[1]
            assert got[0] == want[0] or (np.isnan(got[0]) and np.isnan(want[0]))


def test_the_window_is_every_finite_offset_of_the_last_window_s():
    # Irregular stamps and a few non-finite snapshots, through the buffers' growth and
    # moves: after every epoch the share is that of the oracle over the window's rows.
    rng = np.random.default_rng(5)
    model = SnapshotPersistence(window_s=20.0)
    stamps, rows = [], []
    t = 0
    for k in range(600):
        t += int(rng.choice([200_000_000, 10**9, 3 * 10**9], p=[0.85, 0.1, 0.05]))
        t += int(rng.integers(0, 10**8))
        step = rng.normal(size=2)
        model.move(step)
        snap = rng.normal(scale=3.0, size=2) + (0.0 if k % 53 else np.nan)
        before = model.persistent_share
        model.observe(t, snap)
        if not np.isfinite(snap).all():
            assert model.persistent_share == before        # left out: nothing changes
            continue
        stamps.append(t)
        rows.append(snap - model._path_m)
        keep = [i for i, s in enumerate(stamps) if s >= t - 20 * S]
        ts = np.array([stamps[i] for i in keep], dtype=np.int64)
        d = np.array([rows[i] for i in keep]).reshape(-1, 2)
        short = oracles.median_increment_m2(ts, d, SHORT_LAG_S, PAIR_TOLERANCE)
        long = oracles.median_increment_m2(ts, d, LONG_LAG_S, PAIR_TOLERANCE)
        if short[1] < MIN_PAIRS or long[1] < MIN_PAIRS or not long[0] > 0.0:
            want = 1.0
        else:
            want = min(max(1.0 - short[0] / long[0], 0.0), 1.0)
        assert model.persistent_share == want, k
    assert model._stamps.shape[0] > 64                 # the buffers grew on the way
