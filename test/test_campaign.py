"""The campaign on Dask: same results as a sequential run, on an embedded cluster and on a
separately started scheduler with two workers; an interrupted campaign resumes; a worker
killed mid-case costs a retry, not the campaign.

Tiny grids of short drives (15 s, 200 particles) keep this to seconds per test; the
figures of real campaigns are the bench's (``python -m gnsscam_ros.bench.campaign``).
"""
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import dask
import numpy as np
import pytest
from conftest import stop_child

from gnsscam_ros.evaluation.campaign import campaign_config
from gnsscam_ros.evaluation.campaign_grid import CaseKey
from gnsscam_ros.evaluation.campaign_run import run_campaign
from gnsscam_ros.evaluation.campaign_store import CampaignStoreError
from gnsscam_ros.evaluation.cli import main as eval_main

pytestmark = pytest.mark.slow

GRID = dict(seeds=(1, 2), cases=[(0, 0.0), (4, 200.0)], methods=('gnss_robust',),
            duration_s=15.0, progress=False)
#: What the embedded cluster does to its nannies (campaign_cluster): glibc's own malloc.
FAST_MALLOC = {'distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_': None}
#: Bookkeeping of where and how long a case ran: not part of its result.
TIMING = ('filter_seconds', 'wall_seconds', 'worker')


def base():
    return campaign_config(n_particles=200)


def results(out: dict) -> dict:
    """``{(seed, faults, bias, method): metrics without timing}`` of a campaign."""
    return {(c['seed'], c['faults'], c['bias_m'], c['method']):
            {k: v for k, v in c.items() if k not in TIMING} for c in out['cases']}


def assert_same_series(dir_a: Path, dir_b: Path):
    names = sorted(p.name for p in (dir_a / 'cases').glob('*.npz'))
    assert names == sorted(p.name for p in (dir_b / 'cases').glob('*.npz'))
    for name in names:
        with np.load(dir_a / 'cases' / name) as a, np.load(dir_b / 'cases' / name) as b:
            assert set(a.files) == set(b.files)
            for k in a.files:
                np.testing.assert_array_equal(a[k], b[k], err_msg=f'{name} {k}')


@pytest.fixture(scope='module')
def sequential(tmp_path_factory):
    folder = tmp_path_factory.mktemp('sequential')
    out = run_campaign(base=base(), out_dir=folder, sequential=True, **GRID)
    assert out['cluster']['kind'] == 'sequential' and not out['failed']
    return folder, out


def test_embedded_cluster_equals_the_sequential_run_case_by_case(tmp_path, sequential):
    seq_dir, seq = sequential
    out = run_campaign(base=base(), out_dir=tmp_path, workers=2, **GRID)
    assert out['cluster']['kind'] == 'embedded' and out['cluster']['workers'] == 2
    assert out['cluster']['scheduler'].startswith('tcp://127.0.0.1:')
    assert len(out['cases']) == 4 and out['computed'] == 4 and not out['failed']
    assert results(out) == results(seq)
    assert_same_series(tmp_path, seq_dir)
    assert out['intervals'] == seq['intervals']
    summary = json.loads((tmp_path / 'campaign.json').read_text())
    mi = summary['intervals']['by_method']['gnss_robust']['rates']['mi_rate']
    assert mi['n'] == sum(c['protection_level']['epochs'] for c in summary['cases'])
    assert mi['between_seeds']['seeds'] == 2 and len(mi['ci95']) == 2
    assert (tmp_path / 'runs.csv').read_text().count('\n') == 5
    assert 'between_low' in (tmp_path / 'intervals.csv').read_text().splitlines()[0]


