"""Geotagged image database: vocabulary-tree words, TF-IDF inverted files, top-k queries.

Scoring follows Nister & Stewenius, "Scalable Recognition with a Vocabulary Tree" (CVPR
2006). A word is a tree node (by default only leaves; ``score_levels`` > 1 adds the levels
above them). With ``n_i`` occurrences of word ``i`` in an image, ``N`` database images and
``N_i`` of them containing word ``i``:

    w_i = ln(N / N_i)                      (IDF; 0 for words no database image contains)
    v_i = n_i w_i / sum_j n_j w_j          (L1-normalised TF-IDF vector, query q or image d)
    score(q, d) = 1 - ||q - d||_1 / 2 = sum_i min(q_i, d_i)   in [0, 1], 1 = same words

The last identity holds for non-negative L1-normalised vectors, so the score only needs the
words the query and the image share: it is accumulated from the inverted file (the list of
images and their ``d_i``) of each query word.

A database is stored as one uncompressed ``.npz`` (no pickled objects), written atomically.

**Untrusted files.** A database file, a positions CSV and the images it names may come from
anyone, so what is read is bounded and checked before use:

* :meth:`MapDatabase.load` reads the zip directory and every member's ``.npy`` header
  first and refuses, before allocating anything, a file whose members declare more than
  :data:`MAX_DATABASE_BYTES` in all, or an array larger than the bytes its member holds (a
  "zip bomb"); then it checks what it loaded (array shapes, word and image indices in
  range, finite weights, positions within :data:`MAX_POSITION_M` of the origin and valid
  latitudes/longitudes, ORB settings OpenCV accepts).
* :func:`read_positions_csv` skips rows whose position is not finite or out of range, and
  :meth:`MapDatabase.build_from_files` rows whose ``filename`` resolves outside the image
  folder (an absolute path, ``..``, or a symbolic link leading out) or lies more than
  :data:`MAX_POSITION_M` from the origin, by name with the reason.
"""
from __future__ import annotations

import csv
import json
import math
import os
import stat
import tempfile
import threading
import time
import zipfile
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np
from scipy import sparse

from ..core.frames import LocalFrame
from .errors import ImageError, MapDatabaseError, MapDatabaseOutputError
from .features import DESCRIPTOR_BYTES, OrbExtractor, OrbParams, load_gray
from .vocab_tree import _MAX_LEAVES, VocabularyTree

FORMAT_NAME = 'gnsscam_mapdb'
FORMAT_VERSION = 1

WGS84_COLUMNS = ('lat', 'lon', 'alt_m')          # degrees, degrees, metres (ellipsoidal)
LOCAL_COLUMNS = ('east_m', 'north_m', 'up_m')    # metres in the local ENU (map) frame

#: Largest coordinate of a database position [m]: local east/north/up and altitude, and
#: the ENU offset of a WGS84 position from the origin (a map spans a city, not the globe;
#: 1e300 would overflow the filter downstream).
MAX_POSITION_M = 1.0e7
#: Most bytes the members of a database file may declare in all (uncompressed); a database
#: of 2,000 images takes 17 MB.
MAX_DATABASE_BYTES = 2 * 1024 ** 3
#: Largest positions CSV read [bytes] (~50 bytes a row).
MAX_CSV_BYTES = 256 * 1024 ** 2
#: The arrays a database file holds (FORMAT_VERSION 1); other members are never read.
DATABASE_KEYS = ('format', 'version', 'score_levels', 'filenames', 'n_features',
                 'pos_columns', 'pos_values', 'pos_enu_m', 'pos_llh', 'pos_origin_llh',
                 'orb_params', 'meta', 'tree_branching', 'tree_depth', 'tree_centres',
                 'tree_valid', 'inv_n_images', 'inv_idf', 'inv_indptr', 'inv_images',
                 'inv_weights')

#: ``progress(stage, done, total)``; called from the building thread.
ProgressFn = Callable[[str, int, int], None]


