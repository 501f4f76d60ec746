"""``gnsscam_mapdb``: build and query a geotagged image map database, and benchmark it.

Usage::

    gnsscam_mapdb build --images DIR --positions CSV --out DB [--force] [options]
    gnsscam_mapdb query --db DB IMAGE... [--top-k 5] [--json out.json]
    gnsscam_mapdb bench [--n-images 2000] [--n-queries 200] [--bf-queries 20]

Exit codes: 0 success, 1 error (message on stderr naming the file), 2 bad usage.
Progress and reports go to stderr; results to stdout.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import sys
import tempfile
import time

import cv2
import numpy as np

from .database import MapDatabase
from .errors import VisionError
from .features import OrbExtractor, OrbParams, load_gray

PROG = 'gnsscam_mapdb'


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
    return (vals[0], vals[1], vals[2] if len(vals) == 3 else 0.0)


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
    return dict(orb_params=OrbParams(nfeatures=args.nfeatures, n_levels=args.orb_levels),
                branching=args.branching, depth=args.depth, score_levels=args.score_levels,
                iterations=args.iterations, seed=args.seed,
                max_train_descriptors=args.max_train, jobs=args.jobs)


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

    bn = sub.add_parser('bench', help='synthetic benchmark: build, load, query latency and '
                        'accuracy vs brute-force matching')
    bn.add_argument('--n-images', type=_positive(int), default=2000)
    bn.add_argument('--n-queries', type=_positive(int), default=200)
    bn.add_argument('--bf-queries', type=int, default=20,
                    help='queries also run by brute-force matching (slow; 0 = none)')
    bn.add_argument('--bench-seed', type=int, default=0, help='scene/query seed')
    bn.add_argument('--workdir', help='keep images and database here (default: temp dir)')
    bn.add_argument('--json', metavar='FILE', help='also write the figures as JSON')
    bn.add_argument('--quiet', action='store_true', help='no progress output')
    _add_build_options(bn)
    return ap


# ============================================================================== build
def _cmd_build(args) -> int:
    progress = _Progress(not args.quiet)
    if os.path.exists(args.out) and not args.force:
        _err(f'{args.out}: already exists (use --force to overwrite)')
        return 1
    kw = _build_kwargs(args)
    t0 = time.perf_counter()
    db, report = MapDatabase.build_from_files(args.images, args.positions,
                                              origin_llh=args.origin, progress=progress, **kw)
    t1 = time.perf_counter()
    size = db.save(args.out, overwrite=args.force)
    for s in report.skipped:
        print(f'{PROG}: skipped {s}', file=sys.stderr)
    print(f'{PROG}: wrote {args.out}: {len(db)} images ({len(report.skipped)} skipped of '
          f'{report.n_rows} rows), {report.n_descriptors} descriptors, '
          f'{db.tree.n_leaves} leaves, {size / 1e6:.1f} MB; built in {t1 - t0:.1f} s '
          f'({report.n_rows / (t1 - t0):.0f} images/s)', file=sys.stderr)
    return 0


# ============================================================================== query
def _cmd_query(args) -> int:
    db = MapDatabase.load(args.db)
    results, failed = [], 0
    for path in args.images:
        entry = {'image': path, 'matches': []}
        try:
            matches = db.query(load_gray(path), top_k=args.top_k)
        except VisionError as err:
            _err(str(err))
            entry['error'] = str(err)
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
    if args.json:
        try:
            with open(args.json, 'w', encoding='utf-8') as f:
                json.dump(results, f, indent=2)
                f.write('\n')
        except OSError as err:
            _err(f'{args.json}: cannot write JSON ({err.strerror or err})')
            return 1
    return 1 if failed else 0


# ===================================================================== synthetic data
def synthetic_scene(index: int, seed: int = 0, shape: tuple[int, int] = (480, 640),
                    n_styles: int = 40) -> np.ndarray:
    """A seeded synthetic street-facade image (BGR uint8) for tests and benchmarks.

    Buildings draw their window grid from a small shared set of styles, so different
    images repeat the same facade patterns (ambiguous, as real streets); shop signs with
    image-specific text, poles and clutter make each image identifiable.
    """
    h, w = shape
    rng = np.random.default_rng([seed, index])
    img = np.empty((h, w, 3), np.uint8)
    sky = np.linspace(230, 150, h // 4)[:, None, None]
    img[:h // 4] = (sky * np.array([1.0, 0.9, 0.75])).astype(np.uint8)
    img[h // 4:] = (90, 90, 95)
    x = int(rng.integers(-80, 0))
    while x < w:
        style = int(rng.integers(n_styles))
        srng = np.random.default_rng([seed, 1_000_003, style])
        bw = int(srng.integers(140, 320))
        top = int(srng.integers(h // 12, h // 3))
        wall = tuple(int(c) for c in srng.integers(60, 220, 3))
        cv2.rectangle(img, (x, top), (x + bw, h - h // 8), wall, -1)
        ww, wh = int(srng.integers(14, 30)), int(srng.integers(18, 40))
        gx, gy = ww + int(srng.integers(8, 24)), wh + int(srng.integers(12, 30))
        glass = tuple(int(c) for c in srng.integers(0, 120, 3))
        frame = tuple(int(c) for c in srng.integers(150, 256, 3))
        for yy in range(top + 12, h - h // 8 - wh - 40, gy):
            for xx in range(x + 10, x + bw - ww - 6, gx):
                cv2.rectangle(img, (xx, yy), (xx + ww, yy + wh), glass, -1)
                cv2.rectangle(img, (xx, yy), (xx + ww, yy + wh), frame, 2)
        # Unique per image: shop sign with text, door, clutter.
        sy = h - h // 8 - 40 - int(rng.integers(0, 30))
        sx = x + int(rng.integers(0, max(1, bw - 120)))
        cv2.rectangle(img, (sx, sy), (sx + 120, sy + 30),
                      tuple(int(c) for c in rng.integers(0, 256, 3)), -1)
        text = ''.join(rng.choice(list('ABCDEFGHKMNPRSTUVWXYZ0123456789'), 5))
        cv2.putText(img, text, (sx + 6, sy + 23), cv2.FONT_HERSHEY_SIMPLEX, 0.7,
                    tuple(int(c) for c in rng.integers(0, 256, 3)), 2, cv2.LINE_AA)
        x += bw + int(rng.integers(0, 20))
    for _ in range(int(rng.integers(4, 10))):
        px = int(rng.integers(0, w))
        cv2.line(img, (px, int(rng.integers(h // 3, h // 2))), (px, h),
                 tuple(int(c) for c in rng.integers(20, 90, 3)), int(rng.integers(3, 9)))
    for _ in range(int(rng.integers(10, 25))):
        c = (int(rng.integers(0, w)), int(rng.integers(h // 2, h)))
        cv2.circle(img, c, int(rng.integers(3, 15)),
                   tuple(int(v) for v in rng.integers(0, 256, 3)), -1)
    fonts = (cv2.FONT_HERSHEY_SIMPLEX, cv2.FONT_HERSHEY_DUPLEX, cv2.FONT_HERSHEY_COMPLEX,
             cv2.FONT_HERSHEY_TRIPLEX, cv2.FONT_HERSHEY_SCRIPT_SIMPLEX)
    for _ in range(int(rng.integers(4, 9))):       # posters and graffiti
        org = (int(rng.integers(0, w - 60)), int(rng.integers(h // 4, h - 10)))
        text = ''.join(rng.choice(list('abcdefghijkmnopqrstuvwxyz0123456789'), 4))
        cv2.putText(img, text, org, fonts[int(rng.integers(len(fonts)))],
                    float(rng.uniform(0.5, 1.2)),
                    tuple(int(c) for c in rng.integers(0, 256, 3)), int(rng.integers(1, 3)),
                    cv2.LINE_AA)
    for _ in range(int(rng.integers(2, 5))):       # parked cars: polygon body + wheels
        cx, cy = int(rng.integers(0, w)), int(rng.integers(h - h // 6, h - 10))
        cw, ch = int(rng.integers(60, 130)), int(rng.integers(25, 45))
        body = np.array([[cx, cy], [cx + cw, cy], [cx + cw - 10, cy - ch],
                         [cx + int(cw * 0.3), cy - ch - int(rng.integers(0, 15))],
                         [cx + 8, cy - ch // 2]], np.int32)
        cv2.fillPoly(img, [body], tuple(int(c) for c in rng.integers(0, 256, 3)))
        for wx in (cx + cw // 5, cx + 4 * cw // 5):
            cv2.circle(img, (wx, cy), ch // 3, (20, 20, 20), -1)
    noise = rng.normal(0.0, 4.0, img.shape)
    return np.clip(img + noise, 0, 255).astype(np.uint8)


def perturb_view(image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Another view of a scene: shift, scale, roll, brightness/contrast, noise, slight blur."""
    h, w = image.shape[:2]
    m = cv2.getRotationMatrix2D((w / 2, h / 2), rng.uniform(-3, 3), rng.uniform(0.9, 1.1))
    m[:, 2] += rng.uniform(-25, 25, 2)
    out = cv2.warpAffine(image, m, (w, h), borderMode=cv2.BORDER_REFLECT)
    out = cv2.convertScaleAbs(out, alpha=rng.uniform(0.7, 1.3), beta=rng.uniform(-30, 30))
    if rng.random() < 0.5:
        out = cv2.GaussianBlur(out, (3, 3), 0)
    return np.clip(out + rng.normal(0, 3, out.shape), 0, 255).astype(np.uint8)


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
    work = args.workdir or tempfile.mkdtemp(prefix='gnsscam_mapdb_bench_')
    os.makedirs(work, exist_ok=True)
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
        with open(args.json, 'w', encoding='utf-8') as f:
            json.dump(fig, f, indent=2)
            f.write('\n')
    return 0


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
def main(argv: list[str] | None = None) -> int:
    """Entry point of ``gnsscam_mapdb``; returns the exit code."""
    args = _parser().parse_args(argv)
    try:
        return {'build': _cmd_build, 'query': _cmd_query, 'bench': _cmd_bench}[
            args.command](args)
    except VisionError as err:
        _err(str(err))
        return 1
    except KeyboardInterrupt:
        _err('interrupted')
        return 130


if __name__ == '__main__':
    sys.exit(main())
