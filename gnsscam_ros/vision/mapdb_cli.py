"""``gnsscam_mapdb``: build and query a geotagged image map database, and benchmark it.

Usage::

    gnsscam_mapdb build --images DIR --positions CSV --out DB [--force] [options]
    gnsscam_mapdb query --db DB IMAGE... [--top-k 5] [--json out.json]
    gnsscam_mapdb bench [--n-images 2000] [--n-queries 200] [--bf-queries 20]

Exit codes: 0 success, 2 bad usage, 3 bad input (an image, the positions CSV or the
database is missing, unreadable, corrupt, too large or out of range; ``query`` answers the
other images and then exits 3), 4 output refused or failed (``--out``/``--json`` exists
without ``--force``, or cannot be written; nothing is left behind), 130 interrupted.
Every error is one line on stderr naming the file (and the CSV line where there is one).
``build`` skips unusable rows by name with the reason (missing, unreadable, featureless or
too small/large image, position out of range, file name resolving outside ``--images``).
Progress and reports go to stderr; results to stdout.
"""
from __future__ import annotations

import argparse
import os
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from ..io.atomic import check_writable, write_json_atomic
from .database import MAX_POSITION_M, MapDatabase
from .errors import MapDatabaseOutputError, VisionError
from .features import OrbExtractor, OrbParams, load_gray
from .synthetic import perturb_view, synthetic_scene
from .vocab_tree import _MAX_LEAVES as MAX_LEAVES

PROG = 'gnsscam_mapdb'
EXIT_OK, EXIT_USAGE, EXIT_INPUT, EXIT_OUTPUT, EXIT_INTERRUPTED = 0, 2, 3, 4, 130


# ============================================================================ progress
class _Progress:
    """Throttled progress lines on stderr (one per stage change or per second)."""

    def __init__(self, enabled: bool = True, stream=None):
        self.enabled = enabled
        self.stream = stream or sys.stderr
        self._stage = None
        self._t_stage = self._t_print = time.perf_counter()

    def __call__(self, stage: str, done: int, total: int) -> None:
        if not self.enabled:
            return
        now = time.perf_counter()
        if stage != self._stage:
            self._stage, self._t_stage = stage, now
        elif done < total and now - self._t_print < 1.0:
            return
        self._t_print = now
        rate = done / max(now - self._t_stage, 1e-9)
        extra = f' ({rate:.0f}/s)' if stage == 'features' and done else ''
        print(f'{PROG}: {stage} {done}/{total}{extra}', file=self.stream, flush=True)


def _err(msg: str) -> None:
    print(f'{PROG}: error: {msg}', file=sys.stderr)


def _origin(text: str) -> tuple[float, float, float]:
    try:
        vals = [float(v) for v in text.split(',')]
    except ValueError:
        vals = []
    if len(vals) not in (2, 3):
        raise argparse.ArgumentTypeError(f'expected LAT,LON[,ALT], got {text!r}')
    lat, lon, alt = vals[0], vals[1], vals[2] if len(vals) == 3 else 0.0
    if not (abs(lat) <= 90 and abs(lon) <= 180 and abs(alt) <= MAX_POSITION_M):
        raise argparse.ArgumentTypeError(f'expected latitude in [-90, 90], longitude in '
                                         f'[-180, 180] and |altitude| <= '
                                         f'{MAX_POSITION_M:g} m, got {text!r}')
    return (lat, lon, alt)


def _positive(kind):
    def parse(text):
        try:
            v = kind(text)
        except ValueError as err:
            raise argparse.ArgumentTypeError(str(err)) from err
        if v <= 0:
            raise argparse.ArgumentTypeError(f'must be > 0, got {text}')
        return v
    return parse


