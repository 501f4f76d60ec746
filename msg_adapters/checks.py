"""Checks of decoded values against the limits of :mod:`.limits`, with the reasons the
nodes count (``'size'``, ``'non_finite'``, ``'range'``)."""
from __future__ import annotations

import numpy as np

from .errors import MessageError
from .limits import MAX_MESSAGE_BYTES


def check_count(n: int, limit: int, what: str, noun: str) -> None:
    """Refuse more than ``limit`` items (reason ``'size'``); called with the count from the
    header fields, before the items are decoded."""
    if n > limit:
        raise MessageError(f'{what}: {n} {noun}, at most {limit} accepted', 'size')


def check_finite(what: str, **values) -> None:
    """Refuse NaN or infinity in any of ``values`` (name -> number or array; reason
    ``'non_finite'``)."""
    for name, value in values.items():
        if not np.isfinite(value).all():
            raise MessageError(f'{what}: non-finite {name}', 'non_finite')


def check_range(what: str, name: str, value, low: float, high: float, unit: str = '',
                allow_nan: bool = False) -> None:
    """Refuse a value (or any element of an array) outside ``[low, high]`` (reason
    ``'range'``; NaN: ``'non_finite'`` unless ``allow_nan``, infinity always)."""
    # Every message passes here several times: one comparison decides for valid data
    # (NaN and infinity fail it too); only a refusal, or an allowed NaN, looks closer.
    if isinstance(value, (float, int)):
        if low <= value <= high:
            return
        array = np.array([value], dtype=float)
    else:
        array = np.asarray(value, dtype=float)
        if (array >= low).all() and (array <= high).all():     # NaN: False, no warning
            return
    nan = np.isnan(array)
    if (nan.any() and not allow_nan) or np.isinf(array).any():
        raise MessageError(f'{what}: non-finite {name}', 'non_finite')
    bad = ~nan & ((array < low) | (array > high))
    if bad.any():
        worst = float(array[bad].flat[0])
        raise MessageError(f'{what}: {name} {worst:.6g}{unit} outside the plausible '
                           f'[{low:.6g}, {high:.6g}]{unit}', 'range')


def check_abs(what: str, name: str, value, limit: float, unit: str = '') -> None:
    """Refuse non-finite values or ``|value| > limit`` (see :func:`check_range`)."""
    check_range(what, name, value, -limit, limit, unit)


def check_serialized_size(raw: bytes, what: str, limit: int = MAX_MESSAGE_BYTES) -> None:
    """Refuse a serialised message of more than ``limit`` bytes before it is decoded
    (reason ``'size'``; default: a message without arrays,
    :data:`.limits.MAX_MESSAGE_BYTES`)."""
    if len(raw) > limit:
        raise MessageError(f'{what}: {len(raw)} bytes, at most {limit}', 'size')
