"""Ctrl-C in the evaluation commands: numba's dispatcher turns a KeyboardInterrupt raised
while a kernel runs into a SystemError caused by it; the commands stop with 130 all the
same, and any other SystemError is a defect that propagates."""
import subprocess
import sys
from pathlib import Path

import pytest

from gnsscam_ros.core import interrupts as compile_interrupts
from gnsscam_ros.evaluation import cli, interrupts

ROOT = Path(__file__).resolve().parents[1]


def kernel_interrupt() -> SystemError:
    try:
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as ki:
            raise SystemError('returned a result with an exception set') from ki
    except SystemError as err:
        return err


def test_a_system_error_caused_by_ctrl_c_is_an_interrupt():
    assert interrupts.is_interrupt(KeyboardInterrupt())
    assert interrupts.is_interrupt(kernel_interrupt())
    assert not interrupts.is_interrupt(SystemError('other'))
    assert not interrupts.is_interrupt(ValueError('other'))


@pytest.mark.parametrize('raised', ['keyboard', 'kernel'])
def test_gnsscam_eval_stopped_in_the_filter_exits_130_and_writes_nothing(
        tmp_path, monkeypatch, capsys, raised):
    def interrupted(*args, **kwargs):
        if raised == 'keyboard':
            raise KeyboardInterrupt
        raise kernel_interrupt()
    monkeypatch.setattr(cli, 'evaluate_drive_record', interrupted)
    out = tmp_path / 'run.json'
    code = cli.main(['emulated', '--seed', '1', '--duration-s', '5', '--json', str(out)])
    assert code == interrupts.EXIT_INTERRUPTED == 130
    assert 'interrupted; nothing written' in capsys.readouterr().err
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_another_system_error_is_not_taken_for_an_interrupt(tmp_path, monkeypatch):
    def broken(*args, **kwargs):
        raise SystemError('a real defect')
    monkeypatch.setattr(cli, 'evaluate_drive_record', broken)
    with pytest.raises(SystemError, match='a real defect'):
        cli.main(['emulated', '--seed', '1', '--duration-s', '5'])


CTRL_C_WHILE_NUMBA_COMPILES = """
import ctypes, sys, time
from gnsscam_ros.evaluation import cli

def compiling(*args, **kwargs):
    # As llvmlite calls back into Python while numba compiles a kernel: Python cannot
    # raise out of a ctypes callback, so without the hook the Ctrl-C is printed and lost.
    ctypes.CFUNCTYPE(None)(lambda: (_ for _ in ()).throw(KeyboardInterrupt))()
    for _ in range(200):                    # the rest of the compilation
        time.sleep(0.01)
    print('the Ctrl-C was lost')
    sys.exit(0)

cli.evaluate_drive_record = compiling
print('exit', cli.main(['emulated', '--seed', '1', '--duration-s', '5', '--json', sys.argv[1]]))
"""


def test_gnsscam_eval_stopped_while_numba_compiles_exits_130_without_a_traceback(tmp_path):
    """A Ctrl-C that lands in one of llvmlite's ctypes callbacks stops the command as any
    other (core.interrupts) instead of being printed as ignored and dropped."""
    out = tmp_path / 'run.json'
    result = subprocess.run([sys.executable, '-c', CTRL_C_WHILE_NUMBA_COMPILES, str(out)],
                            cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert result.stdout.split() == ['exit', '130'], (result.stdout, result.stderr)
    assert 'interrupted; nothing written' in result.stderr, result.stderr
    assert 'Traceback' not in result.stderr and 'ignored' not in result.stderr, result.stderr
    assert not out.exists()


def test_the_redelivery_hook_is_removed_when_the_command_ends():
    before = sys.unraisablehook
    with compile_interrupts.interrupts_redelivered():
        assert sys.unraisablehook is not before
    assert sys.unraisablehook is before
