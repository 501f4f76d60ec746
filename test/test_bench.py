"""The benchmark's timing: the epoch and its yardstick take turns, and each ratio pairs
the times of one round (``gnsscam_ros.bench.filter``)."""
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from gnsscam_ros.bench.filter import interleaved_times_ms, paired_ratio


def test_functions_take_turns_and_each_turn_warms_up_before_it_is_timed():
    calls = []
    times = interleaved_times_ms({'a': lambda: calls.append('a'),
                                  'b': lambda: calls.append('b')}, repeats=3, block=2)
    # Per round: a untimed + 2 timed, then b untimed + 2 timed.
    assert calls == ['a'] * 3 + ['b'] * 3 + ['a'] * 3 + ['b'] * 3 + ['a'] * 3 + ['b'] * 3
    assert set(times) == {'a', 'b'}
    assert all(t.shape == (3,) and np.all(t >= 0.0) for t in times.values())


def test_the_ratio_is_taken_within_rounds_so_a_drifting_machine_cancels():
    # The machine slows down 8x over the run; within each round the epoch costs 0.25 of
    # the yardstick, and the paired ratio says so. Taken across rounds (the epoch's
    # series rotated by one round) the same times give another figure.
    slow = np.array([1.0, 2.0, 3.0, 4.0, 8.0])
    assert paired_ratio({'epoch': 0.25 * slow, 'bare': slow}, 'epoch', 'bare') == 0.25
    rotated = {'epoch': 0.25 * np.roll(slow, -1), 'bare': slow}
    assert paired_ratio(rotated, 'epoch', 'bare') == 0.375


@pytest.mark.parametrize('given, expected', [(None, '1'), ('4', '4')])
def test_the_bench_runs_openblas_as_the_nodes_do_unless_told_otherwise(given, expected):
    """One OpenBLAS thread, as the node executables use, set before numpy is imported: with
    its default threads the yardstick leaves a thread spinning that slows the epoch timed
    after it. A value in the environment is kept."""
    env = {k: v for k, v in os.environ.items() if k != 'OPENBLAS_NUM_THREADS'}
    if given is not None:
        env['OPENBLAS_NUM_THREADS'] = given
    code = ('import os, sys, gnsscam_ros; numpy_first = "numpy" in sys.modules; '
            'import gnsscam_ros.bench.filter; '
            'print(numpy_first, os.environ["OPENBLAS_NUM_THREADS"])')
    out = subprocess.run([sys.executable, '-c', code], env=env, capture_output=True,
                         text=True, timeout=120, check=True).stdout.split()
    assert out == ['False', expected]


def test_the_pause_benchmark_runs_a_process_as_started_and_one_frozen():
    """``bench.pauses``: the frozen process's collector no longer tracks its start-up
    objects (the figures it prints are timings, read in its output, not asserted). Each
    run in a process of its own, as the benchmark runs them: a freeze is for good."""
    from gnsscam_ros.bench.pauses import MODES
    rows = []
    for mode in MODES:
        out = subprocess.run([sys.executable, '-m', 'gnsscam_ros.bench.pauses', '--child',
                              mode, '--epochs', '5', '--particles', '16'],
                             capture_output=True, text=True, timeout=300, check=True)
        rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
    assert [r['mode'] for r in rows] == list(MODES)
    as_started, frozen = rows
    assert as_started['tracked_objects'] > 20_000
    assert frozen['tracked_objects'] < 0.01 * as_started['tracked_objects']
    assert all(r['epochs'] == 5 and r['epoch_ms_max'] >= r['epoch_ms_median'] > 0.0
               for r in rows)
