"""Structured malformed messages, one named case per fault, for every input topic.

A :class:`Case` turns a valid template message (:meth:`.stream.ValidStream.templates`) into
a malformed one. Its ``kind`` (``topic:name``) is what the figures are reported by. The
cases cover the list of the issue ("never crash, never lie"): stamps that do not fit
``builtin_interfaces/Time`` or lie far from the stream (``sec = 2**31 - 1``,
``nanosec = 2**32 - 1``, negative, far future, far past), a satellite coordinate of 1e160,
a flipped float64 exponent bit, 1,000 and 10,000 satellites, ``linear.x = 1.7e308``, match
and dead-reckoning positions of 1e300, an 8000x8000 image, wrong field layouts, truncated
data buffers and NaN everywhere, and a few more of each kind.

``expect``: ``'reject'`` means a correct node refuses the message (and counts it: a
satellite dropped by the checks counts too); ``'any'`` means accepting it is legitimate
(a plausible message), refusing it must still be counted. A ``judged`` case's messages
are judged one by one (:mod:`.plausible`): those that came out valid expect ``'any'``.
``heavy`` cases cost seconds and hundreds of MB (the pipeline's and this process's): a
run can leave them out (``--light``). ``issue`` marks the single-message cases the issue
lists.
"""
from __future__ import annotations

import copy
import struct
from dataclasses import dataclass
from typing import Callable

import numpy as np
from sensor_msgs.msg import PointField

import msg_adapters as ma
from msg_adapters import wire
from .stream import INPUT_TOPICS

REJECT, ANY = 'reject', 'any'
STRUCTURED, FLOOD = 'structured', 'flood'
TEN_YEARS_NS = 10 * 365 * 86400 * 10**9
#: Most messages of one burst per topic: within the default subscription depth of the node
#: that takes it (gnss_node 10, camera_node 5, imu_node 100, fusion_node 10), so that a
#: loss in a burst is the message's doing, not the queue's (floods test the queues).
TOPIC_BURST = {wire.GNSS: 8, wire.GNSS_MEASUREMENTS: 5, wire.IMU: 10, wire.TWIST: 10,
               wire.IMAGE: 4, wire.DEAD_RECKONING: 5, wire.MATCHES: 5}
#: Default subscription depth of each input (the floods send three times as many).
TOPIC_DEPTH = {wire.GNSS: 10, wire.GNSS_MEASUREMENTS: 10, wire.IMU: 100, wire.TWIST: 100,
               wire.IMAGE: 5, wire.DEAD_RECKONING: 1000, wire.MATCHES: 10}


@dataclass(frozen=True)
class Case:
    """One structured fault.

    Attributes:
        topic: Input topic it is published on.
        name: Short name (unique per topic).
        build: ``build(template, stamp_ns, rng) -> message`` (the template is a copy).
        expect: ``'reject'`` or ``'any'`` (module doc).
        heavy: Costs seconds and hundreds of MB.
        issue: One of the single-message cases of the issue.
        burst: Most copies published in one burst.
        reuse_stamp: Built with the stamp of the topic's last valid message (a duplicate)
            instead of a fresh one.
        judged: Its messages may come out valid (a flipped exponent bit that lands on a
            plausible value): each is judged (:mod:`.plausible`) and one judged valid is
            expected like a valid message (``'any'``), not refused.
    """

    topic: str
    name: str
    build: Callable
    expect: str = REJECT
    heavy: bool = False
    issue: bool = False
    burst: int = 10
    reuse_stamp: bool = False
    judged: bool = False

    @property
    def kind(self) -> str:
        return f'{self.topic}:{self.name}'

    @property
    def family(self) -> str:
        return FLOOD if self.name == 'flood' else STRUCTURED

    @property
    def size(self) -> int:
        """Messages of one burst of this case."""
        return self.burst if self.name == 'flood' else min(self.burst, TOPIC_BURST[self.topic])


# ------------------------------------------------------------------- helpers
def set_stamp(msg, sec: int, nanosec: int = 0):
    """Set a header stamp field by field (no range check: that is the point)."""
    msg.header.stamp.sec = int(sec)
    msg.header.stamp.nanosec = int(nanosec)
    return msg


def stamped(msg, stamp_ns: int):
    sec, nanosec = divmod(int(stamp_ns), 10**9)
    return set_stamp(msg, sec, nanosec)


def flip_bit(value: float, bit: int) -> float:
    """``value`` with bit ``bit`` (0 = least significant) of its float64 flipped."""
    (raw,) = struct.unpack('<Q', struct.pack('<d', float(value)))
    return struct.unpack('<d', struct.pack('<Q', raw ^ (1 << bit)))[0]


