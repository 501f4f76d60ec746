"""Checks of a database file before and after it is loaded (an untrusted file: bounded and
validated before use; see :mod:`.database`)."""
from __future__ import annotations

import math
import os
import stat
import zipfile

import numpy as np

from .errors import MapDatabaseError
from .positions import MAX_POSITION_M
from .vocab_tree import _MAX_LEAVES

#: Most bytes the members of a database file may declare in all (uncompressed); a database
#: of 2,000 images takes 17 MB.
MAX_DATABASE_BYTES = 2 * 1024 ** 3
#: The arrays a database file holds (FORMAT_VERSION 1); other members are never read.
DATABASE_KEYS = ('format', 'version', 'score_levels', 'filenames', 'n_features',
                 'pos_columns', 'pos_values', 'pos_enu_m', 'pos_llh', 'pos_origin_llh',
                 'orb_params', 'meta', 'tree_branching', 'tree_depth', 'tree_centres',
                 'tree_valid', 'inv_n_images', 'inv_idf', 'inv_indptr', 'inv_images',
                 'inv_weights')


def _check_npz(path: str) -> None:
    """Refuse a database file before allocating its arrays (see the module docstring).

    Reads only the zip directory and the ``.npy`` header of each known member.

    Raises:
        MapDatabaseError: Not a regular file, a missing member, an object array, sizes
            beyond :data:`MAX_DATABASE_BYTES`, or an array larger than its member.
        OSError, zipfile.BadZipFile, ValueError: Unreadable file or header (the caller
            names the file).
    """
    if not stat.S_ISREG(os.stat(path).st_mode):
        raise MapDatabaseError(f'{path}: not a regular file')
    with zipfile.ZipFile(path) as zf:
        infos = {i.filename: i for i in zf.infolist()}
        declared = sum(i.file_size for i in infos.values())
        if declared > MAX_DATABASE_BYTES:
            raise MapDatabaseError(f'{path}: its members declare {declared / 1e6:.0f} MB, more '
                                   f'than a map database may hold '
                                   f'({MAX_DATABASE_BYTES / 1e6:.0f} MB); not loaded')
        for key in DATABASE_KEYS:
            info = infos.get(key + '.npy')
            if info is None:
                raise MapDatabaseError(f'{path}: not a valid map database (no array {key!r})')
            with zf.open(info) as f:
                version = np.lib.format.read_magic(f)
                if version == (1, 0):
                    shape, _, dtype = np.lib.format.read_array_header_1_0(f)
                elif version == (2, 0):
                    shape, _, dtype = np.lib.format.read_array_header_2_0(f)
                else:
                    raise MapDatabaseError(f'{path}: array {key!r} has .npy format '
                                           f'{version}, not 1.0 or 2.0')
                header = f.tell()
            if dtype.hasobject:
                raise MapDatabaseError(f'{path}: array {key!r} holds Python objects')
            wanted = math.prod(shape) * dtype.itemsize
            if wanted > info.file_size - header:
                # numpy allocates the declared array before reading it: a few bytes that
                # declare terabytes would end in MemoryError.
                raise MapDatabaseError(f'{path}: array {key!r} declares {shape} {dtype} '
                                       f'({wanted / 1e6:.3g} MB) but its member holds '
                                       f'{(info.file_size - header) / 1e6:.3g} MB; not loaded')


def _check_arrays(a: dict) -> None:
    """Shapes, ranges and indices of a loaded database (ValueError naming the array)."""
    n = int(a['inv_n_images'])
    names = a['filenames']
    if names.ndim != 1 or names.shape[0] != n or n < 1:
        raise ValueError(f'{names.shape[0] if names.ndim == 1 else names.shape} file names '
                         f'for {n} images')
    _require(np.asarray(a['n_features']).shape == (n,) and np.all(a['n_features'] >= 0),
             'n_features')
    columns = a['pos_columns']
    values = a['pos_values']
    _require(columns.ndim == 1 and values.shape == (n, columns.shape[0]), 'pos_values shape')
    _require(values.dtype.kind == 'f' and np.all(np.isfinite(values)), 'pos_values finite')
    enu = a['pos_enu_m']
    _require(enu.shape == (n, 3) and enu.dtype.kind == 'f', 'pos_enu_m shape')
    if not np.all(np.abs(enu) <= MAX_POSITION_M):     # NaN fails too
        raise ValueError(f'pos_enu_m: positions not finite or beyond {MAX_POSITION_M:g} m')
    llh = a['pos_llh']
    if llh.size:
        _require(llh.shape == (n, 3) and llh.dtype.kind == 'f', 'pos_llh shape')
        _check_llh(llh, 'pos_llh')
    origin = a['pos_origin_llh']
    if origin.size:
        _require(origin.shape == (3,) and origin.dtype.kind == 'f', 'pos_origin_llh shape')
        _check_llh(origin.reshape(1, 3), 'pos_origin_llh')
    branching, depth = int(a['tree_branching']), int(a['tree_depth'])
    if not (2 <= branching <= 1024 and 1 <= depth <= 32
            and branching ** depth <= _MAX_LEAVES):
        raise ValueError(f'tree branching {branching} and depth {depth} out of range')
    idf, indptr = a['inv_idf'], a['inv_indptr']
    images, weights = a['inv_images'], a['inv_weights']
    _require(idf.ndim == 1 and np.all(np.isfinite(idf)) and np.all(idf >= 0), 'inv_idf')
    _require(indptr.ndim == 1 and indptr.dtype.kind in 'iu' and indptr.size == idf.size + 1
             and np.all(np.diff(indptr) >= 0), 'inv_indptr')
    _require(images.ndim == 1 and images.dtype.kind in 'iu'
             and (images.size == 0 or (images.min() >= 0 and images.max() < n)),
             'inv_images (image index out of range)')
    _require(weights.shape == images.shape and np.all(np.isfinite(weights))
             and np.all(weights >= 0), 'inv_weights')


def _check_llh(llh: np.ndarray, name: str) -> None:
    if not (np.all(np.abs(llh[:, 0]) <= 90) and np.all(np.abs(llh[:, 1]) <= 180)
            and np.all(np.abs(llh[:, 2]) <= MAX_POSITION_M)):
        raise ValueError(f'{name}: latitude, longitude or altitude out of range')


def _require(ok, what: str) -> None:
    if not ok:
        raise ValueError(f'{what} inconsistent')
