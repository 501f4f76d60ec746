"""sensor_msgs/PointCloud2 <-> numpy structured arrays, and the GNSS and camera-match clouds.

``sensor_msgs_py`` is not on PyPI, and the conversion is a dtype with the field offsets:
``np.frombuffer(msg.data, dtype)`` reads a cloud without a Python loop and
``array.tobytes()`` writes one.

Layouts: :data:`.wire.GNSS_DTYPE` (``gnss/pseudoranges``, ``gnss/measurements``, frame
``earth``) and :data:`.wire.MATCH_DTYPE` (``camera/matches``, frame ``map``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gnsscam_ros.core.types import GnssEpoch

from .checks import check_abs, check_count, check_range
from .errors import MessageError
from .message_classes import RCLPY, MessageKit
from .limits import (MAX_ABS_ELEVATION_DEG, MAX_CN0_DBHZ, MAX_MATCH_SCORE, MAX_MATCHES,
                     MAX_MESSAGE_BYTES, MAX_POINT_STEP_BYTES, MAX_POSITION_M,
                     MAX_MESSAGE_PSEUDORANGE_M, MAX_MESSAGE_SATELLITE_RADIUS_M,
                     MAX_MESSAGE_SATELLITES, MAX_VARIANCE, MIN_CN0_DBHZ, MIN_MATCH_SCORE,
                     MIN_MESSAGE_PSEUDORANGE_M, MIN_MESSAGE_SATELLITE_RADIUS_M)
from .stamps import make_header, stamp_to_ns
from .wire import (EARTH_FRAME, GNSS, GNSS_DTYPE, KNOWN_SYSTEMS, MAP_FRAME, MATCH_DTYPE,
                   MATCHES, POINTFIELD_CODE, POINTFIELD_NAMES, POINTFIELD_TYPES, header_dims)


def structured_to_pointcloud2(points: np.ndarray, stamp_ns: int, frame_id: str,
                              is_dense: bool = True, kit: MessageKit = RCLPY):
    """Pack a 1-D structured array into an unordered (height 1) PointCloud2.

    Args:
        points: (n,) structured array of scalar numeric fields.
        stamp_ns: Header stamp [ns].
        frame_id: Header frame.
        is_dense: The cloud has no invalid (non-finite) points.
        kit: Message classes to build with (:mod:`.message_classes`).

    Raises:
        MessageError: A field is not a scalar of a PointField type.
    """
    points = np.ascontiguousarray(points)
    if points.dtype.names is None or points.ndim != 1:
        raise MessageError('points must be a 1-D structured array', 'fields')
    point_field = kit['sensor_msgs/msg/PointField']
    fields = []
    for name in points.dtype.names:
        dtype, offset = points.dtype.fields[name][:2]
        if dtype.shape or np.dtype(dtype.type) not in POINTFIELD_CODE:
            raise MessageError(f'field {name!r} has unsupported type {dtype}', 'fields')
        if dtype.byteorder == '>':
            raise MessageError(f'field {name!r} is big-endian; use little-endian', 'fields')
        fields.append(point_field(name=name, offset=offset,
                                  datatype=POINTFIELD_CODE[np.dtype(dtype.type)], count=1))
    n = int(points.shape[0])
    return kit['sensor_msgs/msg/PointCloud2'](
        header=make_header(stamp_ns, frame_id, kit), height=1, width=n, fields=fields,
        is_bigendian=False, point_step=points.dtype.itemsize,
        row_step=points.dtype.itemsize * n, data=kit.octets(points), is_dense=bool(is_dense))


def pointcloud2_to_structured(msg, wanted: np.dtype, what: str = 'cloud',
                              max_points: int | None = None) -> np.ndarray:
    """Read the fields of ``wanted`` from a PointCloud2 (other fields are ignored).

    Args:
        msg: The cloud (any height, padding and field order; either byte order).
        wanted: Structured dtype naming the fields and their exact numeric types.
        what: Name used in error messages (e.g. the topic).
        max_points: Most points accepted (None: any), checked from ``width`` and
            ``height`` before anything is decoded.

    Returns:
        (height * width,) packed array of dtype ``wanted`` (a copy).

    Raises:
        MessageError: More than ``max_points`` points or more than
            :data:`.limits.MAX_POINT_STEP_BYTES` per point (reason ``'size'``), a wanted field
            missing or of another type or count, or inconsistent buffer sizes.
    """
    if max_points is not None:
        check_count(int(msg.width) * int(msg.height), max_points, what, 'points')
    if msg.point_step > MAX_POINT_STEP_BYTES:
        raise MessageError(f'{what}: point_step {msg.point_step} bytes, at most '
                           f'{MAX_POINT_STEP_BYTES}', 'size')
    by_name = {f.name: f for f in msg.fields}
    names, formats, offsets = [], [], []
    order = '>' if msg.is_bigendian else '<'
    for name in wanted.names:
        want_type = np.dtype(wanted.fields[name][0].type)
        field = by_name.get(name)
        if field is None:
            raise MessageError(f'{what}: field {name!r} missing (has '
                               f'{sorted(by_name) or "no fields"})', 'fields')
        got = POINTFIELD_TYPES.get(field.datatype)
        if got is None or np.dtype(got) != want_type or field.count != 1:
            raise MessageError(
                f'{what}: field {name!r} is '
                f'{POINTFIELD_NAMES.get(field.datatype, field.datatype)} x{field.count}, '
                f'expected {POINTFIELD_NAMES[POINTFIELD_CODE[want_type]]} x1',
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


def check_serialized_cloud(raw: bytes, max_points: int, what: str = 'cloud',
                           noun: str = 'points') -> None:
    """Refuse a CDR-serialised PointCloud2 of more than ``max_points`` points (from its
    ``height`` and ``width``) or more bytes than they may take, before it is decoded
    (reason ``'size'``)."""
    dims = header_dims(raw)
    if dims is not None:
        check_count(dims[0] * dims[1], max_points, what, noun)
    limit = max_points * MAX_POINT_STEP_BYTES + MAX_MESSAGE_BYTES
    if len(raw) > limit:
        raise MessageError(f'{what}: {len(raw)} bytes, at most {limit}', 'size')


def check_serialized_gnss(raw: bytes, what: str = GNSS) -> None:
    """:func:`check_serialized_cloud` with :data:`.limits.MAX_MESSAGE_SATELLITES`."""
    check_serialized_cloud(raw, MAX_MESSAGE_SATELLITES, what, 'satellites')


def check_serialized_matches(raw: bytes, what: str = MATCHES) -> None:
    """:func:`check_serialized_cloud` with :data:`.limits.MAX_MATCHES`."""
    check_serialized_cloud(raw, MAX_MATCHES, what, 'matches')


# ---------------------------------------------------------------------------- GNSS
def gnss_epoch_to_pointcloud2(epoch: GnssEpoch, frame_id: str = EARTH_FRAME,
                              kit: MessageKit = RCLPY):
    """One receiver epoch -> the ``gnss/pseudoranges`` cloud (one point per satellite).

    ``variance``, ``cn0`` and ``elevation`` are FLOAT32 on the wire: values are rounded.
    ``is_dense`` tells whether every satellite position is finite.

    Raises:
        MessageError: ``sv_id`` or ``system`` out of the range of its field.
    """
    n = epoch.n_sv
    sv = np.asarray(epoch.sv_pos_ecef_m, dtype=float).reshape(-1, 3)
    sv_id = np.asarray(epoch.sv_id)
    system = np.asarray(epoch.system)
    if n and (sv_id.min() < 0 or sv_id.max() > 65535):
        raise MessageError('sv_id does not fit UINT16', 'value')
    if n and (system.min() < 0 or system.max() > 255):
        raise MessageError('system does not fit UINT8', 'value')
    pts = np.zeros(n, dtype=GNSS_DTYPE)
    pts['x'], pts['y'], pts['z'] = sv[:, 0], sv[:, 1], sv[:, 2]
    pts['pseudorange'] = epoch.pr_m
    pts['variance'] = epoch.var_m2
    pts['cn0'] = epoch.cn0_dbhz
    pts['elevation'] = epoch.elevation_deg
    pts['sv_id'] = sv_id
    pts['system'] = system
    return structured_to_pointcloud2(pts, epoch.stamp_ns, frame_id,
                                     is_dense=bool(np.all(np.isfinite(sv))), kit=kit)


def pointcloud2_to_gnss_epoch(msg, frame_id: str | None = EARTH_FRAME,
                              what: str = GNSS, checked: bool = False) -> GnssEpoch:
    """The ``gnss/pseudoranges`` cloud -> :class:`GnssEpoch`.

    Receivers mark a satellite without a measurement with NaN (or infinity) or a
    non-positive range or variance: such satellites are passed through, since judging
    them is :func:`gnsscam_ros.core.gnss.check_epoch`'s job, which drops and counts them.
    Every other value must be plausible (:mod:`.limits`), else the whole message is
    refused: a corrupt value is no satellite to drop but a message not to trust.

    Args:
        msg: The cloud.
        frame_id: Required header frame (None: any).
        what: Name used in error messages.
        checked: The satellites have passed ``check_epoch`` (``gnss/measurements``):
            non-finite positions, ranges or variances and non-positive variances are
            refused too, and so is a satellite twice (the same ``system`` and ``sv_id``;
            ``'duplicate_satellites'``) or of a ``system`` code not in
            :data:`.wire.KNOWN_SYSTEMS` (``'unknown_system'``): gnss_node drops those.
            Elevation and C/N0 may still be NaN (unknown) in both cases.

    Raises:
        MessageError: Wrong frame, more than :data:`.limits.MAX_MESSAGE_SATELLITES` satellites
            (``'size'``, before decoding), missing or mistyped fields, inconsistent sizes,
            an invalid stamp, or an implausible value (``'range'``, ``'non_finite'``).
    """
    if frame_id is not None and msg.header.frame_id != frame_id:
        raise MessageError(f'{what}: frame {msg.header.frame_id!r}, expected {frame_id!r} '
                           '(ECEF)', 'frame')
    check_count(int(msg.width) * int(msg.height), MAX_MESSAGE_SATELLITES, what, 'satellites')
    stamp_ns = stamp_to_ns(msg.header.stamp, what)
    pts = pointcloud2_to_structured(msg, GNSS_DTYPE, what)
    sv = np.column_stack([pts['x'], pts['y'], pts['z']]).astype(float)
    pr, var = pts['pseudorange'].astype(float), pts['variance'].astype(float)
    cn0, elevation = pts['cn0'].astype(float), pts['elevation'].astype(float)
    _check_satellites(what, sv, pr, var, checked)
    if checked:
        _check_identities(what, pts['sv_id'], pts['system'])
    check_range(what, 'C/N0', cn0, MIN_CN0_DBHZ, MAX_CN0_DBHZ, ' dB-Hz', allow_nan=True)
    check_range(what, 'elevation', elevation, -MAX_ABS_ELEVATION_DEG, MAX_ABS_ELEVATION_DEG,
                ' deg', allow_nan=True)
    return GnssEpoch(
        stamp_ns=stamp_ns, sv_pos_ecef_m=sv, pr_m=pr, var_m2=var,
        sv_id=pts['sv_id'].astype(np.int64), system=pts['system'].astype(np.int64),
        elevation_deg=elevation, cn0_dbhz=cn0)


def _check_satellites(what: str, sv: np.ndarray, pr: np.ndarray, var: np.ndarray,
                      checked: bool) -> None:
    """Satellite positions, pseudoranges and variances against :mod:`.limits` (see
    :func:`pointcloud2_to_gnss_epoch`)."""
    finite = np.isfinite(sv).all(axis=1) & np.isfinite(pr) & np.isfinite(var)
    if checked:
        if not finite.all():
            raise MessageError(f'{what}: non-finite satellite position, pseudorange or '
                               'variance', 'non_finite')
        if (var <= 0.0).any():
            raise MessageError(f'{what}: non-positive variance', 'range')
    # Only what a receiver cannot mean as "no measurement" is judged here.
    rows = finite & (pr > 0.0) & (var > 0.0) if not checked else finite
    if not rows.any():
        return
    # Coordinates first: the norm of a 1e160 coordinate overflows to infinity.
    check_abs(what, 'satellite coordinate', sv[rows], MAX_MESSAGE_SATELLITE_RADIUS_M, ' m')
    check_range(what, 'satellite radius', np.linalg.norm(sv[rows], axis=1),
                MIN_MESSAGE_SATELLITE_RADIUS_M, MAX_MESSAGE_SATELLITE_RADIUS_M, ' m')
    check_range(what, 'pseudorange', pr[rows], MIN_MESSAGE_PSEUDORANGE_M,
                MAX_MESSAGE_PSEUDORANGE_M, ' m')
    check_range(what, 'variance', var[rows], 0.0, MAX_VARIANCE, ' m^2')


def _check_identities(what: str, sv_id: np.ndarray, system: np.ndarray) -> None:
    """Known system codes, each satellite once (see :func:`pointcloud2_to_gnss_epoch`)."""
    known = np.isin(system, KNOWN_SYSTEMS)
    if not known.all():
        raise MessageError(f'{what}: system code {int(system[~known][0])} is none of '
                           f'{KNOWN_SYSTEMS}', 'unknown_system')
    key = system.astype(np.int64) * 65536 + sv_id.astype(np.int64)
    unique, counts = np.unique(key, return_counts=True)
    if (counts > 1).any():
        twice = int(unique[counts > 1][0])
        raise MessageError(f'{what}: satellite {twice % 65536} of system {twice // 65536} '
                           f'{int(counts.max())} times', 'duplicate_satellites')


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


def matches_to_pointcloud2(matches: CameraMatches, kit: MessageKit = RCLPY):
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
    return structured_to_pointcloud2(pts, matches.stamp_ns, matches.frame_id, kit=kit)


def pointcloud2_to_matches(msg, frame_id: str | None = MAP_FRAME,
                           what: str = MATCHES) -> CameraMatches:
    """The ``camera/matches`` cloud -> :class:`CameraMatches`.

    Raises:
        MessageError: Wrong frame or fields, more than :data:`.limits.MAX_MATCHES` matches
            (``'size'``, before decoding), an invalid stamp, non-finite positions or
            scores, positions beyond :data:`.limits.MAX_POSITION_M` or scores outside
            camera_node's [0, 1] (``'range'``).
    """
    if frame_id is not None and msg.header.frame_id != frame_id:
        raise MessageError(f'{what}: frame {msg.header.frame_id!r}, expected {frame_id!r}',
                           'frame')
    check_count(int(msg.width) * int(msg.height), MAX_MATCHES, what, 'matches')
    stamp_ns = stamp_to_ns(msg.header.stamp, what)
    pts = pointcloud2_to_structured(msg, MATCH_DTYPE, what)
    pos = np.column_stack([pts['x'], pts['y'], pts['z']]).astype(float)
    score = pts['score'].astype(float)
    if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(score))):
        raise MessageError(f'{what}: non-finite position or score', 'non_finite')
    check_abs(what, 'match position', pos, MAX_POSITION_M, ' m')
    check_range(what, 'match score', score, MIN_MATCH_SCORE, MAX_MATCH_SCORE)
    return CameraMatches(stamp_ns=stamp_ns, position_m=pos, score=score,
                         image_id=pts['image_id'].astype(np.int64),
                         frame_id=msg.header.frame_id)