def cloud_points(msg, dtype: np.dtype) -> np.ndarray:
    """The points of a well-formed cloud (a writable copy)."""
    return np.frombuffer(bytes(msg.data), dtype=dtype).copy()


def with_points(msg, points: np.ndarray):
    """``msg`` carrying ``points`` (same layout), width and row_step updated."""
    msg.width = int(points.shape[0])
    msg.height = 1
    msg.row_step = int(points.dtype.itemsize * points.shape[0])
    msg.data = points.tobytes()
    return msg


def _edit_points(dtype):
    def decorate(edit):
        def build(msg, stamp_ns, rng):
            pts = cloud_points(msg, dtype)
            return with_points(stamped(msg, stamp_ns), edit(pts, rng))
        return build
    return decorate


def _fields(msg, edit):
    fields = [PointField(name=f.name, offset=f.offset, datatype=f.datatype, count=f.count)
              for f in msg.fields]
    msg.fields = edit(fields)
    return msg


def _many_satellites(n: int):
    def build(msg, stamp_ns, rng):
        pts = cloud_points(msg, wire.GNSS_DTYPE)
        out = pts[np.arange(n) % len(pts)]      # keeps the wire layout (48-byte points)
        out['sv_id'] = np.arange(n) % 65536
        out['x'] += rng.normal(0.0, 1e3, n)
        return with_points(stamped(msg, stamp_ns), out)
    return build


def _floats(msg, paths: list[str], value: float):
    for path in paths:
        *parents, leaf = path.split('.')
        obj = msg
        for p in parents:
            obj = getattr(obj, p)
        setattr(obj, leaf, float(value))
    return msg


