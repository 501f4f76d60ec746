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
  :data:`.database_checks.MAX_DATABASE_BYTES` in all, or an array larger than the bytes
  its member holds (a "zip bomb"); then it checks what it loaded (array shapes, word and
  image indices in range, finite weights, positions within
  :data:`.positions.MAX_POSITION_M` of the origin and valid latitudes/longitudes, ORB
  settings OpenCV accepts).
* :func:`read_positions_csv` skips rows whose position is not finite or out of range, and
  :meth:`MapDatabase.build_from_files` rows whose ``filename`` resolves outside the image
  folder (an absolute path, ``..``, or a symbolic link leading out) or lies more than
  :data:`MAX_POSITION_M` from the origin, by name with the reason.
"""
from __future__ import annotations

import json
import os
import threading
import time
import zipfile
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from ..core.frames import LocalFrame
from ..io.partials import make_partial_file, sweep_and_report
from .errors import ImageError, MapDatabaseError, MapDatabaseOutputError
from .features import DESCRIPTOR_BYTES, OrbExtractor, OrbParams, load_gray
from .database_checks import DATABASE_KEYS, _check_arrays, _check_npz
from .positions import (MAX_POSITION_M, PositionTable, SkippedImage, _outside,
                        read_positions_csv)
from .vocab_tree import VocabularyTree

FORMAT_NAME = 'gnsscam_mapdb'
FORMAT_VERSION = 1


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
        from scipy import sparse     # building only: camera_node, which loads, skips it

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


def _no_usable_image(positions_csv, report: BuildReport) -> MapDatabaseError:
    """The error of a build without a single usable row; ``.skipped`` says why each row
    was left out (the command line prints them)."""
    err = MapDatabaseError(f'{os.fspath(positions_csv)}: no usable image '
                           f'({len(report.skipped)} rows skipped)')
    err.skipped = list(report.skipped)
    return err


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
        tmp = None
        try:
            # Named as io.partials names partial outputs, so that the next save of this
            # path removes what a killed one left (its writer's pid no longer runs).
            sweep_and_report(os.path.abspath(path), None, same_output=True)
            fd, tmp = make_partial_file(os.path.abspath(path))
            with os.fdopen(fd, 'wb') as f:
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
