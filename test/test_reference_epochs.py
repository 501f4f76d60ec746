"""Behaviour unchanged: the estimates, protection levels and verdicts of two short drives
are those recorded in test/data/reference_epochs.npz (by tools/record_reference.py).

The reference holds every GNSS epoch of the smartLoc excerpt (284 epochs at 5 Hz) and of
120 s of the emulated drive (121 epochs) with a 30 m alert limit, so that it holds both OK
and ERROR verdicts: what fusion_node publishes (status, estimate, covariance, heading,
protection level, risk bounds, integrity level) and what the evaluation records of the
same run (its verdicts and the reference risk of the M posteriors at the truth).

Verdicts, statuses and stamps must be equal. Floats are compared with a relative
tolerance of 1e-9 (absolute 1e-9 in their unit): the same code on the same platform
reproduces them bit for bit (checked: two runs, and numba with one thread against the
default), so the tolerance only absorbs a last-bit difference of another CPU's summation
order; a change of the algorithm or of its plumbing moves them by many orders more (1e-9
of a 20 m protection level is 20 nm).

The last bits depend on the numeric libraries and on the CPU numba compiles for, and a
particle filter turns a last-bit difference into another resampling pick: the reference
holds where it was recorded (its environment is stored with it: the default, newest tier,
and the host CPU). On another tier (Debian's or Ubuntu's numpy and numba) or another CPU
the comparison does not apply and says so; there the other tests of the suite check the
behaviour.

When the algorithm changes these outputs on purpose, regenerate the reference (the command
is in every failure message) and commit it with the change that explains it.
"""
import importlib.util
from pathlib import Path

import numpy as np
import pytest

TOOL = Path(__file__).resolve().parent.parent / 'tools' / 'record_reference.py'
_spec = importlib.util.spec_from_file_location('record_reference', TOOL)
record_reference = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(record_reference)

RTOL = ATOL = 1e-9
#: Arrays compared exactly (strings, integers, booleans).
EXACT_KINDS = 'USbiu'


def _stored(name: str) -> dict[str, np.ndarray]:
    with np.load(record_reference.REFERENCE) as stored:
        prefix = f'{name}/'
        return {k[len(prefix):]: stored[k] for k in stored.files if k.startswith(prefix)}


def _advice() -> str:
    return (f'differs from {record_reference.REFERENCE.name}: if the change is intended, '
            f'regenerate it with `{record_reference.COMMAND}` and commit it')


def test_reference_holds_both_verdict_levels():
    """A reference of ERROR verdicts alone would not see a changed OK rule."""
    for name in record_reference.DRIVES:
        levels = set(_stored(name)['level'].tolist())
        assert {'OK', 'ERROR'} <= levels, (name, levels)


@pytest.mark.slow
@pytest.mark.parametrize('name', record_reference.DRIVES)
def test_outputs_equal_the_reference(name):
    with np.load(record_reference.REFERENCE) as stored:
        recorded = str(stored[record_reference.ENVIRONMENT_KEY])
    here = record_reference.numeric_environment()
    if recorded != here:
        pytest.skip(f'reference recorded with {recorded}; this environment has {here}: '
                    'bit-level equality does not carry across numeric libraries')
    expected = _stored(name)
    actual = record_reference.record_drive(name)
    assert sorted(actual) == sorted(expected), f'{name}: recorded arrays {_advice()}'
    for key, want in expected.items():
        got = actual[key]
        assert got.shape == want.shape, f'{name}/{key}: shape {got.shape} {_advice()}'
        if want.dtype.kind in EXACT_KINDS:
            bad = np.flatnonzero(np.asarray(got != want).reshape(len(want), -1).any(axis=1))
            assert bad.size == 0, (f'{name}/{key}: {bad.size} epochs differ (first at row '
                                   f'{bad[:1].tolist()}: {got[bad[:1]]} instead of '
                                   f'{want[bad[:1]]}) {_advice()}')
        else:
            np.testing.assert_allclose(got, want, rtol=RTOL, atol=ATOL, equal_nan=True,
                                       err_msg=f'{name}/{key} {_advice()}')