# ------------------------------------------------------------------- stamps
def stamp_cases(topic: str) -> list[Case]:
    """Stamp faults of a stamped input topic (every one of them is)."""
    def fixed(sec, nanosec=0):
        return lambda msg, stamp_ns, rng: set_stamp(msg, sec, nanosec)

    def shifted(offset_ns):
        return lambda msg, stamp_ns, rng: stamped(msg, max(0, stamp_ns + offset_ns))

    def max_nanosec(msg, stamp_ns, rng):
        return set_stamp(msg, stamp_ns // 10**9, 2**32 - 1)

    return [
        Case(topic, 'stamp_sec_max', fixed(2**31 - 1), issue=True),
        Case(topic, 'stamp_nanosec_max', max_nanosec, issue=True),
        Case(topic, 'stamp_negative', fixed(-1, 0), issue=True),
        Case(topic, 'stamp_far_future', shifted(TEN_YEARS_NS), issue=True),
        Case(topic, 'stamp_far_past', fixed(1, 0)),
        Case(topic, 'stamp_zero', fixed(0, 0)),
        Case(topic, 'stamp_back_5s', shifted(-5 * 10**9)),
        Case(topic, 'stamp_duplicate', shifted(0), expect=ANY, reuse_stamp=True),
    ]


# ------------------------------------------------------------------- GNSS clouds
def gnss_cases(topic: str) -> list[Case]:
    """Cloud faults of ``gnss/pseudoranges`` or ``gnss/measurements``."""
    dt = wire.GNSS_DTYPE

    @_edit_points(dt)
    def coord_1e160(pts, rng):
        pts['x'][0] = 1e160
        return pts

    @_edit_points(dt)
    def exponent_flip(pts, rng):
        k = int(rng.integers(len(pts)))
        axis = ('x', 'y', 'z', 'pseudorange')[int(rng.integers(4))]
        pts[axis][k] = flip_bit(pts[axis][k], int(rng.integers(52, 63)))
        return pts

    @_edit_points(dt)
    def pseudorange_1e160(pts, rng):
        pts['pseudorange'][0] = 1e160
        return pts

    @_edit_points(dt)
    def variance_negative(pts, rng):
        pts['variance'][:] = -1.0
        return pts

    @_edit_points(dt)
    def nan_everywhere(pts, rng):
        for name in ('x', 'y', 'z', 'pseudorange', 'variance', 'cn0', 'elevation'):
            pts[name] = np.nan
        return pts

    @_edit_points(dt)
    def inf_everywhere(pts, rng):
        for name in ('x', 'y', 'z', 'pseudorange', 'variance'):
            pts[name] = np.inf
        return pts

    @_edit_points(dt)
    def duplicate_satellites(pts, rng):
        pts['sv_id'] = pts['sv_id'][0]
        pts['system'] = pts['system'][0]
        return pts

    @_edit_points(dt)
    def unknown_system(pts, rng):
        pts['system'] = 99
        return pts

    @_edit_points(dt)
    def no_satellites(pts, rng):
        return pts[:0]

    @_edit_points(dt)
    def satellites_at_centre(pts, rng):
        for name in ('x', 'y', 'z'):
            pts[name] = 0.0
        return pts

    def frame(msg, stamp_ns, rng):
        msg.header.frame_id = 'map'
        return stamped(msg, stamp_ns)

    def missing_field(msg, stamp_ns, rng):
        return stamped(_fields(msg, lambda f: [x for x in f if x.name != 'pseudorange']),
                       stamp_ns)

    def wrong_type(msg, stamp_ns, rng):
        def edit(fields):
            for f in fields:
                if f.name == 'x':
                    f.datatype = PointField.FLOAT32
            return fields
        return stamped(_fields(msg, edit), stamp_ns)

    def field_count(msg, stamp_ns, rng):
        def edit(fields):
            for f in fields:
                if f.name == 'pseudorange':
                    f.count = 1000
            return fields
        return stamped(_fields(msg, edit), stamp_ns)

    def offset_overrun(msg, stamp_ns, rng):
        def edit(fields):
            for f in fields:
                if f.name == 'z':
                    f.offset = 2**31
            return fields
        return stamped(_fields(msg, edit), stamp_ns)

    return [
        Case(topic, 'coord_1e160', coord_1e160, issue=True),
        Case(topic, 'exponent_bit_flip', exponent_flip, issue=True, judged=True),
        Case(topic, 'pseudorange_1e160', pseudorange_1e160),
        Case(topic, 'variance_negative', variance_negative),
        Case(topic, 'nan_everywhere', nan_everywhere, issue=True),
        Case(topic, 'inf_everywhere', inf_everywhere),
        Case(topic, 'satellites_1000', _many_satellites(1000), heavy=True, issue=True,
             burst=1),
        Case(topic, 'satellites_10000', _many_satellites(10000), heavy=True, issue=True,
             burst=1),
        Case(topic, 'duplicate_satellites', duplicate_satellites),
        Case(topic, 'unknown_system', unknown_system),
        Case(topic, 'no_satellites', no_satellites, expect=ANY),
        Case(topic, 'satellites_at_earth_centre', satellites_at_centre),
        Case(topic, 'wrong_frame', frame, expect=REJECT if topic == wire.GNSS else ANY),
        *layout_cases(topic),
        Case(topic, 'field_missing', missing_field),
        Case(topic, 'field_wrong_type', wrong_type),
        Case(topic, 'field_count_1000', field_count),
        Case(topic, 'field_offset_overrun', offset_overrun),
    ]


def layout_cases(topic: str) -> list[Case]:
    """Buffer and size faults of any PointCloud2 topic."""
    def edit(change):
        def build(msg, stamp_ns, rng):
            change(msg, rng)
            return stamped(msg, stamp_ns)
        return build

    def truncate(msg, rng):
        data = bytes(msg.data)
        msg.data = data[:int(rng.integers(0, max(1, len(data))))]

    def row_step_small(msg, rng):
        msg.row_step = 1

    def width_huge(msg, rng):
        msg.width = 2**32 - 1

    def height_huge(msg, rng):
        msg.height = 2**31

    def point_step_zero(msg, rng):
        msg.point_step = 0

    def big_endian(msg, rng):
        msg.is_bigendian = True

    return [
        Case(topic, 'data_truncated', edit(truncate), issue=True),
        Case(topic, 'row_step_1', edit(row_step_small)),
        Case(topic, 'width_2e32', edit(width_huge)),
        Case(topic, 'height_2e31', edit(height_huge)),
        Case(topic, 'point_step_0', edit(point_step_zero)),
        Case(topic, 'big_endian_flag', edit(big_endian), expect=ANY),
    ]


# ------------------------------------------------------------------- IMU, twist
def imu_cases() -> list[Case]:
    t = wire.IMU

    def values(paths, value):
        return lambda msg, stamp_ns, rng: stamped(_floats(msg, paths, value), stamp_ns)

    def exponent_flip(msg, stamp_ns, rng):
        msg.angular_velocity.z = flip_bit(msg.angular_velocity.z or 0.01,
                                          int(rng.integers(52, 63)))
        return stamped(msg, stamp_ns)

    def unavailable(msg, stamp_ns, rng):
        cov = np.array(msg.angular_velocity_covariance, dtype=float)
        cov[0] = -1.0
        msg.angular_velocity_covariance = cov
        return stamped(msg, stamp_ns)

    accel = ['linear_acceleration.x', 'linear_acceleration.y', 'linear_acceleration.z']
    gyro = ['angular_velocity.x', 'angular_velocity.y', 'angular_velocity.z']
    return [
        Case(t, 'nan_everywhere', values(accel + gyro, np.nan), issue=True),
        Case(t, 'accel_inf', values(accel[:1], np.inf)),
        Case(t, 'accel_1e300', values(accel[:1], 1e300)),
        Case(t, 'gyro_1.7e308', values(gyro[2:], 1.7e308)),
        Case(t, 'exponent_bit_flip', exponent_flip, issue=True, judged=True),
        Case(t, 'gyro_unavailable', unavailable),
    ]


def twist_cases() -> list[Case]:
    t = wire.TWIST

    def values(paths, value, expect=REJECT, issue=False, name=None):
        def build(msg, stamp_ns, rng):
            return stamped(_floats(msg, paths, value), stamp_ns)
        return Case(t, name, build, expect=expect, issue=issue)

    def covariance(value):
        def build(msg, stamp_ns, rng):
            cov = np.array(msg.twist.covariance, dtype=float)
            cov[0] = cov[35] = value
            msg.twist.covariance = cov
            return stamped(msg, stamp_ns)
        return build

    def exponent_flip(msg, stamp_ns, rng):
        msg.twist.twist.linear.x = flip_bit(msg.twist.twist.linear.x or 1.0,
                                            int(rng.integers(52, 63)))
        return stamped(msg, stamp_ns)

    lin, ang = 'twist.twist.linear.x', 'twist.twist.angular.z'
    return [
        values([lin], 1.7e308, issue=True, name='linear_x_1.7e308'),
        values([lin, ang], np.nan, issue=True, name='nan_everywhere'),
        values([lin], -500.0, name='speed_minus_500'),
        values([ang], 1e6, name='yaw_rate_1e6'),
        Case(t, 'covariance_negative', covariance(-1.0)),
        Case(t, 'covariance_nan', covariance(np.nan)),
        Case(t, 'exponent_bit_flip', exponent_flip, issue=True, judged=True),
    ]


# ------------------------------------------------------------------- images
def image_cases() -> list[Case]:
    t = wire.IMAGE

    def edit(change):
        def build(msg, stamp_ns, rng):
            change(msg, rng)
            return stamped(msg, stamp_ns)
        return build

    def sized(h, w, encoding='bgr8', fill=None):
        def change(msg, rng):
            ch = ma.ENCODINGS.get(encoding, 3)
            shape = (h, w) if ch == 1 else (h, w, ch)
            arr = (rng.integers(0, 256, shape, dtype=np.uint8) if fill is None
                   else np.full(shape, fill, np.uint8))
            msg.height, msg.width, msg.encoding, msg.step = h, w, encoding, w * ch
            msg.data = arr.tobytes()
        return change

    def huge(msg, rng):
        msg.height = msg.width = 8000
        msg.encoding, msg.step = 'bgr8', 8000 * 3
        msg.data = bytes(8000 * 8000 * 3)

    def encoding(name):
        def change(msg, rng):
            msg.encoding = name
        return change

    def empty(msg, rng):
        msg.height = msg.width = msg.step = 0
        msg.data = b''

    def truncate(msg, rng):
        data = bytes(msg.data)
        msg.data = data[:int(rng.integers(0, max(1, len(data))))]

    def step_small(msg, rng):
        msg.step = 1

    def dims_huge(msg, rng):
        msg.height, msg.width = 2**31 - 1, 2**31 - 1

    def step_huge(msg, rng):
        msg.step = 2**32 - 1

    return [
        Case(t, 'image_8000x8000', edit(huge), expect=ANY, heavy=True, issue=True, burst=1),
        Case(t, 'encoding_32FC1', edit(encoding('32FC1'))),
        Case(t, 'encoding_empty', edit(encoding(''))),
        Case(t, 'empty_0x0', edit(empty)),
        Case(t, 'one_pixel', edit(sized(1, 1)), expect=ANY),
        Case(t, 'tiny_8x8', edit(sized(8, 8)), expect=ANY),
        Case(t, 'black_featureless', edit(sized(240, 320, fill=0)), expect=ANY),
        Case(t, 'noise_mono8', edit(sized(240, 320, 'mono8')), expect=ANY),
        Case(t, 'data_truncated', edit(truncate), issue=True),
        Case(t, 'step_1', edit(step_small)),
        Case(t, 'dims_2e31', edit(dims_huge)),
        Case(t, 'step_2e32', edit(step_huge)),
    ]


# ------------------------------------------------------------------- links
def matches_cases() -> list[Case]:
    t = wire.MATCHES
    dt = wire.MATCH_DTYPE

    def points(edit, expect=REJECT, issue=False, name=None, burst=5):
        def build(msg, stamp_ns, rng):
            pts = cloud_points(msg, dt)
            return with_points(stamped(msg, stamp_ns), edit(pts, rng))
        return Case(t, name, build, expect=expect, issue=issue, burst=burst)

    def setter(field, value):
        def edit(pts, rng):
            pts[field][0] = value
            return pts
        return edit

    def many(pts, rng):
        out = pts[np.arange(1000) % len(pts)]
        out['image_id'] = np.arange(1000)
        return out

    def frame(msg, stamp_ns, rng):
        msg.header.frame_id = 'earth'
        return stamped(msg, stamp_ns)

    return [
        points(setter('x', 1e300), issue=True, name='position_1e300'),
        points(setter('y', np.nan), name='position_nan'),
        points(setter('z', -np.inf), name='position_inf'),
        points(setter('score', np.nan), name='score_nan'),
        points(setter('score', 1e30), expect=ANY, name='score_1e30'),
        points(setter('x', 1e6), expect=ANY, name='position_1000km'),
        points(many, expect=ANY, name='matches_1000', burst=2),
        points(lambda p, r: p[:0], expect=ANY, name='no_match'),
        Case(t, 'wrong_frame', frame, burst=5),
        *[Case(c.topic, c.name, c.build, c.expect, burst=5) for c in layout_cases(t)],
    ]


def dead_reckoning_cases() -> list[Case]:
    t = wire.DEAD_RECKONING

    def values(paths, value, expect=REJECT, issue=False, name=None):
        def build(msg, stamp_ns, rng):
            return stamped(_floats(msg, paths, value), stamp_ns)
        return Case(t, name, build, expect=expect, issue=issue, burst=5)

    def covariance(value):
        def build(msg, stamp_ns, rng):
            cov = np.array(msg.pose.covariance, dtype=float)
            cov[0] = cov[7] = cov[35] = value
            msg.pose.covariance = cov
            return stamped(msg, stamp_ns)
        return Case(t, f'covariance_{value:g}', build, burst=5)

    def zero_quaternion(msg, stamp_ns, rng):
        q = msg.pose.pose.orientation
        q.x = q.y = q.z = q.w = 0.0
        return stamped(msg, stamp_ns)

    pos = ['pose.pose.position.x', 'pose.pose.position.y']
    return [
        values(pos[:1], 1e300, issue=True, name='position_1e300'),
        values(pos, np.nan, issue=True, name='nan_position'),
        values(['twist.twist.linear.x'], 1.7e308, name='speed_1.7e308'),
        values(pos[:1], 1e7, expect=ANY, name='position_jump_10000km'),
        values(['pose.pose.orientation.z'], 1e300, name='orientation_1e300'),
        covariance(-1.0),
        covariance(float('nan')),
        Case(t, 'zero_quaternion', zero_quaternion, expect=ANY, burst=5),
    ]


def flood_case(topic: str) -> Case:
    """Three times the subscription depth of valid copies at once: a queue that overflows
    must say so (``dropped``/``lost`` counters), the graph must go on."""
    return Case(topic, 'flood', lambda msg, stamp_ns, rng: stamped(msg, stamp_ns),
                expect=ANY, burst=3 * TOPIC_DEPTH[topic])


def all_cases(topics=None, heavy: bool = True, floods: bool = True) -> list[Case]:
    """Every structured case of the input topics (``topics``: a subset; ``heavy=False``
    leaves out the heavy ones, ``floods=False`` the floods of valid messages)."""
    cases = [*gnss_cases(wire.GNSS), *gnss_cases(wire.GNSS_MEASUREMENTS), *imu_cases(),
             *twist_cases(), *image_cases(), *matches_cases(), *dead_reckoning_cases()]
    for topic in INPUT_TOPICS:
        cases += stamp_cases(topic)
        if floods:
            cases.append(flood_case(topic))
    if topics is not None:
        cases = [c for c in cases if c.topic in topics]
    if not heavy:
        cases = [c for c in cases if not c.heavy]
    return cases


def build(case: Case, template, stamp_ns: int, rng: np.random.Generator):
    """The malformed message of ``case`` from a copy of ``template``."""
    return case.build(copy.deepcopy(template), int(stamp_ns), rng)