# ================================================================== TF-IDF inverted files
class InvertedIndex:
    """TF-IDF weighted inverted files over ``n_words`` visual words and ``n_images`` images.

    Attributes:
        idf: (n_words,) float64 weights ``ln(N / N_i)`` (0 for unseen words).
        indptr: (n_words + 1,) int64; word ``i``'s entries are ``indptr[i]:indptr[i+1]``.
        images: (nnz,) int32 image indices of the entries.
        weights: (nnz,) float32 normalised image weights ``d_i`` of the entries.
    """

    def __init__(self, n_images: int, idf: np.ndarray, indptr: np.ndarray,
                 images: np.ndarray, weights: np.ndarray):
        self.n_images = int(n_images)
        self.idf = np.asarray(idf, dtype=np.float64)
        self.indptr = np.asarray(indptr, dtype=np.int64)
        self.images = np.asarray(images, dtype=np.int32)
        self.weights = np.asarray(weights, dtype=np.float32)
        if (self.indptr.shape != (self.idf.size + 1,) or self.indptr[0] != 0
                or self.indptr[-1] != self.images.size
                or self.images.shape != self.weights.shape):
            raise ValueError('inconsistent inverted-file arrays')

    @property
    def n_words(self) -> int:
        return int(self.idf.size)

    @classmethod
    def from_documents(cls, documents: Sequence[np.ndarray], n_words: int) -> 'InvertedIndex':
        """Build from the word ids of each database image.

        Args:
            documents: per image, an int array of word ids (one per feature and level;
                repeats are term frequencies).
            n_words: size of the vocabulary; ids must lie in [0, n_words).
        """
        n_images = len(documents)
        if n_images == 0:
            raise ValueError('an inverted index needs at least one image')
        lengths = np.array([np.size(d) for d in documents], dtype=np.int64)
        words = (np.concatenate([np.asarray(d, dtype=np.int64).ravel() for d in documents])
                 if lengths.sum() else np.zeros(0, np.int64))
        if words.size and (words.min() < 0 or words.max() >= n_words):
            raise ValueError(f'word ids must lie in [0, {n_words})')
        rows = np.repeat(np.arange(n_images), lengths)
        # Duplicate (image, word) pairs are summed: the term frequencies n_i.
        tf = sparse.csr_matrix((np.ones(words.size, np.float64), (rows, words)),
                               shape=(n_images, n_words))
        tf.sum_duplicates()
        df = np.bincount(tf.indices, minlength=n_words)
        with np.errstate(divide='ignore'):
            idf = np.where(df > 0, np.log(n_images / np.maximum(df, 1)), 0.0)
        tf.data *= idf[tf.indices]
        norms = np.asarray(tf.sum(axis=1)).ravel()
        row_of = np.repeat(np.arange(n_images), np.diff(tf.indptr))
        tf.data /= np.where(norms > 0, norms, 1.0)[row_of]
        tf.eliminate_zeros()          # words in every image (idf 0) can never add score
        inv = tf.tocsc()
        inv.sort_indices()
        return cls(n_images, idf, inv.indptr, inv.indices, inv.data)

    def query_vector(self, words: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Unique word ids of a query and their L1-normalised TF-IDF weights.

        Words with zero IDF (unseen in the database, or in every image) are dropped; an
        empty pair is returned when nothing is left.
        """
        uniq, counts = np.unique(np.asarray(words, dtype=np.int64), return_counts=True)
        q = counts * self.idf[uniq]
        keep = q > 0
        uniq, q = uniq[keep], q[keep]
        total = q.sum()
        return uniq, (q / total if total > 0 else q)

    def score(self, words: np.ndarray) -> np.ndarray:
        """(n_images,) similarity ``1 - ||q - d||_1 / 2`` of a query (its word ids)."""
        uniq, q = self.query_vector(words)
        if uniq.size == 0:
            return np.zeros(self.n_images)
        starts = self.indptr[uniq]
        lengths = self.indptr[uniq + 1] - starts
        total = int(lengths.sum())
        if total == 0:
            return np.zeros(self.n_images)
        # Concatenated entry ranges of all query words without a Python loop: position k of
        # word j maps to starts[j] + k.
        offsets = np.repeat(starts - (np.cumsum(lengths) - lengths), lengths)
        entries = offsets + np.arange(total)
        contrib = np.minimum(np.repeat(q, lengths), self.weights[entries])
        return np.bincount(self.images[entries], weights=contrib, minlength=self.n_images)

    def to_arrays(self) -> dict[str, np.ndarray]:
        return {'inv_n_images': np.int64(self.n_images), 'inv_idf': self.idf,
                'inv_indptr': self.indptr, 'inv_images': self.images,
                'inv_weights': self.weights}

    @classmethod
    def from_arrays(cls, arrays) -> 'InvertedIndex':
        return cls(int(arrays['inv_n_images']), arrays['inv_idf'], arrays['inv_indptr'],
                   arrays['inv_images'], arrays['inv_weights'])


# ======================================================================= positions
@dataclass(frozen=True)
class PositionTable:
    """Positions of the database images.

    Attributes:
        columns: Names of the position columns as in the CSV header, in CSV order
            (e.g. ``('lat', 'lon', 'alt_m')`` or ``('east_m', 'north_m')``).
        values: (N, C) float64 values of those columns, as given.
        enu_m: (N, 3) east, north, up [m] in the database's local frame (for WGS84 input:
            the frame at ``origin_llh``; for local input: the coordinates as given, up = 0
            when absent).
        llh: (N, 3) latitude [deg], longitude [deg], ellipsoidal altitude [m] (0 when
            absent), or None for a local-only database.
        origin_llh: Origin of ``enu_m`` for WGS84 input, else None.
    """

    columns: tuple[str, ...]
    values: np.ndarray
    enu_m: np.ndarray
    llh: np.ndarray | None = None
    origin_llh: tuple[float, float, float] | None = None

    def __len__(self) -> int:
        return int(self.enu_m.shape[0])

    def column_dict(self, i: int) -> dict[str, float]:
        """Position columns of image ``i`` as ``{name: value}``."""
        return {c: float(v) for c, v in zip(self.columns, self.values[i])}

    def subset(self, keep: np.ndarray) -> 'PositionTable':
        return PositionTable(self.columns, self.values[keep], self.enu_m[keep],
                             None if self.llh is None else self.llh[keep], self.origin_llh)

    @classmethod
    def from_columns(cls, columns: Sequence[str], values: np.ndarray,
                     origin_llh: tuple[float, float, float] | None = None
                     ) -> 'PositionTable':
        """Interpret position columns (names lower-cased: see module constants).

        Args:
            columns: Column names; must contain ``lat, lon`` or ``east_m, north_m``.
            values: (N, C) float values.
            origin_llh: Local frame origin for WGS84 input (default: the first row).

        Raises:
            ValueError: when neither column set is present or values are out of range.
        """
        columns = tuple(columns)
        values = np.asarray(values, dtype=np.float64).reshape(-1, len(columns))
        key = {c.strip().lower(): i for i, c in enumerate(columns)}

        def col(name, default=0.0):
            return values[:, key[name]] if name in key else np.full(len(values), default)

        llh = None
        if 'lat' in key and 'lon' in key:
            llh = np.stack([col('lat'), col('lon'), col('alt_m')], axis=1)
            if np.any(np.abs(llh[:, 0]) > 90) or np.any(np.abs(llh[:, 1]) > 180):
                raise ValueError('latitude must be in [-90, 90] and longitude in [-180, 180]')
        if 'east_m' in key and 'north_m' in key:
            # Local coordinates win for the ENU array when both sets are given: they are
            # the user's own map frame.
            enu = np.stack([col('east_m'), col('north_m'), col('up_m')], axis=1)
        elif llh is not None:
            if origin_llh is None and len(llh):
                origin_llh = tuple(float(v) for v in llh[0])
            enu = (LocalFrame(*origin_llh).geodetic_to_enu(llh[:, 0], llh[:, 1], llh[:, 2])
                   if len(llh) else np.zeros((0, 3)))
        else:
            raise ValueError(f'position columns must include lat,lon or east_m,north_m; '
                             f'got {list(columns)}')
        if llh is None:
            origin_llh = None
        return cls(columns, values, np.asarray(enu, dtype=np.float64).reshape(-1, 3), llh,
                   None if origin_llh is None else tuple(float(v) for v in origin_llh))


@dataclass(frozen=True)
class SkippedImage:
    """A CSV row or image left out of a build, and why."""

    filename: str
    reason: str
    line: int | None = None      # CSV line number (header = 1)

    def __str__(self) -> str:
        where = f' (line {self.line})' if self.line is not None else ''
        return f'{self.filename}{where}: {self.reason}'


@dataclass
class BuildReport:
    """What a build from files did."""

    n_rows: int = 0
    n_images: int = 0
    n_descriptors: int = 0
    skipped: list[SkippedImage] = field(default_factory=list)
    seconds: dict[str, float] = field(default_factory=dict)
    #: per database image, its descriptors (only with ``keep_descriptors=True``)
    descriptors: list[np.ndarray] | None = None

    @property
    def images_per_s(self) -> float:
        total = sum(self.seconds.values())
        return self.n_rows / total if total > 0 else float('nan')


def read_positions_csv(path: str | os.PathLike
                       ) -> tuple[list[tuple[int, str, list[float]]], tuple[str, ...],
                                  list[SkippedImage]]:
    """Read the positions CSV of a build.

    The header must have ``filename`` and ``lat,lon[,alt_m]`` and/or
    ``east_m,north_m[,up_m]`` (case-insensitive); other columns are ignored.

    Returns:
        (rows, position column names as in the header, skipped rows). Each row is
        (line number, filename, values of the position columns).

    Raises:
        MapDatabaseError: naming the file when it is missing, unreadable or lacks columns.
    """
    path = os.fspath(path)
    try:
        info = os.stat(path)
        if not stat.S_ISREG(info.st_mode):
            raise MapDatabaseError(f'{path}: positions CSV is not a regular file')
        if info.st_size > MAX_CSV_BYTES:
            raise MapDatabaseError(f'{path}: positions CSV of {info.st_size / 1e6:.0f} MB is '
                                   f'larger than {MAX_CSV_BYTES / 1e6:.0f} MB')
        with open(path, newline='', encoding='utf-8-sig') as f:
            reader = csv.reader(f)
            header = next(reader, None)
            if header is None:
                raise MapDatabaseError(f'{path}: empty positions CSV (no header)')
            lines = [(reader.line_num, r) for r in reader]
    except FileNotFoundError as err:
        raise MapDatabaseError(f'{path}: no such positions CSV') from err
    except UnicodeDecodeError as err:
        raise MapDatabaseError(f'{path}: cannot read positions CSV (not UTF-8 text: '
                               f'{err.reason})') from err
    except (OSError, csv.Error, ValueError) as err:
        raise MapDatabaseError(f'{path}: cannot read positions CSV ({err})') from err
    key = {h.strip().lower(): i for i, h in enumerate(header)}
    if 'filename' not in key:
        raise MapDatabaseError(f'{path}: positions CSV needs a "filename" column; header is '
                               f'{header}')
    wanted = [c for c in WGS84_COLUMNS + LOCAL_COLUMNS if c in key]
    if not ({'lat', 'lon'} <= set(wanted) or {'east_m', 'north_m'} <= set(wanted)):
        raise MapDatabaseError(f'{path}: positions CSV needs lat,lon[,alt_m] or '
                               f'east_m,north_m[,up_m] columns; header is {header}')
    idx = sorted(key[c] for c in wanted)          # CSV order
    names = tuple(header[i].strip() for i in idx)
    rows, skipped, seen = [], [], set()
    for line, r in lines:
        if not any(cell.strip() for cell in r):
            continue                               # blank line
        name = r[key['filename']].strip() if len(r) > key['filename'] else ''
        if not name:
            skipped.append(SkippedImage('<no filename>', 'empty filename', line))
            continue
        if name in seen:
            skipped.append(SkippedImage(name, 'duplicate row for this image', line))
            continue
        try:
            vals = [float(r[i]) for i in idx]
        except (IndexError, ValueError):
            skipped.append(SkippedImage(name, 'missing or non-numeric position value', line))
            continue
        if not all(math.isfinite(v) for v in vals):
            skipped.append(SkippedImage(name, 'non-finite position value', line))
            continue
        lowered = {c.lower(): v for c, v in zip(names, vals)}
        if abs(lowered.get('lat', 0.0)) > 90 or abs(lowered.get('lon', 0.0)) > 180:
            skipped.append(SkippedImage(name, 'latitude/longitude out of range', line))
            continue
        metres = [abs(v) for c, v in lowered.items() if c not in ('lat', 'lon')]
        if metres and max(metres) > MAX_POSITION_M:
            skipped.append(SkippedImage(name, f'position value out of range (|value| > '
                                              f'{MAX_POSITION_M:g} m)', line))
            continue
        seen.add(name)
        rows.append((line, name, vals))
    return rows, names, skipped


def _no_usable_image(positions_csv, report: BuildReport) -> MapDatabaseError:
    """The error of a build without a single usable row; ``.skipped`` says why each row
    was left out (the command line prints them)."""
    err = MapDatabaseError(f'{os.fspath(positions_csv)}: no usable image '
                           f'({len(report.skipped)} rows skipped)')
    err.skipped = list(report.skipped)
    return err


def _outside(images_dir: str, name: str) -> str | None:
    """Why the CSV file name ``name`` may not be read from ``images_dir``, or None.

    Refused: a NUL byte, and any name whose real path (symbolic links followed) is not
    inside the real path of ``images_dir`` (absolute names, ``..``, links leading out).
    """
    if '\x00' in name:
        return 'file name contains a NUL byte'
    try:
        root = os.path.realpath(images_dir)
        target = os.path.realpath(os.path.join(images_dir, name))
    except (OSError, ValueError) as err:
        return f'file name cannot be resolved ({err})'
    if os.path.commonpath([root, target]) != root or target == root:
        return f'resolves outside the image folder {images_dir} (to {target}); not read'
    return None


# ======================================================================== matches
@dataclass(frozen=True)
class Match:
    """One database image returned by a query.

    Attributes:
        index: Row of the image in the database.
        filename: Image file name as in the positions CSV.
        score: Similarity in [0, 1] (see module docstring); higher is better.
        position_enu_m: (3,) east, north, up [m] in the database frame.
        columns: Position columns as given in the CSV, ``{name: value}``.
    """

    index: int
    filename: str
    score: float
    position_enu_m: np.ndarray
    columns: dict[str, float]

    def to_json(self) -> dict:
        return {'filename': self.filename, 'score': self.score, **self.columns}


# ======================================================================= database
class MapDatabase:
    """Geotagged image database with vocabulary-tree retrieval.

    Querying is single-threaded and reuses one ORB detector: use one instance per thread.
    """

    def __init__(self, tree: VocabularyTree, index: InvertedIndex, filenames: Sequence[str],
                 positions: PositionTable, orb_params: OrbParams, score_levels: int = 1,
                 n_features: np.ndarray | None = None, meta: dict | None = None):
        if not 1 <= score_levels <= tree.depth:
            raise ValueError(f'score_levels must be in [1, {tree.depth}], got {score_levels}')
        if not len(filenames) == len(positions) == index.n_images:
            raise ValueError('filenames, positions and index disagree on the image count')
        self.tree = tree
        self.index = index
        self.filenames = list(filenames)
        self.positions = positions
        self.orb_params = orb_params
        self.score_levels = int(score_levels)
        self.n_features = (np.zeros(len(self.filenames), np.int32) if n_features is None
                           else np.asarray(n_features, dtype=np.int32))
        self.meta = dict(meta or {})
        offs = tree.level_offsets
        first = tree.depth - self.score_levels
        # Word id of (level l, node j) = j + offset of level l among the scored levels.
        self._word_offsets = offs[first:-1] - offs[first]
        self._n_words = int(offs[-1] - offs[first])
        if index.n_words != self._n_words:
            raise ValueError(f'index has {index.n_words} words, tree gives {self._n_words}')
        self._extractor: OrbExtractor | None = None

    # ------------------------------------------------------------------------ basics
    def __len__(self) -> int:
        return len(self.filenames)

    @property
    def n_words(self) -> int:
        return self._n_words

    def words(self, descriptors: np.ndarray) -> np.ndarray:
        """Word ids of descriptors (one per descriptor and scored level)."""
        if len(descriptors) == 0:
            return np.zeros(0, np.int64)
        path = self.tree.quantise_path(descriptors)[:, self.tree.depth - self.score_levels:]
        return (path + self._word_offsets).ravel()

    # ----------------------------------------------------------------------- building
    @classmethod
    def build(cls, descriptors: Sequence[np.ndarray], filenames: Sequence[str],
              positions: PositionTable, *, orb_params: OrbParams | None = None,
              branching: int = 10, depth: int = 5, score_levels: int = 1,
              iterations: int = 6, seed: int = 0,
              max_train_descriptors: int | None = 200_000,
              progress: ProgressFn | None = None) -> 'MapDatabase':
        """Train a tree on the descriptors and index every image.

        Args:
            descriptors: per image, (n_k, 32) uint8 ORB descriptors made with
                ``orb_params`` (images without descriptors are kept but never match).
            filenames: per image, its name (as in the CSV).
            positions: per image, its position.
            orb_params: the ORB settings used for the descriptors (stored for queries).
            branching: vocabulary tree branching factor B.
            depth: vocabulary tree depth L (B**L leaves).
            score_levels: how many of the deepest tree levels are scored words (1: leaves).
            iterations: k-majority iterations per tree level.
            seed: seed of the training subsample and k-means++ seeding.
            max_train_descriptors: training subsample size (None: all descriptors).
            progress: optional progress callback.
        """
        if len(descriptors) == 0:
            raise MapDatabaseError('no images to build a database from')
        counts = np.array([len(d) for d in descriptors], dtype=np.int64)
        if counts.sum() == 0:
            raise MapDatabaseError('no ORB features in any image')
        all_desc = np.concatenate([np.asarray(d, np.uint8).reshape(-1, DESCRIPTOR_BYTES)
                                   for d in descriptors])
        t0 = time.perf_counter()
        if progress:
            progress('train', 0, depth)
        tree = VocabularyTree.train(all_desc, branching=branching, depth=depth,
                                    iterations=iterations, seed=seed,
                                    max_descriptors=max_train_descriptors, progress=progress)
        t1 = time.perf_counter()
        offs = tree.level_offsets
        first = depth - score_levels
        path = tree.quantise_path(all_desc)[:, first:] + (offs[first:-1] - offs[first])
        docs = np.split(path.ravel(), np.cumsum(counts * score_levels)[:-1])
        index = InvertedIndex.from_documents(docs, int(offs[-1] - offs[first]))
        if progress:
            progress('index', len(docs), len(docs))
        meta = {'branching': branching, 'depth': depth, 'iterations': iterations,
                'seed': seed, 'max_train_descriptors': max_train_descriptors,
                'n_descriptors': int(counts.sum()), 'train_s': t1 - t0,
                'index_s': time.perf_counter() - t1}
        return cls(tree, index, filenames, positions, orb_params or OrbParams(),
                   score_levels, counts, meta)

    @classmethod
    def build_from_files(cls, images_dir: str | os.PathLike,
                         positions_csv: str | os.PathLike, *,
                         orb_params: OrbParams | None = None,
                         origin_llh: tuple[float, float, float] | None = None,
                         jobs: int | None = None, progress: ProgressFn | None = None,
                         keep_descriptors: bool = False, **build_kwargs
                         ) -> tuple['MapDatabase', BuildReport]:
        """Build from an image directory and a positions CSV (see :func:`read_positions_csv`).

        Rows whose image is missing, unreadable or featureless are skipped and listed in
        the report; only a missing/unreadable CSV, a missing directory or no usable image
        at all is an error.

        Args:
            images_dir: directory the CSV file names are relative to.
            positions_csv: the CSV.
            orb_params: ORB settings (default :class:`OrbParams`).
            origin_llh: local frame origin (lat [deg], lon [deg], alt [m]) for WGS84 input;
                default: the first accepted row.
            jobs: feature-extraction threads (default: CPU count).
            progress: optional progress callback.
            keep_descriptors: also return every image's descriptors in the report (for
                benchmarks against brute-force matching).
            **build_kwargs: passed to :meth:`build`.

        Raises:
            MapDatabaseError: as above, naming the file.
        """
        images_dir = os.fspath(images_dir)
        if not os.path.isdir(images_dir):
            raise MapDatabaseError(f'{images_dir}: no such image directory')
        report = BuildReport()
        t0 = time.perf_counter()
        rows, columns, report.skipped = read_positions_csv(positions_csv)
        report.n_rows = len(rows) + len(report.skipped)
        # A file name is the CSV author's, not a licence to read any file: one that
        # resolves outside the image folder is skipped unread.
        inside = []
        for row in rows:
            reason = _outside(images_dir, row[1])
            if reason is None:
                inside.append(row)
            else:
                report.skipped.append(SkippedImage(row[1], reason, row[0]))
        rows = inside
        orb_params = orb_params or OrbParams()
        local = threading.local()

        def extract(row):
            _, name, _ = row
            ext = getattr(local, 'extractor', None)
            if ext is None:
                ext = local.extractor = OrbExtractor(orb_params)
            path = os.path.join(images_dir, name)
            try:
                return ext.descriptors(load_gray(path)), None
            except ImageError as err:
                return None, str(err).removeprefix(path + ': ')

        descs, kept = [], []
        n_jobs = max(1, jobs or os.cpu_count() or 1)
        if progress:
            progress('features', 0, len(rows))
        with ThreadPoolExecutor(max_workers=n_jobs) as pool:
            for k, (row, (desc, err)) in enumerate(zip(rows, pool.map(extract, rows))):
                line, name, _ = row
                if err is None and len(desc) == 0:
                    err = 'no ORB features found'
                if err is not None:
                    report.skipped.append(SkippedImage(name, err, line))
                else:
                    descs.append(desc)
                    kept.append(row)
                if progress and ((k + 1) % 25 == 0 or k + 1 == len(rows)):
                    progress('features', k + 1, len(rows))
        report.seconds['features'] = time.perf_counter() - t0
        if not kept:
            report.skipped.sort(key=lambda s: (s.line is None, s.line or 0))
            raise _no_usable_image(positions_csv, report)
        try:
            positions = PositionTable.from_columns(
                columns, np.array([r[2] for r in kept]), origin_llh)
            # WGS84 rows far from the origin (another continent) give ENU offsets no map
            # of one area has: skipped by name like any other unusable row.
            far = ~np.all(np.abs(positions.enu_m) <= MAX_POSITION_M, axis=1)
            if far.any():
                for k in np.flatnonzero(far):
                    report.skipped.append(SkippedImage(
                        kept[k][1], f'more than {MAX_POSITION_M:g} m from the origin',
                        kept[k][0]))
                descs = [d for d, f in zip(descs, far) if not f]
                kept = [r for r, f in zip(kept, far) if not f]
                if not kept:
                    report.skipped.sort(key=lambda s: (s.line is None, s.line or 0))
                    raise _no_usable_image(positions_csv, report)
                positions = positions.subset(~far)
        except ValueError as err:
            raise MapDatabaseError(f'{positions_csv}: {err}') from err
        report.skipped.sort(key=lambda s: (s.line is None, s.line or 0))
        t1 = time.perf_counter()
        db = cls.build(descs, [r[1] for r in kept], positions, orb_params=orb_params,
                       progress=progress, **build_kwargs)
        report.seconds['build'] = time.perf_counter() - t1
        report.n_images = len(db)
        report.n_descriptors = int(db.n_features.sum())
        if keep_descriptors:
            report.descriptors = descs
        return db, report

    # ------------------------------------------------------------------------ queries
    def scores(self, descriptors: np.ndarray) -> np.ndarray:
        """(N,) similarity of every database image to a query's descriptors."""
        return self.index.score(self.words(descriptors))

    def query_descriptors(self, descriptors: np.ndarray, top_k: int = 5) -> list[Match]:
        """Top-k database images for (n, 32) uint8 ORB descriptors, best first.

        Images with score 0 (no shared informative word) are never returned, so the list
        is empty for a featureless query.
        """
        s = self.scores(descriptors)
        k = min(int(top_k), s.size)
        if k <= 0:
            return []
        cand = np.argpartition(-s, k - 1)[:k] if k < s.size else np.arange(s.size)
        # Best score first, ties by database order (deterministic).
        cand = cand[np.lexsort((cand, -s[cand]))]
        return [self._match(int(i), float(s[i])) for i in cand if s[i] > 0]

    def query(self, image: np.ndarray, top_k: int = 5, encoding: str = 'bgr8') -> list[Match]:
        """Top-k database images for a camera image, best first.

        Args:
            image: (H, W) mono8 or (H, W, 3) colour uint8 image.
            top_k: number of matches wanted (fewer when fewer images score > 0).
            encoding: ``'bgr8'`` or ``'rgb8'`` for colour images.
        """
        if self._extractor is None:
            self._extractor = OrbExtractor(self.orb_params)
        return self.query_descriptors(self._extractor.descriptors(image, encoding), top_k)

    def _match(self, i: int, score: float) -> Match:
        return Match(i, self.filenames[i], score, self.positions.enu_m[i].copy(),
                     self.positions.column_dict(i))

    def positions_in(self, frame: LocalFrame) -> np.ndarray:
        """(N, 3) image positions [m] in another local ENU frame (e.g. the ``map`` frame).

        A local-only database (east_m/north_m columns) has no geodetic anchor: its
        coordinates are taken to be in the caller's frame already and returned unchanged.
        """
        if self.positions.llh is None:
            return self.positions.enu_m.copy()
        llh = self.positions.llh
        return frame.geodetic_to_enu(llh[:, 0], llh[:, 1], llh[:, 2])

    # -------------------------------------------------------------------- persistence
    def to_arrays(self) -> dict[str, np.ndarray]:
        p = self.positions
        arrays = {
            'format': np.array(FORMAT_NAME), 'version': np.int64(FORMAT_VERSION),
            'score_levels': np.int64(self.score_levels),
            'filenames': np.array(self.filenames, dtype=str),
            'n_features': self.n_features,
            'pos_columns': np.array(p.columns, dtype=str), 'pos_values': p.values,
            'pos_enu_m': p.enu_m,
            'pos_llh': p.llh if p.llh is not None else np.zeros((0, 3)),
            'pos_origin_llh': np.array(p.origin_llh if p.origin_llh else [], dtype=float),
            'orb_params': np.array(json.dumps(self.orb_params.as_dict())),
            'meta': np.array(json.dumps(self.meta)),
        }
        arrays.update(self.tree.to_arrays())
        arrays.update(self.index.to_arrays())
        return arrays

    def save(self, path: str | os.PathLike, overwrite: bool = False) -> int:
        """Write the database to one ``.npz`` file atomically; returns its size [bytes].

        The file is written next to its destination and renamed over it, so readers see
        either the old or the new database, never a partial one.

        Raises:
            MapDatabaseError: if ``path`` exists and ``overwrite`` is False, or on I/O error.
        """
        path = os.fspath(path)
        if os.path.lexists(path) and not overwrite:
            raise MapDatabaseOutputError(f'{path}: already exists (use --force to overwrite)')
        directory = os.path.dirname(os.path.abspath(path))
        tmp = None
        try:
            with tempfile.NamedTemporaryFile(dir=directory, prefix='.' + os.path.basename(path),
                                             suffix='.tmp', delete=False) as f:
                tmp = f.name
                np.savez(f, **self.to_arrays())   # a file object: no '.npz' appended
                f.flush()
                os.fsync(f.fileno())
            if os.path.lexists(path) and not overwrite:   # appeared while writing
                raise MapDatabaseOutputError(f'{path}: already exists (use --force to '
                                             'overwrite)')
            os.replace(tmp, path)
            tmp = None
        except OSError as err:
            raise MapDatabaseOutputError(f'{path}: cannot write database '
                                         f'({err.strerror or err})') from err
        finally:
            if tmp is not None and os.path.exists(tmp):
                os.unlink(tmp)
        return os.path.getsize(path)

    @classmethod
    def load(cls, path: str | os.PathLike) -> 'MapDatabase':
        """Load a database written by :meth:`save`.

        Raises:
            MapDatabaseError: naming the file when it is missing or not a valid database.
        """
        path = os.fspath(path)
        try:
            _check_npz(path)
            with np.load(path, allow_pickle=False) as z:
                # Only the known arrays (each checked by _check_npz); others are not read.
                a = {k: z[k] for k in DATABASE_KEYS}
        except FileNotFoundError as err:
            raise MapDatabaseError(f'{path}: no such database file') from err
        except (OSError, ValueError, KeyError, zipfile.BadZipFile, EOFError,
                NotImplementedError, RuntimeError) as err:
            # NotImplementedError, RuntimeError: zipfile on an unsupported compression or
            # an encrypted member.
            raise MapDatabaseError(f'{path}: not a readable map database '
                                   f'({type(err).__name__}: {err})') from err
        try:
            if str(a['format']) != FORMAT_NAME:
                raise ValueError(f'format is {str(a["format"])[:80]!r}')
            if int(a['version']) != FORMAT_VERSION:
                raise ValueError(f'format version {int(a["version"])}, this code reads '
                                 f'{FORMAT_VERSION}')
            _check_arrays(a)
            origin = a['pos_origin_llh']
            positions = PositionTable(
                tuple(str(c) for c in a['pos_columns']), a['pos_values'], a['pos_enu_m'],
                a['pos_llh'] if a['pos_llh'].size else None,
                tuple(float(v) for v in origin) if origin.size else None)
            return cls(VocabularyTree.from_arrays(a), InvertedIndex.from_arrays(a),
                       [str(f) for f in a['filenames']], positions,
                       OrbParams(**json.loads(str(a['orb_params']))),
                       int(a['score_levels']), a['n_features'], json.loads(str(a['meta'])))
        except (KeyError, ValueError, TypeError, IndexError, OverflowError,
                RecursionError) as err:
            # Parsing an untrusted file: any of these means "not what save() writes"
            # (RecursionError: absurdly nested JSON in meta or orb_params).
            raise MapDatabaseError(f'{path}: not a valid map database '
                                   f'({type(err).__name__}: {err})') from err


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
