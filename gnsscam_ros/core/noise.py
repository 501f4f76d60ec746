"""Process noise drawn one epoch ahead, off the epoch's critical path.

The per-particle process noise is the largest random draw of an epoch (M x N x 4 standard
normals: 400,000 at N = 10,000, M = 10, several milliseconds) and depends on nothing the
epoch measures. :class:`ProcessNoise` draws it from a stream of its own, one block ahead:
each :meth:`ProcessNoise.take` hands out the block drawn after the previous one and starts
drawing the next on a worker thread (numpy releases the interpreter lock while it fills
an array), so a node's epoch finds its noise ready and the draw runs while the node waits
for the next epoch (or on another core). The worker is one thread per stream, started
once: a thread started per epoch cost the epoch about 0.17 ms here (``Thread.start``
waits until the new thread runs), handing a block to a running worker about 0.02 ms.

The values never depend on timing or threads: the stream is consumed in the same order
either way — one block of the requested shape per ``take``, the next block drawn in the
shape of the last one asked for; a prefetched block of another shape (the particle count
changed) is discarded and a block of the new shape drawn in its place. Small blocks are
drawn on the calling thread (a thread start would cost more than the draw).
"""
from __future__ import annotations

import math
import os
from concurrent.futures import Future, ThreadPoolExecutor

import numpy as np

#: Blocks of at least this many values are drawn on a worker thread (starting one costs
#: about as much as drawing ~10,000 values; the default configuration draws 40,000).
THREADED_MIN_VALUES = 16_384


class ProcessNoise:
    """Float32 standard normal blocks from ``rng``, each drawn one ``take`` ahead.

    Args:
        rng: The noise stream (used by nothing else).
    """

    def __init__(self, rng: np.random.Generator):
        self.rng = rng
        self._next: np.ndarray | None = None
        # The block handed out last: its memory takes the block after next (two buffers
        # alternate, so no epoch pays for fresh pages).
        self._handed_out: np.ndarray | None = None
        self._pending: Future | None = None          # the block being drawn ahead
        self._worker: ThreadPoolExecutor | None = None
        self._worker_pid = 0

    def take(self, shape: tuple[int, ...]) -> np.ndarray:
        """The next block of standard normals of ``shape`` (float32). It is valid until
        the next ``take``, which reuses its memory."""
        shape = tuple(int(s) for s in shape)
        self._wait()
        block, self._next = self._next, None
        if block is None or block.shape != shape:
            block = self._draw(shape, None)
        free, self._handed_out = self._handed_out, block
        self._draw_ahead(shape, free)
        return block

    def _draw(self, shape: tuple[int, ...], into: np.ndarray | None) -> np.ndarray:
        if into is None or into.shape != shape:
            return self.rng.standard_normal(shape, dtype=np.float32)
        return self.rng.standard_normal(dtype=np.float32, out=into)

    def _draw_ahead(self, shape: tuple[int, ...], into: np.ndarray | None) -> None:
        if math.prod(shape) < THREADED_MIN_VALUES:
            self._next = self._draw(shape, into)
            return
        self._pending = self._running_worker().submit(self._draw, shape, into)

    def _running_worker(self) -> ThreadPoolExecutor:
        """The stream's worker, started on first use. A process forked from this one (a
        campaign worker) has the executor but not its thread, so it starts its own. The
        executor's thread is not a daemon: the interpreter joins it before it finalises
        (a daemon thread still filling an array while a node process exits, Ctrl-C right
        after an epoch, runs on in a half torn-down interpreter and can crash the process,
        SIGSEGV, instead of exiting 0; a draw takes milliseconds, so the join never holds
        an exit up)."""
        if self._worker is None or self._worker_pid != os.getpid():
            self._worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix='process-noise')
            self._worker_pid = os.getpid()
        return self._worker

    def _wait(self) -> None:
        """Take the block drawn ahead into ``_next``; a failed draw is raised here. In a
        process forked before the draw was done it is never done (its thread stayed
        behind, the stream is where the draw found it): ``take`` draws the block."""
        if self._pending is not None:
            pending, self._pending = self._pending, None
            if self._worker_pid == os.getpid() or pending.done():
                self._next = pending.result()

    # A filter is copied (tests compare it with a copy of itself) and handed between
    # processes: the block being drawn is part of the state, the thread is not.
    def __getstate__(self) -> dict:
        self._wait()
        return {'rng': self.rng, 'next': self._next}

    def __setstate__(self, state: dict) -> None:
        self.rng, self._next = state['rng'], state['next']
        self._handed_out = self._pending = self._worker = None
        self._worker_pid = 0
