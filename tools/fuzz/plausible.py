"""Is a faulty message still a valid one? The kit's own judgement, for the accounting.

A random mutation (and a structured fault of random size, such as a flipped exponent bit)
may leave a message every value of which is physically plausible: a pseudorange doubled
to 4.4e7 m, a speed halved, a pixel changed. Such a message is not malformed (a faulty
measurement at most, which is the filter's business, not the boundary's): a node may take
it. The accounting must tell these apart from malformed messages a node takes silently,
without asking the nodes' own validator (``msg_adapters``' parsers), which would classify
away exactly the gaps it has. So the judgement here is written apart from it, from the
documentation: the wire contract (``msg_adapters.wire``: topics, frames, point layouts,
system codes) and the table of physical limits of the README (its numbers are those of
``msg_adapters.limits``, read here as data).

:func:`judge` compares the faulty message with the valid one it was made from:

* raw bytes (a CDR-level mutation) are decoded first, as the subscriber receives them:
  Fast DDS pads a serialised payload with zeros to a multiple of 4 bytes on the way
  between processes (measured: 321, 322 and 323 bytes sent arrive as 324), so a buffer cut
  short by 1-3 bytes can arrive whole again, the valid message when the bytes cut were
  zeros; what does not decode is malformed;
* nothing changed (a flipped padding bit, a value set to what it was): valid;
* the stamp: a ``builtin_interfaces/Time`` (``sec`` >= 0, ``nanosec`` < 1e9) within the
  stamp window (60 s) of the original stamp (that one follows the stream): valid; a stamp
  behind the stream is still valid as a value (the node orders it: ``out_of_order``);
* the frames a topic is defined in (``gnss/*``: ``earth``; ``camera/matches``: ``map``;
  ``odometry/dead_reckoning``: ``odom``, child ``base_link``); the sensors' own frames
  (IMU, odometry twist, camera) are the installation's: any;
* the layout of clouds and images must still describe their buffer (the fields the
  contract names, with their types, inside ``point_step``; ``row_step``, ``height``,
  ``step`` and the buffer length agreeing; the size limits); the values are then decoded
  here and judged;
* every value in its physical domain (README table), and the structure physics asks for:
  covariances with variances in [0, 1e14] and correlations of at most 1, unit quaternions
  (tf2's tolerance), each satellite once and of a known system; a receiver's marks of a
  missing measurement (NaN, a non-positive range or variance) make a malformed satellite
  (gnss_node drops it and counts it).

Anything else is malformed: a node must refuse it (or, for satellites of the receiver's
epochs, drop and count them).
"""
from __future__ import annotations

import math
import os
import sys
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
from rclpy.serialization import deserialize_message

from msg_adapters import limits as lim
from msg_adapters import wire

from .graph import TOPIC_TYPES

#: Frames of the topics whose frame the contract defines (header, child).
EXPECTED_FRAMES = {wire.GNSS: (wire.EARTH_FRAME, None),
                   wire.GNSS_MEASUREMENTS: (wire.EARTH_FRAME, None),
                   wire.MATCHES: (wire.MAP_FRAME, None),
                   wire.DEAD_RECKONING: (wire.ODOM_FRAME, wire.BASE_FRAME)}
#: Image encodings of the contract -> channels (8-bit samples).
IMAGE_CHANNELS = {'mono8': 1, 'bgr8': 3, 'rgb8': 3}
#: A serialised payload reaches another process padded with zeros to this many bytes.
PAYLOAD_ALIGNMENT = 4
#: PointField datatype codes -> numpy types (sensor_msgs/PointField).
_POINTFIELD = {1: 'i1', 2: 'u1', 3: 'i2', 4: 'u2', 5: 'i4', 6: 'u4', 7: 'f4', 8: 'f8'}


@dataclass(frozen=True)
class Judgement:
    """``valid``: the faulty message is a plausible one; ``why``: in a few words."""

    valid: bool
    why: str


def _valid(why: str) -> Judgement:
    return Judgement(True, why)