def _add_build_options(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group('vocabulary tree and features')
    g.add_argument('--branching', type=_positive(int), default=10,
                   help='tree branching factor B (default 10)')
    g.add_argument('--depth', type=_positive(int), default=5,
                   help='tree depth L, B**L leaves (default 5)')
    g.add_argument('--score-levels', type=_positive(int), default=1,
                   help='deepest tree levels used as words, 1 = leaves only (default 1)')
    g.add_argument('--iterations', type=_positive(int), default=6,
                   help='k-majority iterations per level (default 6)')
    g.add_argument('--max-train', type=_positive(int), default=200_000,
                   help='descriptors sampled to train the tree (default 200000)')
    g.add_argument('--seed', type=int, default=0, help='training seed (default 0)')
    g.add_argument('--nfeatures', type=_positive(int), default=OrbParams.nfeatures,
                   help=f'ORB features per image (default {OrbParams.nfeatures})')
    g.add_argument('--orb-levels', type=_positive(int), default=OrbParams.n_levels,
                   help=f'ORB pyramid levels (default {OrbParams.n_levels})')
    g.add_argument('--jobs', type=_positive(int), default=None,
                   help='feature extraction threads (default: CPU count)')


def _build_kwargs(args) -> dict:
    """The build settings; ValueError (a usage error) for values the build would refuse
    only after extracting every image's features."""
    if args.branching < 2:
        raise ValueError(f'--branching must be >= 2, got {args.branching}')
    if args.branching ** args.depth > MAX_LEAVES:
        raise ValueError(f'--branching ** --depth = {args.branching ** args.depth} leaves, '
                         f'more than {MAX_LEAVES}')
    if args.score_levels > args.depth:
        raise ValueError(f'--score-levels must be <= --depth, got {args.score_levels}')
    return dict(orb_params=OrbParams(nfeatures=args.nfeatures, n_levels=args.orb_levels),
                branching=args.branching, depth=args.depth, score_levels=args.score_levels,
                iterations=args.iterations, seed=args.seed,
                max_train_descriptors=args.max_train, jobs=args.jobs)


def _usage(err: ValueError) -> int:
    _err(str(err))
    return EXIT_USAGE


def _output_refused(path: str | None, force: bool) -> bool:
    """Say so and return True when ``path`` cannot be written: it exists without
    ``--force``, or its folder is missing or not a folder (checked before any work)."""
    if path is None:
        return False
    if os.path.lexists(path) and not force:
        _err(f'{path}: already exists (use --force to overwrite)')
        return True
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        _err(f'{path}: cannot write here: no such folder {folder}')
        return True
    if os.path.isdir(path):
        _err(f'{path}: is a folder')
        return True
    try:
        check_writable(Path(path))      # a read-only folder: said before any work
    except OSError as err:
        _err(f'{path}: cannot write here ({err.strerror or err})')
        return True
    return False


def _write_json(path: str, data, force: bool) -> int:
    """Write JSON atomically (never over an existing file without ``force``)."""
    try:
        write_json_atomic(Path(path), data, force=force)
    except (OSError, ValueError) as err:      # OutputExistsError is an OSError
        _err(f'{path}: cannot write JSON ({getattr(err, "strerror", None) or err})')
        return EXIT_OUTPUT
    return EXIT_OK


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog=PROG, description='Geotagged image map database: ORB features, vocabulary '
        'tree, TF-IDF scoring (Nister & Stewenius 2006).')
    sub = ap.add_subparsers(dest='command', required=True)

    b = sub.add_parser('build', help='build a database from geotagged images')
    b.add_argument('--images', required=True, help='directory holding the images')
    b.add_argument('--positions', required=True,
                   help='CSV with header: filename and lat,lon[,alt_m] (WGS84) or '
                   'east_m,north_m[,up_m] (local frame); other columns are ignored')
    b.add_argument('--out', required=True, help='database file to write (.npz)')
    b.add_argument('--force', action='store_true', help='overwrite an existing database')
    b.add_argument('--origin', type=_origin, default=None,
                   help='local frame origin LAT,LON[,ALT] for WGS84 positions '
                   '(default: first image)')
    b.add_argument('--quiet', action='store_true', help='no progress output')
    _add_build_options(b)

    q = sub.add_parser('query', help='top-k database images for query images')
    q.add_argument('--db', required=True, help='database file')
    q.add_argument('images', nargs='+', metavar='IMAGE', help='query image files')
    q.add_argument('--top-k', type=_positive(int), default=5, help='matches per image')
    q.add_argument('--json', metavar='FILE', help='also write the results as JSON')
    q.add_argument('--force', action='store_true', help='replace an existing --json file')

    bn = sub.add_parser('bench', help='synthetic benchmark: build, load, query latency and '
                        'accuracy vs brute-force matching')
    bn.add_argument('--n-images', type=_positive(int), default=2000)
    bn.add_argument('--n-queries', type=_positive(int), default=200)
    bn.add_argument('--bf-queries', type=int, default=20,
                    help='queries also run by brute-force matching (slow; 0 = none)')
    bn.add_argument('--bench-seed', type=int, default=0, help='scene/query seed')
    bn.add_argument('--workdir', help='keep images and database here (default: temp dir)')
    bn.add_argument('--json', metavar='FILE', help='also write the figures as JSON')
    bn.add_argument('--force', action='store_true', help='replace an existing --json file')
    bn.add_argument('--quiet', action='store_true', help='no progress output')
    _add_build_options(bn)
    return ap


