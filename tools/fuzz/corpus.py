"""The valid inputs the corrupt files are made from (generated once per ``files`` run).

* a dataset bag of a short emulated drive (``gnsscam_convert``'s writer), and the same
  with ``std_msgs/String`` on the input topics (a wrong-type bag);
* the same drive as smartLoc libRSF text (``pseudorange3``/``odom3`` input, ``point3``
  truth; times in seconds from the start);
* geotagged synthetic street images (JPEG), their positions CSV (local east/north) and
  the map database built from them (``gnsscam_mapdb``'s builder).
"""
from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from gnsscam_ros.bags import schema
from gnsscam_ros.bags.convert import convert_drive

from .stream import emulated_drive
from gnsscam_ros.vision.database import MapDatabase
from gnsscam_ros.vision.synthetic import synthetic_scene

N_IMAGES = 6


@dataclass(frozen=True)
class Corpus:
    """Paths of the valid inputs."""

    root: Path
    bag: Path
    wrong_type_bag: Path
    librsf_input: Path
    librsf_truth: Path
    images: Path
    positions: Path
    database: Path


def write_librsf(drive, input_path: Path, truth_path: Path, truth_step: int = 10) -> None:
    """A drive as smartLoc libRSF text (the loader's format; times from the first epoch)."""
    t0 = drive.gnss[0].stamp_ns

    def sec(ns):
        return f'{(int(ns) - t0) / 1e9:.9g}'

    def r(value) -> str:
        return repr(float(value))

    lines = []
    odo = drive.odometry
    for k in range(len(odo)):
        lines.append((int(odo.stamp_ns[k]), 0, (
            f'odom3 {sec(odo.stamp_ns[k])} {r(odo.speed_mps[k])} 0 0 0 0 '
            f'{r(odo.yaw_rate_rps[k])} {r(odo.speed_var[k])} 0.0009 0.0009 4e-06 4e-06 '
            f'{r(odo.yaw_rate_var[k])}')))
    for e in drive.gnss:
        for i in range(e.n_sv):
            x, y, z = e.sv_pos_ecef_m[i]
            lines.append((e.stamp_ns, 1, (
                f'pseudorange3 {sec(e.stamp_ns)} {r(e.pr_m[i])} {r(e.var_m2[i])} {r(x)} '
                f'{r(y)} {r(z)} {int(e.sv_id[i])} {int(e.system[i])} '
                f'{r(e.elevation_deg[i])} {r(e.cn0_dbhz[i])}')))
    lines.sort(key=lambda t: (t[0], t[1]))
    input_path.write_text(''.join(text + '\n' for _, _, text in lines), encoding='utf-8')
    truth = drive.truth
    rows = [f'point3 {sec(truth.stamp_ns[k])} ' + ' '.join(r(v) for v in truth.ecef_m[k])
            + ' 0 0 0 0 0 0 0 0 0' for k in range(0, len(truth), truth_step)]
    truth_path.write_text(''.join(r + '\n' for r in rows), encoding='utf-8')


def write_wrong_type_bag(good: Path, path: Path) -> None:
    """``good`` with ``std_msgs/msg/String`` on every input topic."""
    from rosbags.rosbag2 import Reader, StoragePlugin, Writer
    store = schema.typestore()
    text = bytes(store.serialize_cdr(store.types['std_msgs/msg/String'](data='x'),
                                     'std_msgs/msg/String'))
    inputs = {'/gnss/pseudoranges', '/imu/data', '/odom/twist', '/camera/image_raw'}
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer, \
            Reader(good) as reader:
        conns = {}
        for c in reader.connections:
            wrong = c.topic in inputs
            conns[c.id] = (writer.add_connection(
                c.topic, 'std_msgs/msg/String' if wrong else c.msgtype, typestore=store),
                wrong)
        for c, t, raw in reader.messages():
            conn, wrong = conns[c.id]
            writer.write(conn, t, text if wrong else raw)


def write_images(folder: Path, seed: int) -> Path:
    """Synthetic geotagged JPEG images and their positions CSV; the CSV path."""
    folder.mkdir(parents=True, exist_ok=True)
    rows = ['filename,east_m,north_m,up_m']
    for i in range(N_IMAGES):
        name = f'img_{i:03d}.jpg'
        cv2.imwrite(str(folder / name), synthetic_scene(i, seed=seed, shape=(240, 320)),
                    [cv2.IMWRITE_JPEG_QUALITY, 90])
        rows.append(f'{name},{10.0 * i:.1f},{2.0 * i:.1f},0.0')
    csv_path = folder.parent / 'positions.csv'
    csv_path.write_text('\n'.join(rows) + '\n', encoding='utf-8')
    return csv_path


def build_corpus(root: Path, seed: int) -> Corpus:
    """Every valid input, under ``root/base``."""
    base = Path(root) / 'base'
    if base.exists():
        shutil.rmtree(base)
    base.mkdir(parents=True)
    drive = emulated_drive(seed, 8.0, 0)
    bag = base / 'drive_bag'
    convert_drive(drive, bag)
    wrong = base / 'wrong_type_bag'
    write_wrong_type_bag(bag, wrong)
    write_librsf(drive, base / 'run_Input.txt', base / 'run_GT.txt')
    positions = write_images(base / 'images', seed)
    db = MapDatabase.build_from_files(base / 'images', positions, branching=8, depth=3,
                                      jobs=1)[0]
    database = base / 'map.npz'
    db.save(database)
    corpus = Corpus(root=base, bag=bag, wrong_type_bag=wrong,
                    librsf_input=base / 'run_Input.txt', librsf_truth=base / 'run_GT.txt',
                    images=base / 'images', positions=positions, database=database)
    for path in base.rglob('*'):          # readable by the unprivileged runs
        path.chmod(0o755 if path.is_dir() else 0o644)
    base.chmod(0o755)
    return corpus


def random_bytes(rng: np.random.Generator, n: int) -> bytes:
    return rng.bytes(int(n))
