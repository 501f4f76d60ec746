"""README code blocks run as printed (conventions: the suite extracts and executes them).

* every ```python block is saved as a file and started the way the README says
  (``./run python FILE``: this interpreter, a fresh ROS domain). The ``/integrity_risk``
  consumer gets an OK and a STALE verdict published to it, must log both, and stops on
  Ctrl-C (SIGINT) with exit status 0 and no traceback; a block that is not a long-running
  node must finish by itself with status 0;
* every ``./run <job>`` and every executable named in a ```bash block exists (a job of
  ``run`` or a console script of setup.py) and its ``--help`` exits 0.
"""
import ast
import os
import re
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from ros_harness import RosGraph, ros_env, stop
from diagnostic_msgs.msg import DiagnosticArray

from gnsscam_ros.core.verdict import OK, STALE, IntegrityVerdict
from msg_adapters import integrity_risk_to_msg

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / 'README.md').read_text(encoding='utf-8')
BLOCK = re.compile(r'^```(\w+)\n(.*?)^```', re.S | re.M)


def blocks(language: str) -> list[str]:
    return [body for lang, body in BLOCK.findall(README) if lang == language]


def console_scripts() -> set[str]:
    tree = ast.parse((ROOT / 'setup.py').read_text(encoding='utf-8'))
    for node in ast.walk(tree):
        if isinstance(node, ast.keyword) and node.arg == 'entry_points':
            entries = ast.literal_eval(node.value)['console_scripts']
            return {e.split('=')[0].strip() for e in entries}
    raise AssertionError('setup.py declares no console_scripts')


def run_jobs() -> set[str]:
    """The named jobs of the ``run`` script's case statement."""
    text = (ROOT / 'run').read_text(encoding='utf-8')
    start = text.index('case "$job" in')
    case = text[start:text.index('esac', start)]
    return {job for pattern in re.findall(r'^\s+([\w|-]+)\)\s*$', case, re.M)
            for job in pattern.split('|')}


def named_executables() -> tuple[set[str], set[str]]:
    """``(./run jobs or commands, ros2 run executables)`` named in the bash blocks."""
    run_cmds, ros2_run = set(), set()
    for body in blocks('bash'):
        for line in body.replace('\\\n', ' ').splitlines():
            code = line.split('#', 1)[0]
            run_cmds |= set(re.findall(r'\./run\s+([\w.-]+)', code))
            ros2_run |= set(re.findall(r'ros2 run gnsscam_ros\s+([\w.-]+)', code))
    return run_cmds, ros2_run


def script(name: str) -> str:
    found = shutil.which(name, path=os.pathsep.join(
        [str(Path(sys.executable).parent), os.environ.get('PATH', '')]))
    assert found, f'{name} is not on PATH (bootstrap)'
    return found


# ===================================================================== bash blocks
def test_every_command_named_in_bash_blocks_exists():
    run_cmds, ros2_run = named_executables()
    scripts, jobs = console_scripts(), run_jobs()
    assert {'demo', 'test', 'bench'} <= jobs
    assert run_cmds and ros2_run, 'no ./run or ros2 run commands found in the README'
    unknown = sorted((run_cmds - jobs - scripts - {'python'}) | (ros2_run - scripts))
    assert not unknown, f'README names commands that do not exist: {unknown}'


@pytest.mark.slow
def test_help_of_every_console_script_named_in_bash_blocks():
    run_cmds, ros2_run = named_executables()
    scripts = console_scripts()
    named = sorted(((run_cmds | ros2_run) & scripts) | {'gnsscam_bench'})  # ./run bench
    assert len(named) >= 8, named
    env = dict(os.environ, ROS_LOG_DIR=os.environ.get('ROS_LOG_DIR', '/tmp/gnsscam_ros_log'))
    procs = {name: subprocess.Popen([script(name), '--help'], stdout=subprocess.PIPE,
                                    stderr=subprocess.PIPE, text=True, env=env)
             for name in named}
    failed = {}
    for name, proc in procs.items():
        try:
            out, err = proc.communicate(timeout=120)
        except subprocess.TimeoutExpired:
            proc.kill()
            out, err = proc.communicate()
            failed[name] = 'did not exit (--help started the program?)'
            continue
        if proc.returncode != 0 or 'usage' not in out.lower():
            failed[name] = f'exit {proc.returncode}: {err[-400:]}'
    assert not failed, failed


