"""Ctrl-C in the evaluation commands: numba's dispatcher turns a KeyboardInterrupt raised
while a kernel runs into a SystemError caused by it; the commands stop with 130 all the
same, and any other SystemError is a defect that propagates."""
import pytest

from gnsscam_ros.evaluation import cli, interrupts


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
