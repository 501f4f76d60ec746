"""Process noise drawn one epoch ahead: the values are those of the stream drawn in order,
whatever the threads did, and a copied filter draws what the original draws."""
import copy

import numpy as np
import pytest

from gnsscam_ros.core.noise import THREADED_MIN_VALUES, ProcessNoise

SMALL = (2, 10, 4)
LARGE = (10, THREADED_MIN_VALUES // 10, 4)       # drawn on the worker thread
LARGER = (10, THREADED_MIN_VALUES // 5, 4)


def _stream(seed: int, shapes: list) -> list:
    rng = np.random.default_rng(seed)
    return [rng.standard_normal(s, dtype=np.float32) for s in shapes]


@pytest.mark.parametrize('a, b', [(SMALL, (3, 10, 4)), (LARGE, LARGER), (SMALL, LARGE)])
def test_blocks_are_the_stream_in_order_and_a_new_shape_discards_the_block_ahead(a, b):
    noise = ProcessNoise(np.random.default_rng(4))
    got = [noise.take(s).copy() for s in (a, a, b, b, a)]     # each valid until the next
    # Drawn: a, a, (a ahead: discarded), b, b, (b ahead: discarded), a.
    expected = _stream(4, [a, a, a, b, b, b, a])
    for block, want in zip(got, [expected[i] for i in (0, 1, 3, 4, 6)]):
        assert block.dtype == np.float32
        np.testing.assert_array_equal(block, want)


def test_two_buffers_alternate():
    noise = ProcessNoise(np.random.default_rng(8))
    first, second, third = (noise.take(LARGE) for _ in range(3))
    assert first is third and first is not second


def test_a_copy_draws_what_the_original_draws():
    noise = ProcessNoise(np.random.default_rng(5))
    noise.take(LARGE)                       # a block is being drawn ahead now
    twin = copy.deepcopy(noise)
    np.testing.assert_array_equal(twin.take(LARGE), noise.take(LARGE))
    np.testing.assert_array_equal(twin.take(SMALL), noise.take(SMALL))


def test_a_failed_draw_ahead_is_raised_by_the_next_take():
    noise = ProcessNoise(np.random.default_rng(6))
    noise.take(LARGE)
    noise._wait()
    noise._next = None

    def broken(shape, into):
        raise MemoryError('no room for the block')

    noise._draw = broken
    noise._draw_ahead(LARGE, None)
    with pytest.raises(MemoryError, match='no room'):
        noise.take(LARGE)


def test_a_process_exiting_while_a_block_is_drawn_waits_for_it_and_exits_cleanly():
    # The block ahead is drawn on a thread the interpreter joins before it finalises (a
    # daemon thread still filling an array during finalisation can crash the process).
    import subprocess
    import sys
    code = ('import numpy as np, threading\n'
            'from gnsscam_ros.core.noise import ProcessNoise\n'
            'noise = ProcessNoise(np.random.default_rng(0))\n'
            'noise.take((10, 400_000, 4))\n'
            'worker = [t for t in threading.enumerate() if t.name.startswith("process-noise")]\n'
            'assert worker and not worker[0].daemon, worker\n'
            'print("exiting while drawing", worker[0].is_alive())\n')
    done = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr
    assert 'exiting while drawing' in done.stdout


def _takes_in_child(noise, shapes, queue):
    blocks = [noise.take(s).copy() for s in shapes]
    # The block after them is being drawn ahead, by a worker of this process.
    ahead = noise._pending.result(timeout=30).copy()
    queue.put(blocks + [ahead])


@pytest.mark.parametrize('taken', [True, False])
def test_a_forked_process_starts_its_own_worker_and_draws_the_stream(taken):
    # The executor is copied into a forked child without its thread: a block submitted
    # to it there is never drawn. The child starts a worker of its own and draws ahead;
    # a block drawn ahead before the fork but not yet taken is the child's next block.
    import multiprocessing
    noise = ProcessNoise(np.random.default_rng(9))
    noise.take(LARGE)
    if taken:
        noise._wait()                        # drawn and taken into _next before the fork
    else:
        noise._pending.result(timeout=30)    # drawn, still pending at the fork
    context = multiprocessing.get_context('fork')
    queue = context.Queue()
    child = context.Process(target=_takes_in_child, args=(noise, [LARGE, LARGE], queue))
    child.start()
    got = queue.get(timeout=60)
    child.join(timeout=60)
    assert child.exitcode == 0
    expected = _stream(9, [LARGE] * 4)
    for block, want in zip(got, expected[1:]):
        np.testing.assert_array_equal(block, want)
