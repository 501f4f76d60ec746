"""Tests of the emulated street imagery (datasets.emulated: optics, textures, render), its
camera stream (camera) and map database (views, map_database, retrieval)."""
import dataclasses
import os

import cv2
import numpy as np
import pytest

from gnsscam_ros.datasets.emulated import textures
from gnsscam_ros.datasets.emulated.camera import (FAULT_BLUR, FAULT_CLEAN, FAULT_OCCLUSION,
                                                  make_camera_stream, with_camera)
from gnsscam_ros.datasets.emulated.drive import make_emulated_drive
from gnsscam_ros.datasets.emulated.map_database import build_emulated_map_database
from gnsscam_ros.datasets.emulated.optics import CameraIntrinsics, Lighting
from gnsscam_ros.datasets.emulated.render import StreetRenderer, render_view, visibility_order
from gnsscam_ros.datasets.emulated.retrieval import evaluate_retrieval
from gnsscam_ros.datasets.emulated.scenario import make_scenario
from gnsscam_ros.datasets.emulated.textures import facade_texture
from gnsscam_ros.datasets.emulated.views import database_poses, map_database_views

SEED = 2
ORB = cv2.ORB_create(1000)


@pytest.fixture(scope='module')
def scenario():
    return make_scenario(SEED)


@pytest.fixture(scope='module')
def stream(scenario):
    # 60 s of drive with many faults, so that every kind occurs often.
    return make_camera_stream(scenario, duration_s=60.0, fault_fraction=0.5)


def _n_keypoints(img):
    return len(ORB.detect(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY), None))


# ============================================================================ textures
def test_texture_deterministic_and_repeated():
    a = facade_texture(3, 20.0, 15.0)
    b = facade_texture(3, 20.0, 15.0)
    assert a is b and not a.flags.writeable
    assert a.shape == (300, 400, 3) and a.dtype == np.uint8
    # The cache is only a speed-up: a fresh texture is identical.
    assert np.array_equal(textures._make_texture(3, 400, 300, 20.0), a)
    assert not np.array_equal(facade_texture(4, 20.0, 15.0), a)
    # Same style, other width: the upper floors' window grid (anchored at the left edge)
    # repeats; only weathering and clutter differ.
    wide = facade_texture(3, 30.0, 15.0)
    diff = np.abs(wide[40:200, :380].astype(int) - a[40:200, :380].astype(int))
    assert np.median(diff) <= 12
    assert a.std() > 20             # structured, not a flat colour


# ============================================================================ rendering
@pytest.mark.slow
def test_render_deterministic(scenario):
    pose = scenario.pose_at([30.0])
    p = (*pose.enu_m[0], pose.yaw_rad[0])
    light = Lighting.sunny(np.random.default_rng(0))
    a = StreetRenderer(scenario.city, lighting=light).render(p, noise_index=1)
    b = StreetRenderer(scenario.city, lighting=light).render(p, noise_index=1)
    assert a.shape == (480, 640, 3) and a.dtype == np.uint8
    assert np.array_equal(a, b)
    c = render_view(scenario.city, p, lighting=light)
    assert np.array_equal(c, render_view(scenario.city, p, lighting=light))
    # Other lighting: same scene, other pixels.
    d = render_view(scenario.city, p, lighting=Lighting.overcast(np.random.default_rng(0)))
    assert np.mean(np.abs(d.astype(int) - c.astype(int))) > 5


@pytest.mark.slow
def test_stream_images_deterministic_in_any_order(scenario, stream):
    idx = [5, 300, 17, 5]
    first = [stream.image(i) for i in idx]
    again = make_camera_stream(scenario, duration_s=60.0, fault_fraction=0.5)
    for i, img in zip(reversed(idx), reversed(first)):
        assert np.array_equal(again.image(i), img)
    assert np.array_equal(first[0], first[3])


@pytest.mark.slow
def test_frames_have_texture(stream):
    counts = [_n_keypoints(stream.clean_image(i)) for i in range(0, len(stream), 60)]
    assert min(counts) >= 200, counts


