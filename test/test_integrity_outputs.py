"""Integrity outputs: Stanford counts and diagram, error/PL timeline, CSV writer."""
import csv
import math

import numpy as np
import pytest

from gnsscam_ros.evaluation.report import STANFORD_KEYS, stanford_counts
from gnsscam_ros.io.atomic import OutputExistsError, write_csv_atomic

AL = 10.0
# (error, PL, region) by hand, one or more per region, boundaries included.
CASES = [
    (1.0, 5.0, 'nominal'),
    (5.0, 5.0, 'nominal'),            # PE == PL: bounded
    (10.0, 10.0, 'nominal'),          # PE == PL == AL: still available and bounded
    (0.0, 0.0, 'nominal'),
    (6.0, 5.0, 'mi'),
    (10.0, 2.0, 'mi'),                # PE == AL: not hazardous
    (11.0, 2.0, 'hmi'),
    (200.0, 10.0, 'hmi'),             # PL == AL: available
    (3.0, 50.0, 'unavailable'),
    (50.0, 50.0, 'unavailable'),
    (1.0, math.inf, 'unavailable'),   # no PL
    (500.0, math.nan, 'unavailable'),  # no PL, even with a huge error
    (60.0, 50.0, 'unavailable_mi'),
    (12.0, 11.0, 'unavailable_mi'),
]


def _cases():
    err = np.array([c[0] for c in CASES])
    pl = np.array([c[1] for c in CASES])
    return err, pl


def test_stanford_counts_known_answer():
    err, pl = _cases()
    counts = stanford_counts(err, pl, AL)
    assert counts == {'epochs': 14, 'nominal': 4, 'mi': 2, 'hmi': 2, 'unavailable': 4,
                      'unavailable_mi': 2, 'no_pl': 2}
    assert tuple(counts) == STANFORD_KEYS
    assert sum(counts[k] for k in ('nominal', 'mi', 'hmi', 'unavailable',
                                   'unavailable_mi')) == counts['epochs']
    assert all(type(v) is int for v in counts.values())     # JSON-ready
    for e, p, region in CASES:                              # one epoch at a time
        single = stanford_counts([e], [p], AL)
        assert single[region] == 1, (e, p, region, single)


def test_stanford_counts_rejects_bad_input():
    with pytest.raises(ValueError):
        stanford_counts([1.0, math.nan], [1.0, 1.0], AL)
    with pytest.raises(ValueError):
        stanford_counts([1.0], [1.0, 2.0], AL)
    with pytest.raises(ValueError):
        stanford_counts([1.0], [1.0], math.inf)
    assert stanford_counts([], [], AL)['epochs'] == 0


@pytest.mark.slow
def test_plots_written(tmp_path):
    from gnsscam_ros.evaluation.plots import error_pl_timeline, stanford_diagram
    err, pl = _cases()
    # The hand-made set plus one epoch without ground truth that ``valid`` removes.
    err_v, pl_v = np.append(err, math.nan), np.append(pl, 1.0)
    valid = np.isfinite(err_v)
    out = tmp_path / 'figs' / 'stanford.png'
    counts = stanford_diagram(out, 'hand-made', err_v, pl_v, AL, valid=valid)
    assert counts == stanford_counts(err, pl, AL)
    assert out.stat().st_size > 1000
    # Many epochs (the histogram path) and an empty set both draw.
    rng = np.random.default_rng(1)
    big_err = rng.lognormal(1.0, 1.0, 20000)
    big_pl = np.where(rng.random(20000) < 0.05, np.inf, big_err * rng.lognormal(0.5, 0.7, 20000))
    assert stanford_diagram(tmp_path / 'big.png', 'many', big_err, big_pl, AL)['epochs'] == 20000
    assert stanford_diagram(tmp_path / 'empty.png', 'none', [], [], AL)['epochs'] == 0

    t = np.arange(err_v.size, dtype=float)
    levels = np.array(['OK'] * err_v.size)
    levels[::3] = 'ERROR'
    levels[1] = 'STALE'
    timeline = error_pl_timeline(tmp_path / 'timeline.png', 'hand-made', t, err_v, pl_v, AL,
                                 integrity_levels=levels)
    assert timeline.stat().st_size > 1000
    assert error_pl_timeline(tmp_path / 'plain.png', 'no flags', t, err_v, pl_v,
                             AL).stat().st_size > 1000
    assert not list(tmp_path.rglob('.*'))                   # no temporary files left


def test_csv_round_trip_and_missing(tmp_path):
    path = tmp_path / 'sub' / 'epochs.csv'
    floats = [0.1, 1 / 3, 1e-300, 123456789.123456789, -2.5e17, math.inf]
    rows = [[i, x, np.float64(x), None] for i, x in enumerate(floats)]
    rows.append([99, math.nan, np.float32('nan'), 'OK'])
    write_csv_atomic(path, ['i', 'x', 'x_np', 'level'], iter(rows))
    with open(path, newline='', encoding='utf-8') as handle:
        read = list(csv.reader(handle))
    assert read[0] == ['i', 'x', 'x_np', 'level']
    for (i, x, _, _), line in zip(rows[:-1], read[1:-1]):
        assert line[0] == str(i)
        assert float(line[1]) == x and float(line[2]) == x   # bit-exact round trip
        assert line[3] == ''
    assert read[-1] == ['99', '', '', 'OK']


def test_csv_refuses_overwrite_and_cleans_up(tmp_path):
    path = tmp_path / 'out.csv'
    write_csv_atomic(path, ['a'], [[1.0]])
    with pytest.raises(OutputExistsError):
        write_csv_atomic(path, ['a'], [[2.0]])
    assert path.read_text().splitlines() == ['a', '1.0']
    write_csv_atomic(path, ['a'], [[2.0]], force=True)
    assert path.read_text().splitlines() == ['a', '2.0']

    def failing_rows():
        yield [3.0]
        raise RuntimeError('producer failed mid-way')

    with pytest.raises(RuntimeError):
        write_csv_atomic(path, ['a'], failing_rows(), force=True)
    with pytest.raises(ValueError):
        write_csv_atomic(tmp_path / 'short.csv', ['a', 'b'], [[1.0, 2.0], [1.0]])
    assert path.read_text().splitlines() == ['a', '2.0']   # the old file is untouched
    assert sorted(p.name for p in tmp_path.iterdir()) == ['out.csv']
