"""Where a campaign's cases run: in this process, on an embedded Dask cluster, or on an
existing one.

* ``CaseRunner()`` starts an embedded :class:`distributed.LocalCluster`: one worker
  process per core (``workers``), one thread each (the filter is single-threaded numpy;
  the nannies set ``OPENBLAS_NUM_THREADS=1``), nannies that restart a worker that dies.
  Their ``MALLOC_TRIM_THRESHOLD_`` is left out here and undone on any worker
  (:func:`tune_malloc`).
* ``CaseRunner(scheduler='tcp://host:8786')`` connects to a running scheduler (``dask
  scheduler`` and ``dask worker`` processes on machines that have the package installed).
* ``CaseRunner(sequential=True)`` runs every case here, one after the other, without Dask
  (the reference of the equality test; debugging).

Nothing assumes a shared disk: a case is made on its worker from its key (the drive is
generated from the seed); a seed's camera matches are made once by a task on some worker
(cached on that machine's disk by content, :func:`.campaign.camera_matches_for_seed`) and
Dask ships the arrays to the workers that run the seed's fused cases; results come back to
this process, which alone writes files. A worker that dies mid-case costs a retry: the
scheduler gives its tasks to another worker (up to ``distributed.scheduler.allowed-failures``
deaths per task, default 3); a case that still fails is reported and left for the next run.
"""
from __future__ import annotations

import os
import time
from typing import Iterator

from ..core.filter import FilterConfig
from ..nodes.memory import set_malloc_thresholds
from .campaign import camera_cache_key, camera_matches_for_seed, case_task, uses_camera
from .campaign_grid import CaseKey

#: Seconds to wait for an existing scheduler to answer.
CONNECT_TIMEOUT_S = 30.0


class ClusterError(RuntimeError):
    """The cluster cannot be started or reached."""


#: The values glibc's dynamic thresholds reach under numpy.
_MMAP_THRESHOLD_B, _TRIM_THRESHOLD_B = 32 * 2 ** 20, 64 * 2 ** 20
_malloc_tuned = False


def tune_malloc() -> bool:
    """Undo what a Dask nanny's ``MALLOC_TRIM_THRESHOLD_`` does to this worker process.

    Setting that variable turns off glibc's dynamic mmap threshold: every numpy temporary
    above 128 kB is then mapped and unmapped again (measured: ~200,000 page faults and
    1.4x the CPU time per case). Setting the thresholds to where the dynamic ones settle
    (mmap 32 MiB, trim 64 MiB) restores the speed; the cost is up to 64 MiB of freed
    memory kept per worker. Only when the variable is set and the C library has mallopt.

    Returns:
        True when the thresholds were set.
    """
    global _malloc_tuned
    if _malloc_tuned or 'MALLOC_TRIM_THRESHOLD_' not in os.environ:
        return _malloc_tuned
    _malloc_tuned = set_malloc_thresholds(_MMAP_THRESHOLD_B, _TRIM_THRESHOLD_B)
    return _malloc_tuned


def _camera_on_worker(seed, cache_dir, duration_s):
    """:func:`.campaign.camera_matches_for_seed` on a worker (its disk cache)."""
    tune_malloc()
    return camera_matches_for_seed(seed, cache_dir, duration_s)


def _shared_input(value):
    """A shared input as a task's result (its data stays in the task: see run_tasks)."""
    return value


def _task_on_worker(function, shared, args):
    """``function(shared, *args)`` on a worker, and where and how long it ran."""
    from distributed import get_worker      # only on workers (Dask is imported there)
    tune_malloc()
    start = time.perf_counter()
    out = function(shared, *args)
    return {'result': out, 'worker': get_worker().address,
            'wall_seconds': time.perf_counter() - start}


def _case_on_worker(key, base, camera, duration_s, want_epochs):
    """:func:`.campaign.case_task` and where it ran (the worker's address)."""
    from distributed import get_worker      # only on workers (Dask is imported there)
    tune_malloc()
    start = time.perf_counter()
    out = case_task(key, base, camera, duration_s, want_epochs)
    out['worker'] = get_worker().address
    out['wall_seconds'] = time.perf_counter() - start
    return out