# ============================================================================== build
def _cmd_build(args) -> int:
    progress = _Progress(not args.quiet)
    if _output_refused(args.out, args.force):
        return EXIT_OUTPUT
    try:
        kw = _build_kwargs(args)
    except ValueError as err:
        return _usage(err)
    t0 = time.perf_counter()
    try:
        db, report = MapDatabase.build_from_files(args.images, args.positions,
                                                  origin_llh=args.origin, progress=progress,
                                                  **kw)
    except VisionError as err:
        for s in getattr(err, 'skipped', ()):      # why no row was usable
            print(f'{PROG}: skipped {s}', file=sys.stderr)
        raise
    t1 = time.perf_counter()
    size = db.save(args.out, overwrite=args.force)
    for s in report.skipped:
        print(f'{PROG}: skipped {s}', file=sys.stderr)
    print(f'{PROG}: wrote {args.out}: {len(db)} images ({len(report.skipped)} skipped of '
          f'{report.n_rows} rows), {report.n_descriptors} descriptors, '
          f'{db.tree.n_leaves} leaves, {size / 1e6:.1f} MB; built in {t1 - t0:.1f} s '
          f'({report.n_rows / (t1 - t0):.0f} images/s)', file=sys.stderr)
    return EXIT_OK


# ============================================================================== query
def _cmd_query(args) -> int:
    if _output_refused(args.json, args.force):      # before loading anything
        return EXIT_OUTPUT
    db = MapDatabase.load(args.db)
    results, failed = [], 0
    for path in args.images:
        entry = {'image': path, 'matches': []}
        try:
            matches = db.query(load_gray(path), top_k=args.top_k)
        except VisionError as err:
            # load_gray names the file; the extractor's errors (too small) do not.
            text = str(err) if str(err).startswith(f'{path}: ') else f'{path}: {err}'
            _err(text)
            entry['error'] = text
            failed += 1
            results.append(entry)
            continue
        entry['matches'] = [m.to_json() for m in matches]
        results.append(entry)
        print(path)
        if not matches:
            print('  (no match: no informative features)')
        for rank, m in enumerate(matches, 1):
            pos = ' '.join(f'{k}={v:.9g}' for k, v in m.columns.items())
            print(f'  {rank}. {m.filename}  score {m.score:.4f}  {pos}')
    if args.json and _write_json(args.json, results, args.force) != EXIT_OK:
        return EXIT_OUTPUT
    return EXIT_INPUT if failed else EXIT_OK


# ===================================================================== synthetic data
def write_synthetic_set(directory: str, n: int, seed: int = 0,
                        progress=None) -> tuple[str, list[str]]:
    """Write ``n`` synthetic JPEG images and a local-frame positions CSV (5 m spacing)."""
    names = []
    csv_path = os.path.join(directory, 'positions.csv')
    with open(csv_path, 'w', encoding='utf-8') as f:
        f.write('filename,east_m,north_m,up_m\n')
        for i in range(n):
            name = f'img_{i:05d}.jpg'
            cv2.imwrite(os.path.join(directory, name), synthetic_scene(i, seed),
                        [cv2.IMWRITE_JPEG_QUALITY, 90])
            # A street along east, blocks of 100 m turning north: positions matter only
            # as labels here.
            f.write(f'{name},{5.0 * (i % 200):.1f},{100.0 * (i // 200):.1f},0.0\n')
            names.append(name)
            if progress and ((i + 1) % 100 == 0 or i + 1 == n):
                progress('generate', i + 1, n)
    return csv_path, names


# ============================================================================== bench
def _brute_force_best(bf: cv2.BFMatcher, qd: np.ndarray, db_desc: list[np.ndarray],
                      ratio: float = 0.75) -> int:
    """Database image with the most ratio-test matches (Lowe) to the query descriptors."""
    best, best_n = -1, -1
    for i, dd in enumerate(db_desc):
        if len(qd) < 2 or len(dd) < 2:
            continue
        good = sum(1 for m in bf.knnMatch(qd, dd, k=2)
                   if len(m) == 2 and m[0].distance < ratio * m[1].distance)
        if good > best_n:
            best, best_n = i, good
    return best