@contextmanager
def _quiet_stderr():
    """The C++ deserialiser prints some of its refusals on stderr ("sequence size exceeds
    remaining buffer") before it raises: not the kit's progress."""
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, 'w') as null:
            os.dup2(null.fileno(), 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


class _Malformed(Exception):
    pass


def _need(condition, why: str) -> None:
    if not condition:
        raise _Malformed(why)


def judge(topic: str, original, faulty) -> Judgement:
    """The judgement of ``faulty`` (a message or raw CDR bytes) made from the valid
    ``original`` of ``topic``."""
    if isinstance(faulty, (bytes, bytearray)):
        delivered = bytes(faulty) + bytes(-len(faulty) % PAYLOAD_ALIGNMENT)
        try:
            with _quiet_stderr():
                faulty = deserialize_message(delivered, TOPIC_TYPES[topic])
        except Exception as err:     # noqa: BLE001 - rclpy raises several kinds
            return Judgement(False, f'undecodable ({type(err).__name__})')
    try:
        if faulty == original:
            return _valid('unchanged')
        _stamp(original, faulty)
        _frames(topic, faulty)
        check = {wire.GNSS: _gnss, wire.GNSS_MEASUREMENTS: _gnss, wire.MATCHES: _matches,
                 wire.IMU: _imu, wire.TWIST: _twist, wire.DEAD_RECKONING: _odometry,
                 wire.IMAGE: _image}[topic]
        check(topic, faulty)
    except _Malformed as err:
        return Judgement(False, str(err))
    except (ValueError, TypeError, OverflowError) as err:   # e.g. a size beyond numpy's
        return Judgement(False, f'unreadable ({err})'[:80])
    return _valid('plausible values')


# ---------------------------------------------------------------------- header
def _stamp(original, msg) -> None:
    sec, nanosec = int(msg.header.stamp.sec), int(msg.header.stamp.nanosec)
    _need(lim.MIN_STAMP_SEC <= sec <= lim.MAX_STAMP_SEC and 0 <= nanosec <= lim.MAX_NANOSEC,
          f'stamp {sec} s {nanosec} ns is no builtin_interfaces/Time')
    o = original.header.stamp
    offset = (sec - int(o.sec)) * wire.NS_PER_S + nanosec - int(o.nanosec)
    _need(abs(offset) <= lim.STAMP_WINDOW_NS,
          f'stamp {offset / 1e9:+.3g} s away from the stream')


def _frames(topic: str, msg) -> None:
    frame, child = EXPECTED_FRAMES.get(topic, (None, None))
    _need(frame is None or msg.header.frame_id == frame,
          f'frame {msg.header.frame_id!r}, not {frame!r}')
    if child is not None:
        _need(msg.child_frame_id == child, f'child frame {msg.child_frame_id!r}, not {child!r}')


# ---------------------------------------------------------------------- numbers
def _finite(name: str, *values) -> None:
    _need(all(math.isfinite(float(v)) for v in values), f'non-finite {name}')


def _within(name: str, values, limit: float) -> None:
    values = np.asarray(values, dtype=float)
    _need(np.isfinite(values).all(), f'non-finite {name}')
    _need((np.abs(values) <= limit).all(), f'{name} beyond {limit:g}')


def _covariance(name: str, flat) -> None:
    c = np.asarray(flat, dtype=float)
    n = int(round(math.sqrt(c.size)))
    c = c.reshape(n, n)
    _need(np.isfinite(c).all(), f'non-finite {name}')
    tol = lim.COVARIANCE_TOLERANCE
    var = np.diagonal(c)
    _need(((var >= -tol) & (var <= lim.MAX_VARIANCE)).all(),
          f'{name}: a variance outside [0, {lim.MAX_VARIANCE:g}]')
    sd = np.sqrt(np.clip(var, 0.0, None))
    for i in range(n):
        for j in range(n):
            _need(i == j or abs(c[i, j]) <= sd[i] * sd[j] + tol,
                  f'{name}: correlation ({i}, {j}) above 1')


def _unit_quaternion(name: str, q) -> None:
    x, y, z, w = (float(v) for v in (q.x, q.y, q.z, q.w))
    _finite(name, x, y, z, w)
    norm2 = math.fsum([x * x, y * y, z * z, w * w]) if max(map(abs, (x, y, z, w))) < 1e150 \
        else math.inf
    _need(abs(norm2 - 1.0) <= lim.QUATERNION_NORM_TOLERANCE, f'{name} is no unit quaternion')


def _twist_values(twist) -> None:
    lin, ang = twist.linear, twist.angular
    _within('speed', [lin.x, lin.y, lin.z], lim.MAX_SPEED_MPS)
    _within('roll or pitch rate', [ang.x, ang.y], lim.MAX_GYRO_RPS)
    _within('yaw rate', [ang.z], lim.MAX_MESSAGE_YAW_RATE_RPS)


# ---------------------------------------------------------------------- messages
def _imu(topic: str, msg) -> None:
    _need(msg.angular_velocity_covariance[0] != -1.0, 'angular velocity marked unavailable')
    _need(msg.linear_acceleration_covariance[0] != -1.0, 'acceleration marked unavailable')
    a, g = msg.linear_acceleration, msg.angular_velocity
    _within('acceleration', [a.x, a.y, a.z], lim.MAX_ACCEL_MPS2)
    _within('angular velocity', [g.x, g.y, g.z], lim.MAX_GYRO_RPS)
    _within('yaw rate', [g.z], lim.MAX_MESSAGE_YAW_RATE_RPS)
    _covariance('angular velocity covariance', msg.angular_velocity_covariance)
    _covariance('acceleration covariance', msg.linear_acceleration_covariance)
    if msg.orientation_covariance[0] != -1.0:       # REP 145: -1 = no orientation
        _unit_quaternion('orientation', msg.orientation)
        _covariance('orientation covariance', msg.orientation_covariance)


def _twist(topic: str, msg) -> None:
    _twist_values(msg.twist.twist)
    _covariance('twist covariance', msg.twist.covariance)


def _odometry(topic: str, msg) -> None:
    p = msg.pose.pose.position
    _within('position', [p.x, p.y, p.z], lim.MAX_POSITION_M)
    _unit_quaternion('orientation', msg.pose.pose.orientation)
    _twist_values(msg.twist.twist)
    _covariance('pose covariance', msg.pose.covariance)
    _covariance('twist covariance', msg.twist.covariance)


def _image(topic: str, msg) -> None:
    channels = IMAGE_CHANNELS.get(msg.encoding)
    _need(channels is not None, f'encoding {msg.encoding!r}')
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    _need(lim.MIN_IMAGE_SIDE_PX <= h <= lim.MAX_IMAGE_HEIGHT_PX
          and lim.MIN_IMAGE_SIDE_PX <= w <= lim.MAX_IMAGE_WIDTH_PX, f'image {w}x{h} px')
    _need(w * channels <= step <= lim.MAX_IMAGE_STEP_BYTES, f'step {step}')
    _need(len(msg.data) == h * step, f'{len(msg.data)} bytes for {h} rows of {step}')


def _points(msg, layout: np.dtype, limit: int) -> np.ndarray:
    """The points of a cloud, read by its own header (the contract's fields, by name)."""
    by_name = {f.name: f for f in msg.fields}
    step = int(msg.point_step)
    _need(0 < step <= lim.MAX_POINT_STEP_BYTES, f'point_step {step}')
    order = '>' if msg.is_bigendian else '<'
    names, formats, offsets = [], [], []
    for name in layout.names:
        want = layout.fields[name][0]
        f = by_name.get(name)
        _need(f is not None, f'field {name!r} missing')
        _need(f.count == 1 and _POINTFIELD.get(f.datatype) == want.str[1:],
              f'field {name!r} of type {f.datatype} x{f.count}')
        _need(0 <= f.offset and f.offset + want.itemsize <= step, f'field {name!r} outside')
        names.append(name)
        formats.append(np.dtype(order + want.str[1:]))
        offsets.append(int(f.offset))
    height, width = int(msg.height), int(msg.width)
    _need(height * width <= limit, f'{height * width} points')
    row = int(msg.row_step)
    _need(row >= width * step, f'row_step {row}')
    data = bytes(msg.data)
    _need(len(data) == row * height, f'{len(data)} bytes for {height} rows of {row}')
    if not height * width:
        return np.zeros(0, dtype=np.dtype({'names': names, 'formats': formats}))
    rows = np.frombuffer(data, np.uint8).reshape(height, row)[:, :width * step]
    view = np.dtype({'names': names, 'formats': formats, 'offsets': offsets,
                     'itemsize': step})
    return np.ascontiguousarray(rows).view(view).reshape(-1)


def _gnss(topic: str, msg) -> None:
    pts = _points(msg, wire.GNSS_DTYPE, lim.MAX_MESSAGE_SATELLITES)
    sv = np.column_stack([pts['x'], pts['y'], pts['z']]).astype(float)
    pr, var = pts['pseudorange'].astype(float), pts['variance'].astype(float)
    _need(np.isfinite(sv).all() and np.isfinite(pr).all() and np.isfinite(var).all()
          and (pr > 0).all() and (var > 0).all(), 'a satellite without a measurement')
    _within('satellite coordinate', sv, lim.MAX_MESSAGE_SATELLITE_RADIUS_M)
    radius = np.sqrt((sv ** 2).sum(axis=1))
    _need(((radius >= lim.MIN_MESSAGE_SATELLITE_RADIUS_M)
           & (radius <= lim.MAX_MESSAGE_SATELLITE_RADIUS_M)).all(), 'satellite radius')
    _need(((pr >= lim.MIN_MESSAGE_PSEUDORANGE_M) & (pr <= lim.MAX_MESSAGE_PSEUDORANGE_M)).all(),
          'pseudorange')
    _need((var <= lim.MAX_VARIANCE).all(), 'variance')
    cn0, elevation = pts['cn0'].astype(float), pts['elevation'].astype(float)
    _need(np.all(np.isnan(cn0) | ((cn0 >= lim.MIN_CN0_DBHZ) & (cn0 <= lim.MAX_CN0_DBHZ))),
          'C/N0')
    _need(np.all(np.isnan(elevation) | (np.abs(elevation) <= lim.MAX_ABS_ELEVATION_DEG)),
          'elevation')
    system = pts['system'].astype(int)
    _need(np.isin(system, wire.KNOWN_SYSTEMS).all(), 'unknown system')
    keys = list(zip(system.tolist(), pts['sv_id'].astype(int).tolist()))
    _need(len(set(keys)) == len(keys), 'a satellite twice')


def _matches(topic: str, msg) -> None:
    pts = _points(msg, wire.MATCH_DTYPE, lim.MAX_MATCHES)
    pos = np.column_stack([pts['x'], pts['y'], pts['z']]).astype(float)
    _within('match position', pos, lim.MAX_POSITION_M)
    score = pts['score'].astype(float)
    _need(np.isfinite(score).all()
          and ((score >= lim.MIN_MATCH_SCORE) & (score <= lim.MAX_MATCH_SCORE)).all(), 'score')
