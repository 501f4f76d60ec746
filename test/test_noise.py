"""Process noise drawn ahead in chunks: the values are those of the stream drawn one block
ahead, in order, whatever the threads and chunks did, and a copied filter draws what the
original draws."""
import copy
from concurrent.futures import Future

import numpy as np
import pytest

from gnsscam_ros.core.noise import CHUNK_VALUES, MAX_CHUNK_BLOCKS, ProcessNoise, chunk_blocks

SMALL = (2, 10, 4)                                  # MAX_CHUNK_BLOCKS a chunk
MID = (10, 120, 4)                                  # dozens a chunk (N = 120)
LARGE = (10, CHUNK_VALUES // 10, 4)                 # one block a chunk
LARGER = (10, CHUNK_VALUES // 5, 4)


def _stream_one_ahead(seed: int, shapes: list) -> list:
    """What the blocks must be: each take hands out the block drawn ahead and draws the
    next in its shape; a block ahead of another shape is discarded."""
    rng = np.random.default_rng(seed)
    ahead, blocks = None, []
    for shape in shapes:
        if ahead is None or ahead.shape != shape:
            ahead = rng.standard_normal(shape, dtype=np.float32)
        blocks.append(ahead)
        ahead = rng.standard_normal(shape, dtype=np.float32)
    return blocks


def test_chunks_hold_whole_blocks():
    assert chunk_blocks(SMALL) == MAX_CHUNK_BLOCKS
    assert 1 < chunk_blocks(MID) == CHUNK_VALUES // 4800 < MAX_CHUNK_BLOCKS
    assert chunk_blocks(LARGE) == 1 and chunk_blocks(LARGER) == 1


K = chunk_blocks(MID)


@pytest.mark.parametrize('shapes', [
    [MID] * (2 * K + 3),                               # across chunks
    [MID] * 5 + [SMALL] * 3 + [MID] * 2,               # a new shape inside a chunk
    [MID] * (K + 1) + [SMALL] + [MID],                 # ... on a chunk's first block
    [MID] * K + [SMALL] * (MAX_CHUNK_BLOCKS + 6) + [MID],  # ... after its last block
    [SMALL, SMALL, (3, 10, 4), (3, 10, 4), SMALL],
    [LARGE, LARGE, LARGER, LARGER, LARGE],
    [SMALL, LARGE, LARGE, SMALL, MID],
])
def test_blocks_are_the_stream_one_ahead_in_order(shapes):
    noise = ProcessNoise(np.random.default_rng(4))
    got = [noise.take(s).copy() for s in shapes]       # each valid until the next
    for block, want in zip(got, _stream_one_ahead(4, shapes), strict=True):
        assert block.dtype == np.float32
        np.testing.assert_array_equal(block, want)


def test_the_chunks_buffers_alternate():
    noise = ProcessNoise(np.random.default_rng(8))
    blocks = [noise.take(MID) for _ in range(2 * K + 2)]
    # The first block is drawn here; then chunk A (blocks 1..K), chunk B, A's memory again.
    assert np.shares_memory(blocks[1], blocks[2 * K + 1])
    assert not np.shares_memory(blocks[1], blocks[K + 1])


@pytest.mark.parametrize('taken', [1, K - 1, K, K + 1])
def test_a_copy_draws_what_the_original_draws(taken):
    noise = ProcessNoise(np.random.default_rng(5))
    shapes = [MID] * taken
    for shape in shapes:
        noise.take(shape)                    # a chunk is being drawn ahead now
    twin = copy.deepcopy(noise)
    later = [MID, MID, SMALL, MID] + [MID] * K
    expected = _stream_one_ahead(5, shapes + later)[taken:]
    for shape, want in zip(later, expected, strict=True):
        np.testing.assert_array_equal(twin.take(shape), want)
        np.testing.assert_array_equal(noise.take(shape), want)


def test_a_failed_draw_ahead_is_raised_by_the_next_take():
    noise = ProcessNoise(np.random.default_rng(6))

    def broken(blocks, into):
        raise MemoryError('no room for the chunk')

    noise._draw = broken
    noise.take(LARGE)                        # drawn here; the chunk ahead fails
    with pytest.raises(MemoryError, match='no room'):
        noise.take(LARGE)
    del noise._draw                          # the memory is back: the next take draws
    assert noise.take(LARGE).shape == LARGE
    assert copy.deepcopy(noise).take(LARGE).shape == LARGE


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
    queue.put([noise.take(s).copy() for s in shapes])


@pytest.mark.parametrize('drawn_at_fork', [True, False])
def test_a_forked_process_starts_its_own_worker_and_draws_the_stream(drawn_at_fork):
    # The executor is copied into a forked child without its thread: a chunk submitted
    # to it there is never drawn. The child starts a worker of its own; a chunk drawn
    # ahead before the fork is the child's, one still being drawn is drawn again there.
    import multiprocessing
    noise = ProcessNoise(np.random.default_rng(9))
    noise.take(MID)
    noise._pending.result(timeout=30)
    if not drawn_at_fork:
        noise._pending = Future()            # as if the parent's worker were still at it
    context = multiprocessing.get_context('fork')
    queue = context.Queue()
    shapes = [MID] * (2 * K + 1)
    child = context.Process(target=_takes_in_child, args=(noise, shapes, queue))
    child.start()
    got = queue.get(timeout=60)
    child.join(timeout=60)
    assert child.exitcode == 0
    expected = _stream_one_ahead(9, [MID] + shapes)[1:]
    for block, want in zip(got, expected, strict=True):
        np.testing.assert_array_equal(block, want)
