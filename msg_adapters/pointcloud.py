"""sensor_msgs/PointCloud2 <-> numpy structured arrays, and the GNSS and camera-match clouds.

``sensor_msgs_py`` is not on PyPI, and the conversion is a dtype with the field offsets:
``np.frombuffer(msg.data, dtype)`` reads a cloud without a Python loop and
``array.tobytes()`` writes one.

Layouts (design.md §3):

* ``gnss/pseudoranges``, ``gnss/measurements`` (frame ``earth``): ``x y z`` FLOAT64 satellite
  ECEF position [m], ``pseudorange`` FLOAT64 [m], ``variance`` FLOAT32 [m^2], ``cn0`` FLOAT32
  [dB-Hz], ``elevation`` FLOAT32 [deg], ``sv_id`` UINT16, ``system`` UINT8.
* ``camera/matches`` (frame ``map``): ``x y z`` FLOAT64 [m], ``score`` FLOAT32,
  ``image_id`` UINT32, best match first.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header

from gnsscam_ros.core.types import GnssEpoch

from .errors import MessageError
from .stamps import ns_to_stamp, stamp_to_ns

# PointField datatype constant <-> numpy scalar type.
_DATATYPES = {
    PointField.INT8: np.int8, PointField.UINT8: np.uint8,
    PointField.INT16: np.int16, PointField.UINT16: np.uint16,
    PointField.INT32: np.int32, PointField.UINT32: np.uint32,
    PointField.FLOAT32: np.float32, PointField.FLOAT64: np.float64,
}
_TYPE_NAMES = {PointField.INT8: 'INT8', PointField.UINT8: 'UINT8', PointField.INT16: 'INT16',
               PointField.UINT16: 'UINT16', PointField.INT32: 'INT32',
               PointField.UINT32: 'UINT32', PointField.FLOAT32: 'FLOAT32',
               PointField.FLOAT64: 'FLOAT64'}
_DATATYPE_OF = {np.dtype(v): k for k, v in _DATATYPES.items()}

GNSS_FRAME = 'earth'
MAP_FRAME = 'map'

GNSS_DTYPE = np.dtype({
    'names': ['x', 'y', 'z', 'pseudorange', 'variance', 'cn0', 'elevation', 'sv_id', 'system'],
    'formats': ['<f8', '<f8', '<f8', '<f8', '<f4', '<f4', '<f4', '<u2', 'u1'],
    'offsets': [0, 8, 16, 24, 32, 36, 40, 44, 46], 'itemsize': 48})

MATCH_DTYPE = np.dtype({
    'names': ['x', 'y', 'z', 'score', 'image_id'],
    'formats': ['<f8', '<f8', '<f8', '<f4', '<u4'],
    'offsets': [0, 8, 16, 24, 28], 'itemsize': 32})

# Satellite systems of the `system` field (1 GPS, 2 SBAS, 4 GLONASS, 8 Galileo, 16 QZSS,
# 32 BeiDou).
KNOWN_SYSTEMS = (1, 2, 4, 8, 16, 32)


def structured_to_pointcloud2(points: np.ndarray, stamp_ns: int, frame_id: str) -> PointCloud2:
    """Pack a 1-D structured array into an unordered (height 1) PointCloud2.

    Args:
        points: (n,) structured array of scalar numeric fields.
        stamp_ns: Header stamp [ns].
        frame_id: Header frame.

    Raises:
        MessageError: A field is not a scalar of a PointField type.
    """
    points = np.ascontiguousarray(points)
    if points.dtype.names is None or points.ndim != 1:
        raise MessageError('points must be a 1-D structured array', 'fields')
    fields = []
    for name in points.dtype.names:
        dtype, offset = points.dtype.fields[name][:2]
        if dtype.shape or np.dtype(dtype.type) not in _DATATYPE_OF:
            raise MessageError(f'field {name!r} has unsupported type {dtype}', 'fields')
        if dtype.byteorder == '>':
            raise MessageError(f'field {name!r} is big-endian; use little-endian', 'fields')
        fields.append(PointField(name=name, offset=offset,
                                 datatype=_DATATYPE_OF[np.dtype(dtype.type)], count=1))
    msg = PointCloud2(header=Header(stamp=ns_to_stamp(stamp_ns), frame_id=frame_id),
                      height=1, width=int(points.shape[0]), fields=fields,
                      is_bigendian=False, point_step=points.dtype.itemsize,
                      row_step=points.dtype.itemsize * int(points.shape[0]), is_dense=True)
    msg.data = points.tobytes()
    return msg


def pointcloud2_to_structured(msg: PointCloud2, wanted: np.dtype, what: str = 'cloud'
                              ) -> np.ndarray:
    """Read the fields of ``wanted`` from a PointCloud2 (other fields are ignored).

    Args:
        msg: The cloud (any height, padding and field order; either byte order).
        wanted: Structured dtype naming the fields and their exact numeric types.
        what: Name used in error messages (e.g. the topic).

    Returns:
        (height * width,) packed array of dtype ``wanted`` (a copy).

    Raises:
        MessageError: A wanted field is missing or has another type or count, or the
            buffer sizes are inconsistent.
    """
    by_name = {f.name: f for f in msg.fields}
    names, formats, offsets = [], [], []
    order = '>' if msg.is_bigendian else '<'
    for name in wanted.names:
        want_type = np.dtype(wanted.fields[name][0].type)
        field = by_name.get(name)
        if field is None:
            raise MessageError(f'{what}: field {name!r} missing (has '
                               f'{sorted(by_name) or "no fields"})', 'fields')
        got = _DATATYPES.get(field.datatype)
        if got is None or np.dtype(got) != want_type or field.count != 1:
            raise MessageError(
                f'{what}: field {name!r} is {_TYPE_NAMES.get(field.datatype, field.datatype)}'
                f' x{field.count}, expected {_TYPE_NAMES[_DATATYPE_OF[want_type]]} x1',
                'fields')
        if field.offset + want_type.itemsize > msg.point_step:
            raise MessageError(f'{what}: field {name!r} at offset {field.offset} overruns '
                               f'point_step {msg.point_step}', 'size')
        names.append(name)
        formats.append(want_type.newbyteorder(order))
        offsets.append(field.offset)
    width, height = int(msg.width), int(msg.height)
    if msg.row_step < width * msg.point_step:
        raise MessageError(f'{what}: row_step {msg.row_step} < width {width} x point_step '
                           f'{msg.point_step}', 'size')
    raw = np.frombuffer(msg.data, dtype=np.uint8)
    if raw.size != msg.row_step * height:
        raise MessageError(f'{what}: {raw.size} data bytes, expected row_step x height = '
                           f'{msg.row_step * height}', 'size')
    layout = np.dtype({'names': names, 'formats': formats, 'offsets': offsets,
                       'itemsize': msg.point_step})
    out = np.empty(width * height, dtype=wanted)
    if width * height == 0:
        return out
    rows = raw.reshape(height, msg.row_step)[:, :width * msg.point_step]
    src = np.ascontiguousarray(rows).view(layout).reshape(-1)
    for name in names:
        out[name] = src[name]
    return out


# ---------------------------------------------------------------------------- GNSS
def gnss_epoch_to_pointcloud2(epoch: GnssEpoch, frame_id: str = GNSS_FRAME) -> PointCloud2:
    """One receiver epoch -> the ``gnss/pseudoranges`` cloud (one point per satellite).

    ``variance``, ``cn0`` and ``elevation`` are FLOAT32 on the wire: values are rounded.
    """
    pts = np.zeros(epoch.n_sv, dtype=GNSS_DTYPE)
    sv = np.asarray(epoch.sv_pos_ecef_m, dtype=float).reshape(-1, 3)
    pts['x'], pts['y'], pts['z'] = sv[:, 0], sv[:, 1], sv[:, 2]
    pts['pseudorange'] = epoch.pr_m
    pts['variance'] = epoch.var_m2
    pts['cn0'] = epoch.cn0_dbhz
    pts['elevation'] = epoch.elevation_deg
    sv_id = np.asarray(epoch.sv_id)
    system = np.asarray(epoch.system)
    if sv_id.size and (sv_id.min() < 0 or sv_id.max() > 65535):
        raise MessageError('sv_id does not fit UINT16', 'value')
    if system.size and (system.min() < 0 or system.max() > 255):
        raise MessageError('system does not fit UINT8', 'value')
    pts['sv_id'] = sv_id
    pts['system'] = system
    return structured_to_pointcloud2(pts, epoch.stamp_ns, frame_id)


def pointcloud2_to_gnss_epoch(msg: PointCloud2, frame_id: str | None = GNSS_FRAME,
                              what: str = 'gnss/pseudoranges') -> GnssEpoch:
    """The ``gnss/pseudoranges`` cloud -> :class:`GnssEpoch`.

    Non-finite values are passed through: judging satellites (NaN, duplicates, masks) is
    :func:`gnsscam_ros.core.gnss.check_epoch`'s job, which counts what it drops.

    Args:
        msg: The cloud.
        frame_id: Required header frame (None: any).
        what: Name used in error messages.

    Raises:
        MessageError: Wrong frame, missing or mistyped fields, inconsistent sizes.
    """
    if frame_id is not None and msg.header.frame_id != frame_id:
        raise MessageError(f'{what}: frame {msg.header.frame_id!r}, expected {frame_id!r} '
                           '(ECEF)', 'frame')
    pts = pointcloud2_to_structured(msg, GNSS_DTYPE, what)
    return GnssEpoch(
        stamp_ns=stamp_to_ns(msg.header.stamp),
        sv_pos_ecef_m=np.column_stack([pts['x'], pts['y'], pts['z']]).astype(float),
        pr_m=pts['pseudorange'].astype(float), var_m2=pts['variance'].astype(float),
        sv_id=pts['sv_id'].astype(np.int64), system=pts['system'].astype(np.int64),
        elevation_deg=pts['elevation'].astype(float), cn0_dbhz=pts['cn0'].astype(float))


# -------------------------------------------------------------------- camera matches
@dataclass(frozen=True)
class CameraMatches:
    """Top-k database matches of one camera image, best first.

    Attributes:
        stamp_ns: Image stamp [ns].
        position_m: (k, 3) matched image positions in the map frame [m].
        score: (k,) retrieval similarity scores.
        image_id: (k,) database image indices.
        frame_id: Header frame (``map``).
    """

    stamp_ns: int
    position_m: np.ndarray
    score: np.ndarray
    image_id: np.ndarray
    frame_id: str = MAP_FRAME

    def __len__(self) -> int:
        return int(self.score.shape[0])


def matches_to_pointcloud2(matches: CameraMatches) -> PointCloud2:
    """:class:`CameraMatches` -> the ``camera/matches`` cloud.

    Raises:
        MessageError: Non-finite positions or scores, or mismatched lengths.
    """
    pos = np.asarray(matches.position_m, dtype=float).reshape(-1, 3)
    score = np.asarray(matches.score, dtype=float).reshape(-1)
    ids = np.asarray(matches.image_id).reshape(-1)
    if not pos.shape[0] == score.shape[0] == ids.shape[0]:
        raise MessageError('positions, scores and image ids differ in length', 'value')
    if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(score))):
        raise MessageError('camera matches must be finite', 'non_finite')
    pts = np.zeros(pos.shape[0], dtype=MATCH_DTYPE)
    pts['x'], pts['y'], pts['z'] = pos[:, 0], pos[:, 1], pos[:, 2]
    pts['score'] = score
    pts['image_id'] = ids
    return structured_to_pointcloud2(pts, matches.stamp_ns, matches.frame_id)


def pointcloud2_to_matches(msg: PointCloud2, frame_id: str | None = MAP_FRAME,
                           what: str = 'camera/matches') -> CameraMatches:
    """The ``camera/matches`` cloud -> :class:`CameraMatches`.

    Raises:
        MessageError: Wrong frame or fields, or non-finite positions or scores.
    """
    if frame_id is not None and msg.header.frame_id != frame_id:
        raise MessageError(f'{what}: frame {msg.header.frame_id!r}, expected {frame_id!r}',
                           'frame')
    pts = pointcloud2_to_structured(msg, MATCH_DTYPE, what)
    pos = np.column_stack([pts['x'], pts['y'], pts['z']]).astype(float)
    score = pts['score'].astype(float)
    if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(score))):
        raise MessageError(f'{what}: non-finite position or score', 'non_finite')
    return CameraMatches(stamp_ns=stamp_to_ns(msg.header.stamp), position_m=pos, score=score,
                         image_id=pts['image_id'].astype(np.int64),
                         frame_id=msg.header.frame_id)