@pytest.mark.slow
def test_texture_cache_is_only_a_speed_up(scenario, stream):
    # Speed comes from the cached lit facade textures (timing: bench.emulation); a renderer
    # that keeps almost nothing must draw the same frames.
    small = StreetRenderer(scenario.city, stream.intrinsics, stream.lighting,
                           seed=stream.seed, cache_size=2)
    for i in range(0, 100, 9):
        img = small.render(stream.pose[i], gain=float(stream.gain[i]),
                           noise_index=int(stream.noise_index[i]))
        assert np.array_equal(img, stream.clean_image(i))
    assert len(small._cache) <= 2
    assert 2 < len(stream.renderer._cache) <= stream.renderer._cache_size


@pytest.mark.slow
def test_near_plane_clipping_next_to_a_wall(scenario):
    city = scenario.city
    f = city.facades
    r = StreetRenderer(city)
    k = int(np.argmax(f.width_m))
    p0, p1, nrm = f.p0_m[k], f.p1_m[k], f.normal[k]
    mid = 0.5 * (p0 + p1)
    along = (p1 - p0) / np.linalg.norm(p1 - p0)
    facing = np.arctan2(-nrm[1], -nrm[0])
    poses = [
        (*(mid + 0.05 * nrm), 1.8, facing),                          # nose on the wall
        (*(mid + 0.05 * nrm), 1.8, np.arctan2(along[1], along[0])),  # along it, 5 cm off
        (*(p0 + 0.2 * nrm - 3.0 * along), 1.8, facing + 0.7),        # corner, oblique
        (*(mid + 0.31 * nrm), 1.8, facing),                          # just past near plane
        (*(mid - 2.0 * nrm), 1.8, facing),                           # inside the building
    ]
    for p in poses:
        img = r.render(p)
        assert img.shape == (480, 640, 3)
    # Facing the wall from 2 m: the wall fills the view (no sky, no far ground).
    img = r.render((*(mid + 2.0 * nrm), 1.8, facing), stats=(st := {}))
    assert st['n_facades'] >= 1
    sky = np.asarray(Lighting().sky_zenith_bgr, float)
    assert np.linalg.norm(img[5, 320].astype(float) - sky) > 10
    with pytest.raises(ValueError):
        r.render((np.nan, 0.0, 1.8, 0.0))


def test_visibility_order_far_before_near():
    # Camera at the origin looking along +z. Wall 0 at z = 5 (near) hides wall 1 at z = 20.
    seg = np.array([[[-2.0, 5.0], [2.0, 5.0]], [[-10.0, 20.0], [10.0, 20.0]],
                    [[30.0, 10.0], [40.0, 10.0]]])
    order = list(visibility_order(seg, np.array([5.0, 20.0, 10.0])))
    assert order.index(1) < order.index(0)
    # A long oblique side wall whose nearest point is closer than a short far wall that it
    # hides: distance sorting alone would get this wrong.
    seg = np.array([[[5.0, 2.0], [5.0, 80.0]], [[6.0, 60.0], [20.0, 60.0]]])
    order = list(visibility_order(seg, np.array([2.0, 60.0])))
    assert order == [1, 0]