@pytest.mark.slow
def test_run_jobs_named_in_bash_blocks_have_help():
    """``./run demo`` is a job of the run script, not a console script: its module's
    ``--help`` must work too."""
    run_cmds, _ = named_executables()
    assert 'demo' in run_cmds
    result = subprocess.run([sys.executable, '-m', 'gnsscam_ros.evaluation.demo', '--help'],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0 and 'usage' in result.stdout.lower(), result.stderr


# =================================================================== python blocks
class _Reader:
    """Collects a child's output on a thread (the child logs to stderr)."""

    def __init__(self, stream):
        self.text = ''
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._read, args=(stream,), daemon=True)
        self._thread.start()

    def _read(self, stream):
        for line in stream:
            with self._lock:
                self.text += line

    def get(self) -> str:
        with self._lock:
            return self.text


def _verdicts():
    ok = IntegrityVerdict(stamp_ns=1_000_000_000, level=OK, message='integrity sufficient',
                          risk_bound=0.02, empirical_risk=0.01, divergence_risk=0.01,
                          alert_limit_m=8.0, target_risk=0.1, epoch_stamp_ns=1_000_000_000,
                          protection_level_m=6.5)
    stale = IntegrityVerdict(stamp_ns=2_000_000_000, level=STALE, message='no GNSS',
                             alert_limit_m=8.0, target_risk=0.1)
    return integrity_risk_to_msg(ok), integrity_risk_to_msg(stale)


def _run_consumer(path: Path, tmp_path: Path) -> tuple[int, str]:
    """Start the saved block, publish verdicts until it logged both, then Ctrl-C it."""
    graph = RosGraph()
    env = ros_env(tmp_path, graph.domain, base=dict(os.environ,
                                                    RCUTILS_LOGGING_BUFFERED_STREAM='0'))
    proc = subprocess.Popen([sys.executable, str(path)], cwd=tmp_path, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    out = _Reader(proc.stdout)
    pub = graph.probe.create_publisher(DiagnosticArray, 'integrity_risk', 10)
    ok, stale = _verdicts()

    last = [0.0]

    def logged_both() -> bool:
        assert proc.poll() is None, f'the example exited early:\n{out.get()}'
        if pub.get_subscription_count() > 0 and time.monotonic() - last[0] > 0.2:
            last[0] = time.monotonic()
            pub.publish(ok)
            pub.publish(stale)
        return ('position usable: protection level 6.5 m' in out.get()
                and 'STALE: no GNSS' in out.get())

    try:
        graph.spin_until(logged_both, 60.0, 'both verdicts logged by the example')
        rc = stop(proc)                             # Ctrl-C, as a user stops it
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        graph.close()
    return rc, out.get()


@pytest.mark.slow
def test_every_python_block_runs_as_printed(tmp_path):
    found = blocks('python')
    assert found, 'no python block in the README'
    consumers = 0
    for i, code in enumerate(found):
        path = tmp_path / f'readme_block_{i}.py'
        path.write_text(code, encoding='utf-8')
        if "'integrity_risk'" in code and 'rclpy.spin' in code:
            consumers += 1
            rc, out = _run_consumer(path, tmp_path)
            assert rc == 0, out
            assert 'Traceback' not in out, out
            assert 'position usable: protection level 6.5 m <= alert limit 8.0 m' in out, out
            assert 'STALE: no GNSS' in out, out
        else:
            result = subprocess.run([sys.executable, str(path)], cwd=tmp_path, timeout=300,
                                    capture_output=True, text=True)
            assert result.returncode == 0, (code, result.stderr)
    assert consumers == 1, 'the /integrity_risk consumer example is missing'


@pytest.mark.slow
def test_the_old_block_without_a_main_call_fails_this_test(tmp_path):
    """The README block once defined main() and never called it: started, it exited 0 at
    once having done nothing. The consumer check catches that."""
    code = next(c for c in blocks('python') if "'integrity_risk'" in c)
    old = code.replace("\n\nif __name__ == '__main__':\n    main()\n", '\n')
    assert old != code
    path = tmp_path / 'old_block.py'
    path.write_text(old, encoding='utf-8')
    with pytest.raises(AssertionError, match='exited early'):
        _run_consumer(path, tmp_path)