def test_campaign_interrupted_by_ctrl_c_resumes_without_recomputing(tmp_path, sequential):
    """Ctrl-C (SIGINT to the whole process group, as a terminal sends it) while the
    embedded cluster runs: exit 130, the finished cases kept whole; the same campaign run
    again computes only the others. One worker: the cases run one after the other, so the
    signal sent when the first is written finds the next one running (with two workers
    the last cases could all finish before it arrived, and the run exited 0)."""
    _, seq = sequential
    cases = tmp_path / 'cases'
    cmd = [sys.executable, '-m', 'gnsscam_ros.evaluation', 'campaign', '--seeds', '1-2',
           '--faults', '0', '4', '--bias-m', '200', '--methods', 'gnss_robust',
           '--n-particles', '200', '--duration-s', '15', '--workers', '1', '--quiet',
           '--out', str(tmp_path)]
    # SIGINT as a terminal's process has it, whatever the test runner inherited (a runner
    # started in the background of a non-interactive shell ignores it, and so would the
    # campaign).
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        deadline = time.monotonic() + 180
        while not list(cases.glob('*.json')) and time.monotonic() < deadline:
            assert proc.poll() is None, proc.communicate()
            time.sleep(0.1)
        os.killpg(proc.pid, signal.SIGINT)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 130, err
    assert 'interrupted' in err and 'resumes' in err
    done = sorted(p.stem for p in cases.glob('*.json'))
    assert 1 <= len(done) < 4
    assert not [p for p in cases.iterdir() if p.name.startswith('.')]   # no partial file
    stamps = {p.name: p.stat().st_mtime_ns for p in cases.iterdir()}
    computed = []
    out = run_campaign(base=base(), out_dir=tmp_path, sequential=True,
                       on_case=lambda key, m: computed.append(key.tag), **GRID)
    assert out['resumed'] == len(done) and out['computed'] == 4 - len(done)
    assert not set(computed) & set(done)                       # nothing recomputed
    assert all((cases / name).stat().st_mtime_ns == ns for name, ns in stamps.items())
    assert results(out) == results(seq)
    # Another configuration is refused in the same folder, not mixed in.
    with pytest.raises(CampaignStoreError, match='another campaign configuration'):
        run_campaign(base=campaign_config(n_particles=300), out_dir=tmp_path,
                     sequential=True, **GRID)


def _kill_a_worker_mid_case(probe, killed: dict, stop: threading.Event):
    """SIGKILL the process of the first worker seen executing a case."""
    def executing(dask_worker):
        return [str(ts.key) for ts in dask_worker.state.executing]

    while not stop.is_set():
        for address, keys in probe.run(executing).items():
            if any(k.startswith('case-') for k in keys):
                pid = probe.run(os.getpid, workers=[address])[address]
                os.kill(pid, signal.SIGKILL)
                killed.update(address=address, pid=pid, keys=keys)
                return
        time.sleep(0.05)


def test_a_worker_killed_mid_case_costs_a_retry_not_the_campaign(tmp_path, sequential):
    from distributed import Client, LocalCluster
    _, seq = sequential
    killed: dict = {}
    stop = threading.Event()
    with dask.config.set(FAST_MALLOC), \
            LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                         dashboard_address=None, silence_logs=50) as cluster, \
            Client(cluster) as probe:
        killer = threading.Thread(target=_kill_a_worker_mid_case,
                                  args=(probe, killed, stop), daemon=True)
        killer.start()
        try:
            out = run_campaign(base=base(), out_dir=tmp_path,
                               scheduler=cluster.scheduler_address, **GRID)
        finally:
            stop.set()
            killer.join(timeout=10)
    assert killed, 'no worker was seen executing a case'
    with pytest.raises(ProcessLookupError):
        os.kill(killed['pid'], 0)                          # it did die
    assert not out['failed'] and len(out['cases']) == 4
    assert results(out) == results(seq)
    victim = next(c for c in out['cases']
                  if f"case-{CaseKey(c['seed'], c['faults'], c['bias_m'], c['method']).tag}"
                  in killed['keys'][0])
    assert victim['worker'] != killed['address']           # retried elsewhere


def _start(cmd, log: Path, env: dict) -> subprocess.Popen:
    return subprocess.Popen(cmd, stdout=log.open('w'), stderr=subprocess.STDOUT, env=env)


