"""Confidence intervals of the campaign's rates and its grid: known answers first.

Clopper-Pearson against closed forms and the binomial tails that define it; the between-seed
interval on correlated epochs (coverage in a seeded simulation); seed ranges; the rates of
a campaign pooled from per-case counts.
"""
import numpy as np
import pytest
from scipy import stats

from gnsscam_ros.evaluation.campaign_grid import (CaseKey, GridError, case_grid, format_seeds,
                                                  gnss_cases, parse_seeds)
from gnsscam_ros.evaluation.campaign_summary import (campaign_intervals, campaign_tables,
                                                     case_counts, interval_csv_rows, run_csv)
from gnsscam_ros.evaluation.intervals import (between_seed_interval, clopper_pearson,
                                              epochs_needed, rate_entry)


# ------------------------------------------------------------------ Clopper-Pearson
@pytest.mark.parametrize('n', [1, 2, 10, 72, 1000, 123456])
def test_zero_of_n_has_the_closed_form_upper_bound(n):
    lo, hi = clopper_pearson(0, n)
    assert lo == 0.0
    assert hi == pytest.approx(1 - 0.025 ** (1 / n), rel=1e-9)


@pytest.mark.parametrize('n', [1, 5, 400])
def test_n_of_n_has_the_closed_form_lower_bound(n):
    lo, hi = clopper_pearson(n, n)
    assert hi == 1.0
    assert lo == pytest.approx(0.025 ** (1 / n), rel=1e-9)


@pytest.mark.parametrize('k, n, expected', [
    (1, 10, (0.002528579, 0.445016117)),      # R: binom.test(1, 10)$conf.int
    (5, 20, (0.08657147, 0.49104587)),        # R: binom.test(5, 20)$conf.int
])
def test_published_values(k, n, expected):
    assert clopper_pearson(k, n) == pytest.approx(expected, abs=2e-8)


@pytest.mark.parametrize('k, n', [(1, 10), (3, 57), (20, 400), (399, 400)])
def test_bounds_are_where_the_binomial_tails_are_two_and_a_half_percent(k, n):
    lo, hi = clopper_pearson(k, n)
    assert stats.binom.cdf(k, n, hi) == pytest.approx(0.025, abs=1e-9)      # P(X <= k)
    assert stats.binom.sf(k - 1, n, lo) == pytest.approx(0.025, abs=1e-9)   # P(X >= k)


def test_no_epochs_no_interval_and_bad_counts_refused():
    assert clopper_pearson(0, 0) is None
    assert rate_entry(0, 0) == {'rate': None, 'count': 0, 'n': 0, 'ci95': None}
    for k, n in ((-1, 5), (6, 5), (float('nan'), 5)):
        with pytest.raises(ValueError):
            clopper_pearson(k, n)
    with pytest.raises(ValueError):
        clopper_pearson(1, 5, confidence=1.0)


def test_epochs_needed_for_an_upper_bound():
    # 0 of n: 1 - 0.025^(1/n) < 0.05 from n = 72 on.
    assert epochs_needed(0.0, 0.05) == 72
    n = epochs_needed(0.01, 0.05)
    assert clopper_pearson(0.01 * n, n)[1] < 0.05 <= clopper_pearson(0.01 * (n - 1), n - 1)[1]
    assert epochs_needed(0.01, 0.05, design_effect=10) == 10 * n
    assert epochs_needed(0.06, 0.05) is None


# ------------------------------------------------------------------ between seeds
def test_between_seed_interval_needs_two_seeds_and_widens_with_clustering():
    assert between_seed_interval([3], [400]) is None
    assert between_seed_interval([3, 0], [400, 0]) is None     # a seed without epochs
    even = between_seed_interval([4, 4, 4, 4], [400, 400, 400, 400])
    clustered = between_seed_interval([16, 0, 0, 0], [400, 400, 400, 400])
    cp = clopper_pearson(16, 1600)
    # Same pooled rate; all events in one drive is far less information.
    assert clustered['ci95'][1] > 3 * even['ci95'][1]
    assert clustered['design_effect'] > 10 and even['design_effect'] == pytest.approx(1.0)
    # Few seeds cost degrees of freedom even without clustering.
    assert even['ci95'][1] > cp[1]
    assert even['drive_rate_mean'] == pytest.approx(0.01) and even['drive_rate_sd'] == 0
    zero = between_seed_interval([0] * 5, [300] * 5)
    assert zero['ci95'][0] == 0 and 0 < zero['ci95'][1] < 0.01


def _correlated_counts(rng, shape, n, rate, episode):
    """Flagged epochs of drives of ``n`` epochs whose flags come in episodes of
    ``episode`` epochs on average (a two-state chain, ``rate`` flagged on average):
    strongly correlated within a drive, independent between drives."""
    p_leave = 1 / episode
    p_enter = rate * p_leave / (1 - rate)
    state = rng.random(shape) < rate
    counts = np.zeros(shape, dtype=int)
    for _ in range(n):
        counts += state
        u = rng.random(shape)
        state = np.where(state, u >= p_leave, u < p_enter)
    return counts


