"""Checks of decoded values against the limits of :mod:`.limits`, with the reasons the
nodes count (``'size'``, ``'non_finite'``, ``'range'``, ``'frame'``)."""
from __future__ import annotations

import numpy as np

from .errors import MessageError
from .limits import (COVARIANCE_TOLERANCE, MAX_MESSAGE_BYTES, MAX_VARIANCE,
                     QUATERNION_NORM_TOLERANCE)


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


def check_frame(what: str, frame_id: str, expected: str | None, field: str = 'frame') -> None:
    """Refuse a header frame other than ``expected`` (None: any; reason ``'frame'``)."""
    if expected is not None and frame_id != expected:
        raise MessageError(f'{what}: {field} {frame_id!r}, expected {expected!r}', 'frame')


def check_covariance(what: str, name: str, cov) -> None:
    """Refuse a covariance matrix (a flat row-major n x n array, as in ROS messages) that
    is none: a non-finite element (``'non_finite'``), a variance outside
    [0, :data:`.limits.MAX_VARIANCE`] or an off-diagonal element beyond
    ``sqrt(c_ii * c_jj)`` (``'range'``), each up to :data:`.limits.COVARIANCE_TOLERANCE`."""
    c = np.asarray(cov, dtype=float)
    n = int(round(np.sqrt(c.size)))
    c = c.reshape(n, n)
    if not np.isfinite(c).all():
        raise MessageError(f'{what}: non-finite {name}', 'non_finite')
    var = np.diagonal(c)
    tol = COVARIANCE_TOLERANCE
    if (var < -tol).any() or (var > MAX_VARIANCE).any():
        bad = var[(var < -tol) | (var > MAX_VARIANCE)][0]
        raise MessageError(f'{what}: {name}: variance {bad:.6g} outside [0, '
                           f'{MAX_VARIANCE:.6g}]', 'range')
    sd = np.sqrt(np.maximum(var, 0.0))
    bound = np.outer(sd, sd) + tol
    np.fill_diagonal(bound, np.inf)          # sqrt(v)^2 need not be v in floating point
    if (np.abs(c) > bound).any():
        i, j = np.argwhere(np.abs(c) > bound)[0]
        raise MessageError(f'{what}: {name}: element ({i}, {j}) = {c[i, j]:.6g} beyond '
                           f'sqrt(c_ii c_jj) = {sd[i] * sd[j]:.6g} (a correlation above 1)',
                           'range')


def check_unit_quaternion(what: str, name: str, x: float, y: float, z: float,
                          w: float) -> None:
    """Refuse a quaternion that is no rotation: non-finite (``'non_finite'``) or with
    ``|q|^2`` farther than :data:`.limits.QUATERNION_NORM_TOLERANCE` from 1 (``'range'``;
    a zero quaternion too)."""
    q = np.array([x, y, z, w], dtype=float)
    if not np.isfinite(q).all():
        raise MessageError(f'{what}: non-finite {name}', 'non_finite')
    with np.errstate(over='ignore'):
        norm2 = float(q @ q)
    if not abs(norm2 - 1.0) <= QUATERNION_NORM_TOLERANCE:
        raise MessageError(f'{what}: {name} of squared norm {norm2:.6g}, not a unit '
                           f'quaternion (tolerance {QUATERNION_NORM_TOLERANCE:g})', 'range')