def test_campaign_on_a_separately_started_scheduler_and_two_workers(tmp_path):
    """``dask scheduler`` and two ``dask worker`` processes, each worker with a cache of its
    own (no shared disk): the fused cases need the seed's camera matches, made once on
    one worker and shipped."""
    from distributed import Client
    dask_cli = str(Path(sys.executable).with_name('dask'))
    env = dict(os.environ, OPENBLAS_NUM_THREADS='1', PYTHONUNBUFFERED='1')
    scheduler_file = tmp_path / 'scheduler.json'
    procs = [_start([dask_cli, 'scheduler', '--host', '127.0.0.1', '--port', '0',
                     '--no-dashboard', '--scheduler-file', str(scheduler_file)],
                    tmp_path / 'scheduler.log', env)]
    try:
        deadline = time.monotonic() + 60
        while not scheduler_file.exists() and time.monotonic() < deadline:
            assert procs[0].poll() is None, (tmp_path / 'scheduler.log').read_text()
            time.sleep(0.1)
        address = json.loads(scheduler_file.read_text())['address']
        assert address.startswith('tcp://127.0.0.1:')
        for name in ('w1', 'w2'):
            worker_env = dict(env, GNSSCAM_CACHE_DIR=str(tmp_path / f'cache_{name}'))
            procs.append(_start([dask_cli, 'worker', address, '--name', name, '--nthreads',
                                 '1', '--no-dashboard', '--local-directory',
                                 str(tmp_path / name)], tmp_path / f'{name}.log', worker_env))
        with Client(address, timeout=30) as probe:
            probe.wait_for_workers(2, timeout=60)
        out = run_campaign(base=base(), seeds=(1,), cases=[(0, 0.0), (4, 200.0)],
                           methods=('fused',), duration_s=10.0,
                           out_dir=tmp_path / 'out', scheduler=address, progress=False)
    finally:
        for proc in reversed(procs):
            stop_child(proc, timeout_s=20)
    assert not out['failed'] and len(out['cases']) == 2
    summary = json.loads((tmp_path / 'out' / 'campaign.json').read_text())
    assert summary['cluster']['kind'] == 'scheduler'
    assert summary['cluster']['scheduler'] == address
    assert summary['cluster']['workers'] == 2
    assert all(c['camera']['epochs_with_camera'] > 0 for c in summary['cases'])
    made = [p for name in ('w1', 'w2')
            for p in (tmp_path / f'cache_{name}').glob('camera_matches_*.npz')]
    assert len(made) == 1                          # made once, on one worker's own disk
    assert not list((tmp_path / 'out').glob('cache*'))   # nothing written beside the out


def test_cli_seed_ranges_summary_and_exit_codes(tmp_path, capsys):
    out = tmp_path / 'out'
    args = ['campaign', '--seeds', '1', '--faults', '0', '--methods', 'gnss_robust',
            '--n-particles', '200', '--duration-s', '12', '--sequential', '--quiet',
            '--out', str(out)]
    assert eval_main(args + ['--json', str(tmp_path / 'c.json')]) == 0
    text = capsys.readouterr().out
    assert 'Clopper-Pearson' in text and '1 runs computed, 0 resumed' in text
    summary = json.loads((tmp_path / 'c.json').read_text())
    assert summary['campaign']['seeds'] == '1'
    assert eval_main(args) == 0                               # resumed, nothing to do
    assert '0 runs computed, 1 resumed' in capsys.readouterr().out
    assert eval_main(args[:-2] + ['--n-particles', '300', '--out', str(out)]) == 4
    assert 'another campaign configuration' in capsys.readouterr().err
    assert eval_main(['campaign', '--seeds', '3-1', '--out', str(out)]) == 2
    assert eval_main(['campaign', '--sequential', '--scheduler', 'tcp://127.0.0.1:1']) == 2


MALLOC_PROBE = """
import resource, sys
import numpy as np
from gnsscam_ros.evaluation.campaign_cluster import tune_malloc
def faults():
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(200):
        np.ones(2 ** 17).sum()                 # a 1 MiB temporary, as the filter makes
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before
faults()
untuned = faults()
tuned = tune_malloc()
print(untuned, faults(), tuned)
"""


def test_workers_undo_the_nannies_malloc_trim_threshold():
    env = dict(os.environ, MALLOC_TRIM_THRESHOLD_='65536')
    out = subprocess.run([sys.executable, '-c', MALLOC_PROBE], env=env, capture_output=True,
                         text=True, check=True).stdout.split()
    untuned, tuned_faults, tuned = int(out[0]), int(out[1]), out[2] == 'True'
    if not tuned:
        pytest.skip('not glibc: no mallopt to undo the variable with')
    assert untuned > 200 * 100                     # every temporary mapped afresh
    assert tuned_faults < untuned / 20
