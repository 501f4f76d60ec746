"""Process noise drawn ahead, off the epoch's critical path.

The per-particle process noise is the largest random draw of an epoch (M x N x 4 standard
normals: 400,000 at N = 10,000, M = 10, several milliseconds; 4,800 at N = 120, about 45 us
here, a tenth of that epoch) and depends on nothing the epoch measures.
:class:`ProcessNoise` draws it from a stream of its own, ahead, on a worker thread (numpy
releases the interpreter lock while it fills an array), so a node's epoch finds its noise
ready and the draw runs while the node waits for the next epoch (or on another core).
The blocks are drawn in chunks of about :data:`CHUNK_VALUES` values: one block per chunk
at the default size, some fifty at N = 120. Handing a chunk over costs about 0.1 ms here
(the worker needs the interpreter lock to start its draw and to hand the chunk back, and
the epoch's Python code holds it most of the time), more than drawing one small block; a
chunk spreads that over many epochs and gives the worker time to finish (a block per
chunk at N = 120 cost the epoch more than drawing it). The worker is one thread per
stream, started once: a thread started per epoch cost the epoch about 0.17 ms here
(``Thread.start`` waits until the new thread runs).

The values never depend on timing, threads or chunks: the stream is consumed as if each
``take`` handed out the block drawn after the previous one and drew the next one in the
shape of the last one asked for. A block of another shape asked for discards that block
ahead and draws one of the new shape; the blocks a chunk drew beyond the block ahead are
put back (the stream is set to its state before the chunk and the blocks up to the block
ahead drawn again).
"""
from __future__ import annotations

import math
import os
from concurrent.futures import Future, ThreadPoolExecutor

import numpy as np

#: Values a chunk drawn ahead holds at most, unless one block is larger (a chunk holds
#: whole blocks, at least one).
CHUNK_VALUES = 262_144
#: Blocks a chunk holds at most (a few values per block: the chunk stays a chunk).
MAX_CHUNK_BLOCKS = 64


def chunk_blocks(shape: tuple[int, ...]) -> int:
    """Blocks of ``shape`` in a chunk drawn ahead."""
    size = max(math.prod(shape), 1)
    return max(1, min(MAX_CHUNK_BLOCKS, CHUNK_VALUES // size))


class ProcessNoise:
    """Float32 standard normal blocks from ``rng``, drawn ahead in chunks.

    Args:
        rng: The noise stream (used by nothing else).
    """

    def __init__(self, rng: np.random.Generator):
        self.rng = rng
        # The chunk blocks are handed out from, the stream's state before it, and the
        # index of its next block (the block ahead when there is one).
        self._ready: np.ndarray | None = None
        self._ready_state: dict | None = None
        self._index = 0
        # The chunk after it being drawn (a Future of the chunk) and the stream's state
        # before it; the buffer of the chunk before (its memory takes the next chunk, so
        # no epoch pays for fresh pages).
        self._pending: Future | None = None
        self._pending_state: dict | None = None
        self._pending_blocks: tuple[int, ...] = ()
        self._spare: np.ndarray | None = None
        self._worker: ThreadPoolExecutor | None = None
        self._worker_pid = 0

    def take(self, shape: tuple[int, ...]) -> np.ndarray:
        """The next block of standard normals of ``shape`` (float32). It is valid until
        the next ``take``, which may reuse its memory."""
        shape = tuple(int(s) for s in shape)
        if self._ready is None or self._ready.shape[1:] != shape:
            self._restart(shape)
        elif self._index == self._ready.shape[0]:
            if self._pending is None:          # its draw failed, and the last take said so
                self._restart(shape)
            else:
                self._spare = self._ready
                self._ready_state = self._pending_state
                self._ready, self._index = self._collect(), 0
        block = self._ready[self._index]
        self._index += 1
        if self._pending is None:
            self._draw_ahead(shape)
        return block

    def _restart(self, shape: tuple[int, ...]) -> None:
        """Discard the block ahead (of another shape) and draw one of ``shape`` here."""
        self._settle()
        self._spare = None
        self._ready_state = self.rng.bit_generator.state
        self._ready = self.rng.standard_normal((1, *shape), dtype=np.float32)
        self._index = 0

    def _draw_ahead(self, shape: tuple[int, ...]) -> None:
        """Start drawing the chunk after the ready one on the worker."""
        blocks = (chunk_blocks(shape), *shape)
        into = self._spare if self._spare is not None and self._spare.shape == blocks else None
        self._spare = None
        # Read here, while nothing draws: the worker is idle and the caller waits.
        self._pending_state, self._pending_blocks = self.rng.bit_generator.state, blocks
        self._pending = self._running_worker().submit(self._draw, blocks, into)

    def _draw(self, blocks: tuple[int, ...], into: np.ndarray | None) -> np.ndarray:
        # One call for the chunk: the values are those of its blocks drawn one by one.
        if into is None:
            return self.rng.standard_normal(blocks, dtype=np.float32)
        return self.rng.standard_normal(dtype=np.float32, out=into)

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

    def _collect(self) -> np.ndarray:
        """The chunk drawn ahead; a failed draw is raised here. In a process forked
        before the draw was done it is never done (its thread stayed behind): the stream
        is set back to its state before the chunk and the chunk drawn here."""
        pending, self._pending = self._pending, None
        if self._worker_pid == os.getpid() or pending.done():
            return pending.result()
        self.rng.bit_generator.state = self._pending_state
        return self.rng.standard_normal(self._pending_blocks, dtype=np.float32)

    def _settle(self) -> None:
        """Leave the stream as drawing one block ahead leaves it: the ready chunk is the
        block ahead alone, the stream's state the one after it, nothing drawn ahead."""
        if self._ready is None:
            return
        following = self._collect() if self._pending is not None else None
        if self._index < self._ready.shape[0]:
            chunk, state, index = self._ready, self._ready_state, self._index
            beyond = chunk.shape[0] - index - 1 + (
                following.shape[0] if following is not None else 0)
        elif following is not None:
            chunk, state, index = following, self._pending_state, 0
            beyond = chunk.shape[0] - 1
        else:                                   # nothing ahead: its draw failed
            self._ready, self._ready_state = None, None
            return
        if beyond:
            # Drawn again up to the block ahead, from the state before its chunk.
            self.rng.bit_generator.state = state
            self.rng.standard_normal((index + 1, *chunk.shape[1:]), dtype=np.float32)
        self._ready, self._index = chunk[index:index + 1].copy(), 0
        self._ready_state = None                # its blocks beyond it are put back

    # A filter is copied (tests compare it with a copy of itself) and handed between
    # processes: the block ahead is part of the state, the thread and chunks are not.
    def __getstate__(self) -> dict:
        self._settle()
        return {'rng': self.rng, 'next': None if self._ready is None else self._ready[0]}

    def __setstate__(self, state: dict) -> None:
        self.__init__(state['rng'])
        if state['next'] is not None:
            self._ready = np.asarray(state['next'], dtype=np.float32)[None].copy()