class CaseRunner:
    """Runs cases; a context manager that owns its cluster (if embedded) and client.

    Args:
        scheduler: Address of an existing scheduler (None: embedded cluster).
        workers: Worker processes of the embedded cluster (default: the cores).
        sequential: Run in this process without Dask.
        cache_dir: Where workers cache map databases and camera matches (a path on each
            worker; None: each worker's default cache folder).

    Attributes:
        info: ``{'kind', 'scheduler', 'workers', 'threads_per_worker', 'dask'}`` once
            entered: what the campaign JSON records.
    """

    def __init__(self, scheduler: str | None = None, workers: int | None = None,
                 sequential: bool = False, cache_dir: str | None = None):
        if sequential and scheduler:
            raise ValueError('sequential and scheduler exclude each other')
        self.scheduler, self.sequential, self.cache_dir = scheduler, sequential, cache_dir
        self.workers = workers or os.cpu_count() or 1
        self.client = self.cluster = None
        self.info: dict = {}

    def __enter__(self) -> 'CaseRunner':
        if self.sequential:
            self.info = {'kind': 'sequential', 'scheduler': None, 'workers': 1,
                         'threads_per_worker': 1, 'dask': None}
            return self
        import dask
        from distributed import Client, LocalCluster
        try:
            if self.scheduler:
                self.client = Client(self.scheduler, timeout=CONNECT_TIMEOUT_S)
            else:
                # Dask's nannies set MALLOC_TRIM_THRESHOLD_ in their workers, which turns
                # off glibc's dynamic mmap threshold: every large numpy temporary is then
                # mapped and unmapped again, and the filter runs ~1.4x slower.
                with dask.config.set(
                        {'distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_': None}):
                    self.cluster = LocalCluster(n_workers=self.workers, threads_per_worker=1,
                                                processes=True, dashboard_address=None,
                                                silence_logs=40)
                self.client = Client(self.cluster)
        except (OSError, TimeoutError) as err:
            self.__exit__(None, None, None)
            where = self.scheduler or 'an embedded cluster'
            raise ClusterError(f'cannot reach {where}: {err}') from err
        workers = self.client.scheduler_info(n_workers=-1)['workers']
        self.info = {'kind': 'scheduler' if self.scheduler else 'embedded',
                     'scheduler': self.client.scheduler.address, 'workers': len(workers),
                     'threads_per_worker': sorted({w['nthreads'] for w in workers.values()}),
                     'dask': dask.__version__}
        return self

    def __exit__(self, *exc) -> None:
        if self.client is not None:
            self.client.close()
        if self.cluster is not None:
            self.cluster.close()
        self.client = self.cluster = None

    def run(self, todo: list[CaseKey], base: FilterConfig, duration_s: float | None = None,
            want_epochs: bool = False) -> Iterator[tuple[CaseKey, dict | None, str | None]]:
        """Run the cases; yields ``(key, result, None)`` as each finishes, or
        ``(key, None, error message)`` for a case that failed."""
        if self.sequential:
            yield from self._run_here(todo, base, duration_s, want_epochs)
        else:
            yield from self._run_dask(todo, base, duration_s, want_epochs)

    def run_tasks(self, function, tasks, shared: dict | None = None
                  ) -> Iterator[tuple[object, dict | None, str | None]]:
        """Run ``function(shared[name], *args)`` for every task ``(label, name, args)``,
        here or on the cluster; yields ``(label, {'result', 'worker', 'wall_seconds'},
        None)`` as each finishes, or ``(label, None, error message)`` for one that failed.

        A shared input (e.g. the drive a group of tasks reads) goes to the cluster once: it
        becomes a task of its own whose result the group's tasks take, so its data lives in
        the task's definition and a worker that dies holding it costs a recomputation, not
        the run (scattered data would be lost with it). ``function`` and the arguments
        must be picklable (module-level functions, plain data).
        """
        shared = shared or {}
        if self.sequential:
            for label, name, args in tasks:
                start = time.perf_counter()
                try:
                    out = function(shared.get(name), *args)
                except Exception as err:  # reported like a failed task of a cluster
                    yield label, None, f'{type(err).__name__}: {err}'
                    continue
                yield label, {'result': out, 'worker': 'local',
                              'wall_seconds': time.perf_counter() - start}, None
            return
        from distributed import as_completed
        client = self.client
        inputs = {name: client.submit(_shared_input, value, pure=False,
                                      key=f'shared-{name}-{id(self):x}')
                  for name, value in shared.items()}
        futures = {client.submit(_task_on_worker, function, inputs.get(name), args,
                                 pure=False, key=f'task-{label}-{id(self):x}'): label
                   for label, name, args in tasks}
        try:
            for fut in as_completed(futures):
                label = futures.pop(fut)
                try:
                    result, error = fut.result(), None
                except Exception as err:  # KilledWorker after too many deaths, a bug
                    result, error = None, f'{type(err).__name__}: {err}'
                fut.release()
                yield label, result, error
        finally:
            for fut in list(futures) + list(inputs.values()):
                fut.cancel()

    def _run_here(self, todo, base, duration_s, want_epochs):
        camera: dict[int, object] = {}
        for key in todo:
            start = time.perf_counter()
            try:
                cam = None
                if uses_camera(key.method, base):
                    if key.seed not in camera:
                        camera[key.seed] = camera_matches_for_seed(key.seed, self.cache_dir,
                                                                   duration_s)
                    cam = camera[key.seed]
                out = case_task(key, base, cam, duration_s, want_epochs)
            except Exception as err:      # reported like a failed task of a cluster
                yield key, None, f'{type(err).__name__}: {err}'
                continue
            out['worker'] = 'local'
            out['wall_seconds'] = time.perf_counter() - start
            yield key, out, None

    def _run_dask(self, todo, base, duration_s, want_epochs):
        from distributed import as_completed
        client = self.client
        camera = {}
        needs = {}
        for key in todo:
            if uses_camera(key.method, base):
                needs[key.seed] = needs.get(key.seed, 0) + 1
        for seed in needs:
            # The key names the content: the same seed is made once per campaign, and a
            # worker's disk cache (same content key) makes a recomputation cheap.
            camera[seed] = client.submit(
                _camera_on_worker, seed, self.cache_dir, duration_s,
                key=f'camera-{camera_cache_key(seed, duration_s)}', pure=False)
        # Every task carries the configuration (a few kB): scattered data would be lost
        # with the worker holding it, whereas a task's arguments are resent on a retry.
        futures = {}
        for key in todo:
            cam = camera.get(key.seed) if uses_camera(key.method, base) else None
            fut = client.submit(_case_on_worker, key, base, cam, duration_s,
                                want_epochs, key=f'case-{key.tag}-{id(self):x}', pure=False)
            futures[fut] = key
        try:
            for fut in as_completed(futures):
                key = futures.pop(fut)
                try:
                    result, error = fut.result(), None
                except Exception as err:   # KilledWorker after too many deaths, a bug
                    result, error = None, f'{type(err).__name__}: {err}'
                fut.release()
                if key.seed in needs and uses_camera(key.method, base):
                    needs[key.seed] -= 1
                    if needs[key.seed] == 0:
                        camera.pop(key.seed).release()     # free the workers' memory
                yield key, result, error
        finally:
            for fut in list(futures) + list(camera.values()):
                fut.cancel()