def _cmd_bench(args) -> int:
    progress = _Progress(not args.quiet)
    if _output_refused(args.json, args.force):
        return EXIT_OUTPUT
    try:
        _build_kwargs(args)
    except ValueError as err:
        return _usage(err)
    try:
        work = args.workdir or tempfile.mkdtemp(prefix='gnsscam_mapdb_bench_')
        os.makedirs(work, exist_ok=True)
    except OSError as err:
        _err(f'{args.workdir or tempfile.gettempdir()}: cannot write here '
             f'({err.strerror or err})')
        return EXIT_OUTPUT
    try:
        return _bench(args, work, progress)
    finally:
        if not args.workdir:
            shutil.rmtree(work, ignore_errors=True)


def _bench(args, work: str, progress) -> int:
    n, kw = args.n_images, _build_kwargs(args)
    csv_path, names = write_synthetic_set(work, n, args.bench_seed, progress)
    db_path = os.path.join(work, 'map.npz')

    t0 = time.perf_counter()
    db, report = MapDatabase.build_from_files(work, csv_path, progress=progress,
                                              keep_descriptors=args.bf_queries > 0, **kw)
    build_s = time.perf_counter() - t0
    size = db.save(db_path, overwrite=True)
    load_times = []
    for _ in range(3):
        t = time.perf_counter()
        db = MapDatabase.load(db_path)
        load_times.append(time.perf_counter() - t)

    rng = np.random.default_rng([args.bench_seed, 7])
    truth = rng.integers(0, n, args.n_queries)
    queries = [perturb_view(synthetic_scene(int(i), args.bench_seed), rng) for i in truth]

    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)      # single-core latency, as the camera node would see it
    try:
        ext = OrbExtractor(db.orb_params)
        t_orb, t_tree, t_score, top1 = [], [], [], []
        cpu = []
        for k, img in enumerate(queries):
            c = time.thread_time()
            t = time.perf_counter()
            desc = ext.descriptors(img)
            t1 = time.perf_counter()
            words = db.words(desc)
            t2 = time.perf_counter()
            s = db.index.score(words)
            best = int(np.argmax(s))
            t3 = time.perf_counter()
            # CPU time of this thread: robust to other processes competing for the cores.
            cpu.append(time.thread_time() - c)
            t_orb.append(t1 - t)
            t_tree.append(t2 - t1)
            t_score.append(t3 - t2)
            top1.append(best == truth[k])
            if (k + 1) % 50 == 0:
                progress('queries', k + 1, len(queries))
        total = np.array(t_orb) + np.array(t_tree) + np.array(t_score)
        # End-to-end through the public API too (adds building the Match objects).
        t_api = []
        for img in queries:
            t = time.perf_counter()
            db.query(img, top_k=5)
            t_api.append(time.perf_counter() - t)

        n_bf = min(max(args.bf_queries, 0), len(queries))
        bf_times, bf_top1 = [], []
        if n_bf:
            bf = cv2.BFMatcher(cv2.NORM_HAMMING)
            for k in range(n_bf):
                t = time.perf_counter()
                qd = ext.descriptors(queries[k])
                best = _brute_force_best(bf, qd, report.descriptors)
                bf_times.append(time.perf_counter() - t)
                bf_top1.append(best == truth[k])
                progress('brute-force', k + 1, n_bf)
    finally:
        cv2.setNumThreads(threads)

    ms = 1e3
    fig = {
        'n_images': len(db), 'n_queries': len(queries), 'n_descriptors': report.n_descriptors,
        'tree': f'B={db.tree.branching} L={db.tree.depth} ({db.tree.n_leaves} leaves, '
                f'score levels {db.score_levels})',
        'orb_nfeatures': db.orb_params.nfeatures,
        'build_s': build_s, 'build_images_per_s': n / build_s,
        'build_feature_s': report.seconds.get('features'),
        'build_train_index_s': report.seconds.get('build'),
        'db_size_mb': size / 1e6, 'load_s_median': float(np.median(load_times)),
        'query_ms_median': float(np.median(total) * ms),
        'query_ms_p90': float(np.percentile(total, 90) * ms),
        'query_cpu_ms_median': float(np.median(cpu) * ms),
        'query_orb_ms_median': float(np.median(t_orb) * ms),
        'query_tree_ms_median': float(np.median(t_tree) * ms),
        'query_score_ms_median': float(np.median(t_score) * ms),
        'query_api_ms_median': float(np.median(t_api) * ms),
        'tree_top1': float(np.mean(top1)),
    }
    if n_bf:
        bf_med = float(np.median(bf_times))
        fig.update({
            'bf_queries': n_bf, 'bf_ms_median': bf_med * ms,
            'bf_top1': float(np.mean(bf_top1)),
            'tree_top1_on_bf_queries': float(np.mean(top1[:n_bf])),
            'speedup_median': bf_med / float(np.median(total)),
        })
    _print_bench(fig)
    if args.json:
        return _write_json(args.json, fig, args.force)
    return EXIT_OK