# ============================================================================ faults
def test_faults_recorded_and_applied(stream):
    n = len(stream)
    assert set(np.unique(stream.fault)) <= {FAULT_CLEAN, FAULT_BLUR, FAULT_OCCLUSION}
    frac = np.mean(stream.fault != FAULT_CLEAN)
    assert 0.4 < frac < 0.6
    assert stream.info['fault_counts']['blur'] == np.sum(stream.fault == FAULT_BLUR)
    occ = stream.frames_with('occlusion')
    blur = stream.frames_with('blur')
    assert len(occ) > 20 and len(blur) > 20
    # Occlusion boxes: 25-50 % of width and height, inside the image, recorded.
    box = stream.fault_box[occ]
    assert np.all(box[:, 2] >= 0.25 * 640 - 1) and np.all(box[:, 2] <= 0.5 * 640 + 1)
    assert np.all(box[:, 3] >= 0.25 * 480 - 1) and np.all(box[:, 3] <= 0.5 * 480 + 1)
    assert np.all(box[:, 0] >= 0) and np.all(box[:, 0] + box[:, 2] <= 640)
    assert np.all(box[:, 1] >= 0) and np.all(box[:, 1] + box[:, 3] <= 480)
    assert np.all(stream.fault_box[stream.fault != FAULT_OCCLUSION] == -1)
    for i in occ[:3]:
        x, y, w, h = stream.fault_box[i]
        img = stream.image(i)
        patch = img[y:y + h, x:x + w].reshape(-1, 3)
        assert np.all(patch == stream.fault_colour[i])
        clean = stream.clean_image(i)
        outside = np.ones(img.shape[:2], bool)
        outside[y:y + h, x:x + w] = False
        assert np.array_equal(img[outside], clean[outside])
    # Blur: 21x21 Gaussian, Laplacian variance collapses.
    assert stream.blur_ksize == 21
    for i in blur[:3]:
        lap_b = cv2.Laplacian(cv2.cvtColor(stream.image(i), cv2.COLOR_BGR2GRAY), cv2.CV_64F)
        lap_c = cv2.Laplacian(cv2.cvtColor(stream.clean_image(i), cv2.COLOR_BGR2GRAY),
                              cv2.CV_64F)
        assert lap_b.var() < 0.2 * lap_c.var()
    for i in np.flatnonzero(stream.fault == FAULT_CLEAN)[:2]:
        assert np.array_equal(stream.image(i), stream.clean_image(i))
    assert len(stream.stamp_ns) == n and np.all(np.diff(stream.stamp_ns) == 100_000_000)


def test_fault_sets_nested_and_seeded(scenario):
    lo = make_camera_stream(scenario, duration_s=60.0, fault_fraction=0.1)
    hi = make_camera_stream(scenario, duration_s=60.0, fault_fraction=0.3)
    assert np.all(hi.fault[lo.fault != 0] == lo.fault[lo.fault != 0])
    assert lo.lighting == hi.lighting
    other = make_camera_stream(scenario, seed=SEED + 1, duration_s=60.0, fault_fraction=0.1)
    assert not np.array_equal(other.fault, lo.fault)
    none = make_camera_stream(scenario, duration_s=10.0, fault_fraction=0.0)
    assert np.all(none.fault == FAULT_CLEAN)
    with pytest.raises(ValueError):
        make_camera_stream(scenario, fault_fraction=1.5)
    with pytest.raises(ValueError):
        make_camera_stream(scenario, fault_kinds=('rain',))
    with pytest.raises(IndexError):
        lo.image(len(lo))


def test_with_camera_attaches_stream():
    drive = make_emulated_drive(SEED, duration_s=12.0)
    d2 = with_camera(drive)
    cam = d2.camera
    assert drive.camera is None and cam is not None
    assert len(cam) == 121 and cam.stamp_ns[0] == drive.truth.stamp_ns[0]
    assert cam.stamp_ns[-1] <= drive.truth.stamp_ns[-1]
    assert d2.info['camera']['n_frames'] == 121
    # Camera poses are the truth (antenna) positions.
    from gnsscam_ros.core.frames import LocalFrame
    enu = LocalFrame(*drive.origin_llh).ecef_to_enu(drive.truth.ecef_m)
    k = np.searchsorted(drive.truth.stamp_ns, cam.stamp_ns[50])
    assert np.allclose(cam.pose[50, :3], enu[k], atol=0.05)


