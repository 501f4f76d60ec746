"""The demo's run folder: Ctrl-C stops it with 130 and leaves it marked INCOMPLETE (it
printed "interrupted", ran on ~45 s, printed the truncated run as a result and exited 0);
a finished run removes its bags unless --keep-bags and says what it keeps."""
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from ros_harness import ros_domain_id, ros_env  # the demo runs nodes: skips without rclpy

from gnsscam_ros.evaluation import demo

ROOT = Path(__file__).resolve().parents[1]


def demo_command(out: Path, *extra: str) -> list:
    return [sys.executable, '-m', 'gnsscam_ros.evaluation.demo', '--out', str(out),
            '--no-camera', '--no-smartloc', '--n-particles', '200', *extra]


def test_ctrl_c_in_any_stage_exits_130_and_marks_the_folder_incomplete(tmp_path, monkeypatch,
                                                                       capsys):
    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt
    monkeypatch.setattr(demo, 'make_emulated_drive', interrupted)
    monkeypatch.setattr(demo, 'warm_up_kernels', lambda: 0.0)
    assert demo.main(['--out', str(tmp_path), '--no-smartloc']) == demo.EXIT_INTERRUPTED
    (run,) = tmp_path.iterdir()
    marker = (run / demo.INCOMPLETE).read_text()
    assert 'interrupted (Ctrl-C) during "emulated: generate the drive"' in marker
    assert not (run / 'summary.json').exists()
    assert 'is incomplete' in capsys.readouterr().err


def _as_from_a_terminal() -> None:
    """Ctrl-C's default action in the demo, as a terminal starts it: a test runner started
    in the background of a non-interactive shell (``nohup ./run test &``) ignores SIGINT,
    its children inherit that, and the demo never saw the Ctrl-C (it played on)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@pytest.mark.slow
@pytest.mark.ros
@pytest.mark.parametrize('delay_s', [1.0, 4.0])
def test_sigint_during_the_replay_stops_the_demo_with_130(tmp_path, delay_s):
    """Ctrl-C while the nodes start (the replay waited for them on, then for every
    acknowledgement) and while the bag plays: 120 s of bag time, some 9 s of replay stage on
    CI (nodes up in ~4 s, then ~24x real time). With 60 s and an 8 s delay the replay had
    ended, and the late Ctrl-C landed in the interpreter's exit (exit 0)."""
    out = tmp_path / 'out'
    err_path = tmp_path / 'demo.err'
    with open(err_path, 'w') as err:
        proc = subprocess.Popen(demo_command(out, '--duration-s', '120'), cwd=ROOT,
                                env=ros_env(tmp_path, ros_domain_id()), stdout=subprocess.PIPE,
                                stderr=err, text=True, start_new_session=True,
                                preexec_fn=_as_from_a_terminal)
        try:
            deadline = time.monotonic() + 300
            while 'replay through the nodes' not in err_path.read_text():
                assert proc.poll() is None and time.monotonic() < deadline, \
                    err_path.read_text()
                time.sleep(0.2)
            time.sleep(delay_s)
            assert proc.poll() is None, err_path.read_text()
            os.killpg(proc.pid, signal.SIGINT)          # Ctrl-C in a terminal
            sent = time.monotonic()
            stdout, _ = proc.communicate(timeout=90)    # a hang guard, not a measurement
            print(f'stopped {time.monotonic() - sent:.1f} s after SIGINT')
        finally:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
    text = err_path.read_text()
    assert proc.returncode == 130, text
    assert 'Results at alert limit' not in stdout and 'interrupted during' in text
    (run,) = out.iterdir()
    assert (run / demo.INCOMPLETE).is_file()
    assert not (run / 'summary.json').exists()
    assert not (run / 'emulated' / 'results.json').exists()
    assert not (run / 'emulated' / 'result_bag').exists()      # the partial recording


@pytest.mark.slow
@pytest.mark.ros
@pytest.mark.parametrize('keep', [False, True])
def test_a_finished_demo_removes_its_bags_unless_asked_to_keep_them(tmp_path, keep):
    out = tmp_path / 'out'
    args = ['--duration-s', '12', '--layout', 'threads'] + (['--keep-bags'] if keep else [])
    result = subprocess.run(demo_command(out, *args), cwd=ROOT, capture_output=True,
                            text=True, env=ros_env(tmp_path, ros_domain_id()), timeout=600)
    assert result.returncode == 0, result.stderr
    (run,) = out.iterdir()
    assert not (run / demo.INCOMPLETE).exists() and (run / 'summary.json').is_file()
    bags = [run / 'emulated' / 'dataset_bag', run / 'emulated' / 'result_bag']
    assert [b.is_dir() for b in bags] == [keep, keep]
    kept = [f for f in run.rglob('*') if f.is_file()]
    size_mb = sum(f.stat().st_size for f in kept) / 1e6
    line = next(ln for ln in result.stdout.splitlines() if ln.startswith('Outputs in'))
    assert f'{len(kept)} files, {size_mb:.0f} MB' in line
    assert ('--keep-bags' in line) and (('kept' in line) == keep)
    assert 'compile the filter kernels' in result.stderr