def _print_bench(f: dict) -> None:
    print(f'{PROG} bench  ({platform.machine()}, {os.cpu_count()} CPUs, OpenCV '
          f'{cv2.__version__}, numpy {np.__version__})')
    print(f'  database        {f["n_images"]} synthetic 640x480 images, {f["n_descriptors"]} '
          f'ORB descriptors (nfeatures {f["orb_nfeatures"]}), tree {f["tree"]}')
    print(f'  build           {f["build_s"]:.1f} s = {f["build_images_per_s"]:.0f} images/s '
          f'(features {f["build_feature_s"]:.1f} s, train+index '
          f'{f["build_train_index_s"]:.1f} s)')
    print(f'  size on disk    {f["db_size_mb"]:.1f} MB')
    print(f'  load            {f["load_s_median"] * 1e3:.0f} ms (median of 3)')
    print(f'  query (1 core)  median {f["query_ms_median"]:.2f} ms, p90 '
          f'{f["query_ms_p90"]:.2f} ms wall  [ORB {f["query_orb_ms_median"]:.2f} + tree '
          f'{f["query_tree_ms_median"]:.2f} + scoring {f["query_score_ms_median"]:.2f}]; '
          f'CPU {f["query_cpu_ms_median"]:.2f} ms; API query() '
          f'{f["query_api_ms_median"]:.2f} ms')
    print(f'  tree top-1      {f["tree_top1"] * 100:.1f} % of {f["n_queries"]} queries')
    if 'bf_queries' in f:
        print(f'  brute force     median {f["bf_ms_median"]:.0f} ms per query '
              f'(ORB + BFMatcher Hamming knn, ratio 0.75, vs every image)')
        print(f'  on the same {f["bf_queries"]} queries: top-1 tree '
              f'{f["tree_top1_on_bf_queries"] * 100:.1f} %, brute force '
              f'{f["bf_top1"] * 100:.1f} %; speedup {f["speedup_median"]:.0f}x')


# =============================================================================== main
def opencv_log_level_api() -> tuple:
    """``(get_level, set_level, silent)``: OpenCV's log level, on every OpenCV supported.

    ``cv2.utils.logging`` exists from OpenCV 4.13 (and is the only form in 5.x); older
    ones (Debian 12's and Ubuntu 24.04's 4.6.0) have ``cv2.getLogLevel``/``setLogLevel``
    with the same integer levels, of which ``LOG_LEVEL_SILENT`` is 0.
    """
    api = getattr(getattr(cv2, 'utils', None), 'logging', None)
    if api is not None and hasattr(api, 'setLogLevel'):
        return api.getLogLevel, api.setLogLevel, api.LOG_LEVEL_SILENT
    return cv2.getLogLevel, cv2.setLogLevel, 0


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``gnsscam_mapdb``; returns the exit code."""
    args = _parser().parse_args(argv)
    # OpenCV logs its codecs' complaints ("PNG input buffer is incomplete") on stderr; the
    # tool says what matters on one line naming the file, so they stay silent meanwhile.
    get_level, set_level, silent = opencv_log_level_api()
    level = get_level()
    set_level(silent)
    try:
        return {'build': _cmd_build, 'query': _cmd_query, 'bench': _cmd_bench}[
            args.command](args)
    except MapDatabaseOutputError as err:
        _err(str(err))
        return EXIT_OUTPUT
    except VisionError as err:
        _err(str(err))
        return EXIT_INPUT
    except KeyboardInterrupt:
        _err('interrupted')
        return EXIT_INTERRUPTED
    finally:
        set_level(level)


if __name__ == '__main__':
    sys.exit(main())