# ============================================================================ database
@pytest.mark.slow
def test_database_pass(scenario):
    dbp = database_poses(scenario, margin_m=30.0)
    assert len(dbp) > 100 and dbp.kind.any()
    big = database_poses(scenario, margin_m=60.0)
    assert len(big) > len(dbp)
    # Nested: the 30 m pass is a subset of the 60 m pass (same random offsets).
    s = {tuple(np.round(p, 6)) for p in big.pose}
    assert all(tuple(np.round(p, 6)) in s for p in dbp.pose)
    # Other lighting than the query pass.
    assert dbp.lighting != make_camera_stream(scenario, duration_s=1.0).lighting
    # Offsets: street views lie 3 +- 1.5 m right of a street centre line, heading within
    # 5 deg of the street direction; both directions are present.
    city, street = scenario.city, dbp.pose[dbp.kind == 0]
    psi = street[:, 3]
    ns = np.abs(np.cos(psi)) < 0.5
    off_e = street[ns, 0][:, None] - city.street_e_m[None, :]
    d = off_e[np.arange(ns.sum()), np.argmin(np.abs(off_e), axis=1)]
    lateral = d * np.sign(np.sin(psi[ns]))        # right of travel when heading north
    assert np.all(lateral >= 1.5 - 1e-6) and np.all(lateral <= 4.5 + 1e-6)
    dev = np.degrees(np.abs((psi * 2 / np.pi - np.rint(psi * 2 / np.pi)) * np.pi / 2))
    assert np.all(dev <= 5.0 + 1e-6)
    assert np.any(np.sin(psi[ns]) > 0) and np.any(np.sin(psi[ns]) < 0)
    views = map_database_views(scenario, margin_m=30.0)
    name, img, e, n, u = next(views)
    assert name == dbp.names[0] and img.shape == (480, 640, 3)
    assert (e, n, u) == tuple(dbp.pose[0, :3])


@pytest.mark.slow
def test_retrieval_on_short_sequence(scenario, tmp_path):
    """A database over the first ~300 m of the route; clean frames match within 10 m."""
    t_end = 45.0
    s_end = float(np.interp(t_end, scenario.t_s, scenario.s_m))
    kw = dict(margin_m=20.0, route_range_m=(0.0, s_end), branching=8, depth=4,
              max_train_descriptors=60_000)
    db = build_emulated_map_database(scenario, cache_dir=tmp_path, **kw)
    assert 200 < len(db) < 1000
    files = os.listdir(tmp_path)
    assert len(files) == 1 and files[0].endswith('.npz')      # no temporary left behind
    # Cached: the second call loads the same database.
    db2 = build_emulated_map_database(scenario, cache_dir=tmp_path, **kw)
    assert db2.filenames == db.filenames
    assert np.array_equal(db2.index.images, db.index.images)
    stream = make_camera_stream(scenario, duration_s=t_end, fault_fraction=0.0)
    res = evaluate_retrieval(stream, db, frames=np.arange(0, len(stream), 3))
    assert res['by_kind']['clean']['n'] == len(res['frames'])
    assert res['by_kind']['clean']['top1'] >= 0.8, res['by_kind']
    # Positions are in the drive's ENU frame.
    assert np.allclose(db.positions.enu_m[:, 2], scenario.config.antenna_height_m)


def test_intrinsics_and_lighting_validation():
    cam = CameraIntrinsics()
    assert cam.fx == pytest.approx(320.0 / np.tan(np.radians(40.0)))
    assert cam.matrix[0, 2] == pytest.approx(319.5)
    with pytest.raises(ValueError):
        CameraIntrinsics(hfov_deg=200.0)
    with pytest.raises(ValueError):
        Lighting(gain=0.0)
    lut = Lighting(gain=1.0, gamma=1.0).lut()
    assert lut.shape == (1, 256, 3) and np.array_equal(lut[0, :, 0], np.arange(256))
    assert dataclasses.replace(Lighting(), gain=1.1) != Lighting()


def test_stream_pickles_without_its_caches(stream):
    import pickle
    stream.clean_image(3)                       # renderer and caches exist now
    blob = pickle.dumps(stream)
    assert len(blob) < 2_000_000                # no textures inside
    copy = pickle.loads(blob)
    assert np.array_equal(copy.image(3), stream.image(3))