def test_between_seed_interval_covers_correlated_epochs_where_clopper_pearson_does_not():
    rng = np.random.default_rng(2024)
    rate, trials, seeds, n = 0.05, 300, 10, 400
    counts = _correlated_counts(rng, (trials, seeds), n, rate, episode=20)
    cp_hits = between_hits = 0
    for k in counts:
        cp = clopper_pearson(int(k.sum()), seeds * n)
        between = between_seed_interval(k.tolist(), [n] * seeds)['ci95']
        cp_hits += cp[0] <= rate <= cp[1]
        between_hits += between[0] <= rate <= between[1]
    assert cp_hits / trials < 0.5             # epochs are not independent trials (~0.2)
    assert between_hits / trials > 0.90


# ------------------------------------------------------------------ grid
def test_seeds_as_ranges_and_lists():
    assert parse_seeds(['1-200']) == list(range(1, 201))
    assert parse_seeds(['1', '2', '3']) == [1, 2, 3]
    assert parse_seeds(['1-3,7', '9-10', '2']) == [1, 2, 3, 7, 9, 10]
    assert format_seeds([3, 1, 2, 7, 9, 10]) == '1-3,7,9-10'
    for bad in ('a', '5-2', '-3', '1-', '', '1-2000000'):
        with pytest.raises(GridError):
            parse_seeds([bad])


def test_grid_of_cases():
    cases = gnss_cases([0, 2, 4], [100, 200])
    assert cases == [(0, 0.0), (2, 100.0), (4, 100.0), (2, 200.0), (4, 200.0)]
    keys = case_grid([1, 2], cases, ['fused'])
    assert len(keys) == 10 and keys[0] == CaseKey(1, 0, 0.0, 'fused')
    assert keys[1].tag == 's1_f2_b100_fused' and keys[0].tag == 's1_nlos_fused'
    with pytest.raises(GridError):
        gnss_cases([], [100])


# ------------------------------------------------------------------ pooled rates
def _case(seed, faults, method, mi, epochs, missed=0, fault_epochs=10):
    integrity = {lim: {'false_alarms': 3, 'epochs': epochs, 'faults': fault_epochs,
                       'missed_identifications': missed, 'failures': 5,
                       'failure_error_m': 4.0, 'bound_gap': 0.01}
                 for lim in ('8', '16')}
    return {'seed': seed, 'faults': faults, 'bias_m': 100.0 if faults else 0.0,
            'method': method, 'epochs': epochs, 'gnss_epochs': epochs, 'rmse_2d_m': 2.0,
            'rmse_3d_m': 3.0, 'filter_seconds': 1.0, 'integrity': integrity,
            'protection_level': {'mi_epochs': mi, 'epochs': epochs,
                                 'available_epochs': {'8': epochs - 20, '16': epochs}}}


def test_rates_pool_counts_over_seeds_with_their_intervals():
    cases = [_case(1, 0, 'fused', 4, 400), _case(2, 0, 'fused', 0, 380, missed=2),
             _case(1, 2, 'fused', 8, 400), _case(2, 2, 'fused', 2, 390)]
    assert case_counts(cases[1])[('p_fa', '8')] == (3, 370)
    assert case_counts(cases[1])[('p_mi', '8')] == (2, 10)
    out = campaign_intervals(cases)
    nlos = next(g for g in out['by_case'] if g['faults'] == 0)
    mi = nlos['rates']['mi_rate']
    assert (mi['count'], mi['n']) == (4, 780)
    assert mi['ci95'] == pytest.approx(clopper_pearson(4, 780))
    assert mi['per_seed'] == [[1, 4, 400], [2, 0, 380]]
    assert mi['between_seeds']['seeds'] == 2
    pooled = out['by_method']['fused']['rates']
    # Every case of a seed is one cluster: seed 1 has 12 MI epochs in 800.
    assert pooled['mi_rate']['per_seed'] == [[1, 12, 800], [2, 2, 770]]
    assert pooled['p_mi']['8']['count'] == 2 and pooled['p_mi']['8']['n'] == 40
    assert pooled['availability']['8']['count'] == 1570 - 80
    text = campaign_tables(cases, out)
    assert '0.0051 [0.0014, 0.0131] 4/780' in text          # NLOS-only MI rate
    rows = list(interval_csv_rows(out))
    assert any(r[0] == 'fused' and r[1] is None and r[3] == 'mi_rate' for r in rows)
    header, run_rows = run_csv(cases)
    assert len(run_rows) == 4 and 'p_mi_8_count' in header
