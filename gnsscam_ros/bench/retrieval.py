"""Retrieval figures of the emulated camera: ``python -m gnsscam_ros.bench.retrieval``.

``--measure --seed 1`` builds (or loads from the cache) the map database of the drive's
route, queries every frame of the drive's camera stream and prints top-1 retrieval within
10 m of the truth for clean, blurred and occluded frames separately, with the render and
query times. ``--save-frames DIR`` writes a few example frames and database views.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

import cv2
import numpy as np

from ..datasets.emulated.camera import make_camera_stream
from ..datasets.emulated.map_database import build_emulated_map_database
from ..datasets.emulated.retrieval import evaluate_retrieval
from ..datasets.emulated.scenario import make_scenario
from ..datasets.emulated.views import map_database_views


def _progress(stage: str, done: int, total: int) -> None:
    print(f'  {stage}: {done}/{total}', file=sys.stderr, flush=True)


def main(argv: list[str] | None = None) -> int:
    """``python -m gnsscam_ros.bench.retrieval --measure --seed 1``: retrieval figures."""
    ap = argparse.ArgumentParser(prog='python -m gnsscam_ros.bench.retrieval',
                                 description='Emulated camera stream and map database.')
    ap.add_argument('--measure', action='store_true',
                    help='build/load the database and measure top-1 retrieval on the drive')
    ap.add_argument('--seed', type=int, default=1, help='drive seed (default 1)')
    ap.add_argument('--cache-dir', default=None, help='database cache folder '
                    '(default $GNSSCAM_CACHE_DIR or ~/.cache/gnsscam_ros)')
    ap.add_argument('--no-cache', action='store_true', help='always rebuild, write nothing')
    ap.add_argument('--spacing', type=float, default=3.0, help='database spacing [m]')
    ap.add_argument('--margin', type=float, default=120.0,
                    help='database streets within this distance of the route [m]')
    ap.add_argument('--region', choices=('route', 'city'), default='route')
    ap.add_argument('--every', type=int, default=1, help='use every k-th frame')
    ap.add_argument('--fault-fraction', type=float, default=0.2)
    ap.add_argument('--radius', type=float, default=10.0, help='correct-match radius [m]')
    ap.add_argument('--save-frames', default=None,
                    help='folder to write a few example frames (PNG) into')
    ap.add_argument('--json', default=None, help='also write the figures to this JSON file')
    args = ap.parse_args(argv)
    if not args.measure and not args.save_frames:
        ap.print_help()
        return 0
    sc = make_scenario(args.seed)
    stream = make_camera_stream(sc, fault_fraction=args.fault_fraction)
    if args.save_frames:
        os.makedirs(args.save_frames, exist_ok=True)
        for i in np.linspace(0, len(stream) - 1, 8).astype(int):
            cv2.imwrite(os.path.join(args.save_frames,
                                     f'frame{i:05d}_{stream.fault_name(i)}.png'),
                        stream.image(int(i)))
        for k, (name, img, *_) in enumerate(map_database_views(sc, margin_m=args.margin)):
            if k % 200 == 0:
                cv2.imwrite(os.path.join(args.save_frames, name), img)
            if k >= 1000:
                break
    if not args.measure:
        return 0
    print(f'seed {args.seed}: {len(stream)} frames at 10 Hz, '
          f'{stream.info["fault_counts"]}', flush=True)
    t0 = time.perf_counter()
    db = build_emulated_map_database(sc, cache_dir=args.cache_dir, use_cache=not args.no_cache,
                                     spacing_m=args.spacing, margin_m=args.margin,
                                     region=args.region, progress=_progress)
    t_db = time.perf_counter() - t0
    meta = db.meta.get('emulated', {})
    res = evaluate_retrieval(stream, db, frames=np.arange(0, len(stream), args.every),
                             radius_m=args.radius, progress=_progress)
    print(f'database: {len(db)} images ({meta.get("n_turn_views", "?")} on turn arcs), '
          f'{int(db.n_features.sum())} descriptors; build {meta.get("build_s", float("nan")):.1f}'
          f' s (render+ORB {meta.get("features_s", float("nan")):.1f} s, tree '
          f'{meta.get("tree_s", float("nan")):.1f} s); this run {t_db:.1f} s')
    if meta.get('render_s') is not None and meta.get('n_views'):
        print(f'database render: {1e3 * meta["render_s"] / meta["n_views"]:.1f} ms/image')
    print(f'query frames: render {res["render_ms"]:.1f} ms/frame (incl. faults), '
          f'ORB+query {res["query_ms"]:.1f} ms/frame')
    print(f'top-1 within {args.radius:g} m:')
    for name, r in res['by_kind'].items():
        print(f'  {name:10s} n={r["n"]:5d}  top-1 {100 * r["top1"]:5.1f} %  '
              f'top-5 {100 * r["topk"]:5.1f} %  ambiguous {100 * r["ambiguous"]:5.1f} %  '
              f'median error {r["median_error_m"]:.1f} m')
    print(f'  {"all":10s} n={len(res["frames"]):5d}  top-1 {100 * res["top1"]:5.1f} %')
    if args.json:
        out = {'seed': args.seed, 'n_db': len(db), 'db_meta': {k: v for k, v in meta.items()
                                                               if k != 'yaw_rad'},
               'by_kind': res['by_kind'], 'top1': res['top1'], 'render_ms': res['render_ms'],
               'query_ms': res['query_ms'], 'radius_m': args.radius}
        with open(args.json, 'w') as f:
            json.dump(out, f, indent=2, default=str)
    return 0


if __name__ == '__main__':
    sys.exit(main())
