"""The ``./run`` bootstrap and its verification (``tools/check_bootstrap.py``), no network.

The bootstrap once wrote its stamp after a legacy ``setup.py develop`` had put the console
scripts into ``.venv/lib/gnsscam_ros`` (Debian's python3.11, pip 23.0.1: ``setup.cfg
[develop] script_dir``), so ``./run gnsscam_eval`` failed with exit 127 for good. The
check must find exactly that, and the run script must check before it writes the stamp.
"""
import importlib.metadata
import importlib.util
import os
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
RUN = (ROOT / 'run').read_text(encoding='utf-8')


def _checker():
    spec = importlib.util.spec_from_file_location('check_bootstrap',
                                                  ROOT / 'tools' / 'check_bootstrap.py')
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


cb = _checker()


def test_console_scripts_are_read_from_setup_py():
    names = cb.console_scripts(ROOT / 'setup.py')
    assert 'gnsscam_eval' in names and 'pipeline_node' in names
    assert len(names) == len(set(names)) >= 11
    # The same list the installed distribution declares.
    installed = {e.name for e in importlib.metadata.distribution('gnsscam_ros').entry_points
                 if e.group == 'console_scripts'}
    assert set(names) == installed


def test_console_scripts_errors(tmp_path):
    bad = tmp_path / 'setup.py'
    bad.write_text("from setuptools import setup\nsetup(name='x')\n")
    with pytest.raises(cb.SetupError, match='no entry_points'):
        cb.console_scripts(bad)
    bad.write_text("setup(entry_points={'console_scripts': ['noname']})\n")
    with pytest.raises(cb.SetupError, match='no name'):
        cb.console_scripts(bad)
    assert cb.check(tmp_path / 'missing', tmp_path) == [
        f'cannot read the console scripts: [Errno 2] No such file or directory: '
        f"'{tmp_path / 'missing' / 'setup.py'}'"]


def test_scripts_off_path_are_reported(tmp_path):
    """The Debian failure: the scripts exist, but in lib/gnsscam_ros, not in bin."""
    venv = tmp_path / 'venv'
    (venv / 'bin').mkdir(parents=True)
    (venv / 'lib' / 'gnsscam_ros').mkdir(parents=True)
    names = ['gnsscam_eval', 'gnss_node', 'imu_node']
    for name in names:
        script = venv / 'lib' / 'gnsscam_ros' / name
        script.write_text('#!/bin/sh\n')
        script.chmod(0o755)
    assert cb.missing_scripts(names, venv / 'bin') == [
        f'console script {n} is not in {venv / "bin"}' for n in names]
    # In bin, but one not executable.
    for name in names:
        (venv / 'bin' / name).write_text('#!/bin/sh\n')
        (venv / 'bin' / name).chmod(0o755)
    (venv / 'bin' / 'imu_node').chmod(0o644)
    problems = cb.missing_scripts(names, venv / 'bin')
    if os.geteuid() != 0:                        # root may execute anything
        assert problems == [f'console script {venv / "bin" / "imu_node"} is not executable']


def test_imports_from_elsewhere_are_reported(tmp_path):
    assert cb.import_problems(ROOT, modules=('json',), from_root=()) == []
    problems = cb.import_problems(tmp_path, modules=('json', 'no_such_module_xyz'),
                                  from_root=('json',))
    assert len(problems) == 2
    assert 'json is imported from' in problems[0] and str(tmp_path) in problems[0]
    assert problems[1].startswith('import no_such_module_xyz failed: ModuleNotFoundError')


def _tier_of_this_environment() -> str | None:
    """'' in the project .venv, the tier's name in .venv-<tier>, None elsewhere."""
    for tier in ('', 'debian-bookworm', 'ubuntu-noble'):
        venv = ROOT / ('.venv' + (f'-{tier}' if tier else ''))
        if Path(sys.prefix).resolve() == venv.resolve():
            return tier
    return None


@pytest.mark.skipif(_tier_of_this_environment() is None,
                    reason='runs inside the project .venv or a tier .venv-<tier> only')
def test_this_environment_passes_the_check():
    tier = _tier_of_this_environment()
    args = [] if not tier else ['--constraints', str(ROOT / 'constraints' / f'{tier}.txt')]
    if tier == 'ubuntu-noble':
        args.append('--no-rclpy')
    assert cb.check(ROOT, sys.prefix, constraints=(args[1] if args else None),
                    ros=tier != 'ubuntu-noble') == []
    assert cb.main([str(ROOT), sys.prefix] + args) == 0
    assert cb.main([]) == 2


