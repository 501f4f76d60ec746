"""Retrieval accuracy of an emulated camera stream against a map database.

A frame counts as correct when its best database match lies within ``radius_m`` of the
true camera position; the figures are split by camera fault (clean, blur, occlusion).
``python -m gnsscam_ros.bench.retrieval --measure --seed 1`` prints them for a whole drive.
"""
from __future__ import annotations

import time
from typing import Callable

import numpy as np

from ...vision.database import MapDatabase
from .camera import FAULT_NAMES, CameraStream


def evaluate_retrieval(stream: CameraStream, db: MapDatabase, frames=None,
                       radius_m: float = 10.0, top_k: int = 5,
                       progress: Callable[[str, int, int], None] | None = None) -> dict:
    """Top-1 (and top-k) retrieval accuracy of a camera stream against a database.

    A frame counts as correct when its best match lies within ``radius_m`` (horizontal
    distance) of the true camera position; frames without any match count as wrong. A
    frame is *ambiguous* when another of its top-k matches, more than ``2 radius_m`` away
    from the best one, scores at least 80 % of the best score (another place looks alike).

    Args:
        stream: The camera stream (faults applied as recorded).
        db: The map database (positions in the same frame as ``stream.pose``).
        frames: Frame indices to use (default: all).
        radius_m: Correctness radius [m].
        top_k: Also report whether any of the first ``top_k`` matches is within the radius.
        progress: Optional ``progress(stage, done, total)`` callback.

    Returns:
        ``{'frames', 'error_m' (per frame, inf when no match), 'top1_ok', 'topk_ok',
        'ambiguous', 'fault', 'by_kind': {name: {'n', 'top1', 'topk', 'ambiguous',
        'median_error_m'}}, 'top1', 'render_ms', 'query_ms'}`` with fractions in [0, 1].
    """
    idx = np.arange(len(stream)) if frames is None else np.asarray(frames, dtype=int)
    err = np.full(len(idx), np.inf)
    ok_k = np.zeros(len(idx), bool)
    ambiguous = np.zeros(len(idx), bool)
    render_s = query_s = 0.0
    for j, i in enumerate(idx):
        t0 = time.perf_counter()
        img = stream.image(int(i))
        t1 = time.perf_counter()
        matches = db.query(img, top_k=top_k)
        query_s += time.perf_counter() - t1
        render_s += t1 - t0
        if matches:
            d = [float(np.hypot(*(m.position_enu_m[:2] - stream.pose[i, :2]))) for m in matches]
            err[j] = d[0]
            ok_k[j] = min(d) <= radius_m
            best = matches[0]
            ambiguous[j] = any(
                m.score >= 0.8 * best.score
                and np.hypot(*(m.position_enu_m[:2] - best.position_enu_m[:2])) > 2 * radius_m
                for m in matches[1:])
        if progress and ((j + 1) % 250 == 0 or j + 1 == len(idx)):
            progress('query', j + 1, len(idx))
    ok1 = err <= radius_m
    fault = stream.fault[idx]
    by_kind = {}
    for code, name in enumerate(FAULT_NAMES):
        m = fault == code
        by_kind[name] = {'n': int(m.sum()),
                         'top1': float(ok1[m].mean()) if m.any() else float('nan'),
                         'topk': float(ok_k[m].mean()) if m.any() else float('nan'),
                         'ambiguous': float(ambiguous[m].mean()) if m.any() else float('nan'),
                         'median_error_m': float(np.median(err[m])) if m.any() else float('nan')}
    n = max(len(idx), 1)
    return {'frames': idx, 'error_m': err, 'top1_ok': ok1, 'topk_ok': ok_k,
            'ambiguous': ambiguous, 'fault': fault,
            'by_kind': by_kind, 'top1': float(ok1.mean()) if len(idx) else float('nan'),
            'radius_m': float(radius_m), 'top_k': int(top_k),
            'render_ms': 1e3 * render_s / n, 'query_ms': 1e3 * query_s / n}