def test_run_verifies_before_it_writes_the_stamp():
    body = RUN[RUN.index('bootstrap() {'):RUN.index('\n}\n', RUN.index('bootstrap() {'))]
    check = body.index('tools/check_bootstrap.py')
    stamp = body.index('echo "$want" > "$stamp"')
    assert check < stamp
    assert 'exit 1' in body[check:stamp]                   # fails loudly, no stamp
    assert body.index('rm -f "$stamp"') < body.index('pip install')
    # An editable install that ignores setup.cfg's [develop] script_dir, with a pip and
    # setuptools that can build it, whatever the interpreter brought.
    assert '--use-pep517' in body and 'setup.py develop' not in body.replace(
        '`setup.py develop`', '')
    assert "'setuptools>=70.1,<80'" in body and "'pip>=23.1" in body
    # The stamp covers the bootstrap itself, so a fixed bootstrap repairs old venvs.
    assert 'declare -f pick_python find_python312 tier_python bootstrap' in body
    assert 'check_bootstrap.py' in body and 'constraints/*.txt' in body


def test_setup_cfg_keeps_the_ament_layout():
    """colcon and `ros2 run` need the scripts in lib/<package> (ros2/examples)."""
    text = (ROOT / 'setup.cfg').read_text(encoding='utf-8')
    assert 'script_dir=$base/lib/gnsscam_ros' in text
    assert 'install_scripts=$base/lib/gnsscam_ros' in text


def _dispatch(tmp_path, *args: str):
    """The run script's job dispatch (its usage function and case statement, as written
    there) run by bash for ``./run ARGS``, with the environment's set-up left out: the
    jobs themselves are stand-ins on PATH that print their name."""
    import subprocess
    body = RUN[RUN.index('usage() {'):RUN.index('esac', RUN.index('case "$job" in')) + 4]
    bin_dir = tmp_path / 'bin'
    bin_dir.mkdir(exist_ok=True)
    for name in ('python', 'flake8', 'gnsscam_bench', 'gnsscam_eval'):
        stub = bin_dir / name
        stub.write_text(f'#!/bin/sh\necho "{name} $*"\n')
        stub.chmod(0o755)
    harness = f'set -euo pipefail\nROOT=/x SHARED=/s CALLER_DIR="$PWD"\n{body}\n'
    env = {'PATH': f'{bin_dir}:/usr/bin:/bin', 'HOME': str(tmp_path)}
    return subprocess.run(['bash', '-c', harness, 'run', *args], env=env, cwd=tmp_path,
                          capture_output=True, text=True, timeout=30)


@pytest.mark.parametrize('args', [(), ('nonsense',), ('nonsense', '--flag')])
def test_run_without_a_job_or_with_an_unknown_one_prints_the_usage_and_exits_2(
        tmp_path, args):
    """``./run`` alone started the whole demo; ``./run nonsense`` said
    ``./run: line 114: exec: nonsense: not found``."""
    result = _dispatch(tmp_path, *args)
    assert result.returncode == 2, (result.stdout, result.stderr)
    assert result.stdout == ''
    assert result.stderr.count('usage: ./run JOB') == 1
    assert './run demo' in result.stderr and './run COMMAND' in result.stderr
    if args:
        assert result.stderr.splitlines()[0] == (
            './run: nonsense: neither a job nor a command of the environment')


def test_run_jobs_and_installed_commands_still_dispatch(tmp_path):
    demo = _dispatch(tmp_path, 'demo', '--keep-bags')
    assert demo.returncode == 0 and demo.stdout.split() == [
        'python', '-m', 'gnsscam_ros.evaluation.demo', '--shared', '/s', '--out', '/x/out',
        '--keep-bags']
    assert _dispatch(tmp_path, 'gnsscam_eval', '--help').stdout == 'gnsscam_eval --help\n'
    assert _dispatch(tmp_path, 'bench').stdout == 'gnsscam_bench \n'
    helped = _dispatch(tmp_path, '--help')
    assert helped.returncode == 0 and 'usage: ./run JOB' in helped.stdout
