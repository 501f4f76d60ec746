"""The physical limits every input message is checked against, in one place.

The parsers of this package refuse a message outside them with a :class:`.MessageError`
whose ``reason`` is the counter key the nodes report on ``diagnostics``:

* ``'stamp'``: a stamp that is not a valid ``builtin_interfaces/Time``;
* ``'size'``: more satellites, matches or pixels than below (checked from the header
  fields, before any array of the message is decoded);
* ``'non_finite'``: NaN or infinity where a number is needed;
* ``'range'``: a finite value no road vehicle, GNSS satellite or camera map can have
  (a negative variance, a correlation above 1 and a quaternion that is no rotation too);
* ``'frame'``: a header frame other than the one the topic is defined in;
* ``'duplicate_satellites'``, ``'unknown_system'``: a checked GNSS epoch
  (``gnss/measurements``) with a satellite twice or of a system code not in
  :data:`.wire.KNOWN_SYSTEMS` (gnss_node drops such satellites of the receiver's epochs
  and counts them per satellite);
* ``'stamp_jump'``: a stamp too far from the recent stream (:class:`.gate.StampGate`).

Each limit keeps the valid data of this package with a wide margin (smartLoc Berlin
Potsdamer Platz and the emulated drives: 12-17 satellites, satellite radii 2.55e7-2.69e7 m,
pseudoranges 1.90e7-2.57e7 m, variances 10-196 m^2, C/N0 10-55 dB-Hz, elevations 1.8-85
deg, speeds up to 13.6 m/s, yaw rates up to 0.61 rad/s, accelerations up to 10 m/s^2,
dead-reckoning positions within 600 m of their origin, stamps from 0 (smartLoc) to 1.7e18
ns (emulated)) and refuses what would make the filter's arithmetic overflow or its cost
explode: one satellite coordinate of 1e160 or a speed of 1.7e308 turned the estimate
non-finite, 1,000 satellites stalled an epoch for seconds and grew the process by 1.6 GB.
"""
from __future__ import annotations

from . import wire
from .wire import NS_PER_S

# ------------------------------------------------------------------------------ stamps
#: ``builtin_interfaces/Time.sec`` is an int32; stamps before the clock's epoch do not
#: exist (the writers refuse them: an accepted one could not be published again).
MIN_STAMP_SEC = 0
#: Largest ``sec`` (int32); with ``nanosec < NS_PER_S`` every accepted stamp re-encodes.
MAX_STAMP_SEC = wire.MAX_STAMP_SEC
#: ``nanosec`` must be a fraction of a second; 2**32-1 would carry over 4 s into ``sec``
#: and can push it past the int32 range.
MAX_NANOSEC = NS_PER_S - 1

#: A stamp more than this far before or after the newest accepted stamp of its topic is a
#: jump (``'stamp_jump'``), not the stream. 60 s: longer than any gap of a live stream
#: (GNSS in a tunnel, a camera that pauses) that should continue the same estimate.
STAMP_WINDOW_S = 60.0
STAMP_WINDOW_NS = int(STAMP_WINDOW_S * NS_PER_S)
#: A deliberate change of the time base (a bag replayed again, a clock set anew): this
#: many consecutive messages of one topic consistent with each other (each after the
#: previous one and within the window of it) but not with the stream before are adopted
#: as the new time base (the last of them is accepted), once they also span
#: ``NEW_TIME_BASE_SPAN_S`` of receipt time. 5 messages: 5 s of GNSS at 1 Hz; one
#: glitch, or a few stray messages, never reaches it.
NEW_TIME_BASE_MESSAGES = 5
#: Receipt (wall-clock) time the consistent run must span before it is a new time base
#: [s]: a new clock keeps sending, a burst of garbage with consistent stamps arrives
#: within milliseconds and is over. 1 s: 100 messages of a 100 Hz IMU, 5 of a 1 Hz GNSS
#: receiver (which need 4 s anyway); at 10x replay speed, 10 s of the bag.
NEW_TIME_BASE_SPAN_S = 1.0

# -------------------------------------------------------------------------------- GNSS
# The ``MESSAGE`` limits bound what one message may carry; the core's own checks behind
# them (``core.gnss_checks``: ``MAX_EPOCH_SATELLITES``, ``MAX_SATELLITE_RADIUS_M``,
# ``MAX_PSEUDORANGE_M``) are wider or smaller for reasons of their own, said there and
# here. A test keeps every message limit within the core's (what a node accepts, the
# core never refuses as corrupt).
#: Satellites per message. All constellations together have ~130 satellites, about half
#: of them above the horizon at once; 128 leaves room for dual-frequency receivers that
#: report a satellite twice. An epoch *uses* fewer (``core.gnss_checks.
#: MAX_EPOCH_SATELLITES``, 64: the strongest), since the filter's cost grows with
#: particles x satellites; a message may carry more so that the filter, not the parser,
#: chooses which.
MAX_MESSAGE_SATELLITES = 128
#: Satellite distance from the Earth's centre [m]: above the Earth's surface (equatorial
#: radius 6.378e6 m) and within the geostationary orbit (4.216e7 m: BeiDou GEO/IGSO,
#: QZSS, SBAS) with margin; GPS, GLONASS and Galileo orbit at 2.55e7-2.99e7 m. (The core
#: drops only radii beyond 1e8 m, ``core.gnss_checks.MAX_SATELLITE_RADIUS_M``: its bound is
#: for arithmetic every caller's data must pass, offline loaders included.)
MIN_MESSAGE_SATELLITE_RADIUS_M = 6.4e6
MAX_MESSAGE_SATELLITE_RADIUS_M = 5.0e7
#: Pseudorange [m]: geometric range from the ground (2.0e7 m to a GPS satellite at the
#: zenith, 4.2e7 m to a geostationary one at the horizon) plus the receiver clock
#: offset, which receivers steer to within +-1 ms (+-3e5 m); the margins allow +-16 ms.
#: (The core's arithmetic bound is 1e8 m, ``core.gnss_checks.MAX_PSEUDORANGE_M``.)
MIN_MESSAGE_PSEUDORANGE_M = 1.5e7
MAX_MESSAGE_PSEUDORANGE_M = 5.0e7
#: C/N0 [dB-Hz]: receivers report 0-60 dB-Hz; gnss_node's mask goes up to 100.
MIN_CN0_DBHZ = 0.0
MAX_CN0_DBHZ = 100.0
#: Elevation [deg]: an angle above the horizon.
MAX_ABS_ELEVATION_DEG = 90.0

# --------------------------------------------------------------------- variances
#: Any variance read from a message [m^2, (m/s)^2, rad^2, ...]: the square of
#: :data:`MAX_POSITION_M`. A larger one says nothing more than "unknown", and sums and
#: products of a few of them stay finite (1e300 variances overflowed to infinity).
MAX_VARIANCE = 1.0e14

# ------------------------------------------------------------------- vehicle motion
#: Forward speed [m/s] (360 km/h), of the odometry, the dead reckoning and its twist.
MAX_SPEED_MPS = 100.0
#: Yaw rate of the vehicle in a message [rad/s] (odometry, dead reckoning, IMU gyro z): a
#: car spinning out turns at 2-3 rad/s, a tight parking turn at under 1 rad/s. The epoch
#: engine's backstop for dead-reckoning states from any caller is twice this
#: (``core.engine.MAX_DR_YAW_RATE_RPS``, 10 rad/s): a state integrated from messages within
#: this limit is never refused there.
MAX_MESSAGE_YAW_RATE_RPS = 5.0
#: IMU angular rate about any axis [rad/s]: the full scale of automotive MEMS gyros
#: (2000 deg/s); beyond it a value is not a measurement.
MAX_GYRO_RPS = 35.0
#: IMU specific force along any axis [m/s^2]: 16 g, the full scale of automotive MEMS
#: accelerometers. A road vehicle's own accelerations stay under 1.5 g, but potholes
#: and kerbs give vertical spikes of several g that are real samples.
MAX_ACCEL_MPS2 = 160.0
#: The twist components a planar vehicle does not use but a twist carries (``odom/twist``,
#: the dead reckoning's twist) are held to the same physics: lateral and vertical speed to
#: :data:`MAX_SPEED_MPS`, roll and pitch rates to :data:`MAX_GYRO_RPS`.

# ------------------------------------------------------------------- covariances
#: Covariance matrices (IMU 3x3, twist and pose 6x6, row major): every element finite,
#: every diagonal element (a variance) in [0, :data:`MAX_VARIANCE`], every off-diagonal
#: element within ``sqrt(c_ii * c_jj)`` (a correlation of at most 1), each up to this
#: tolerance [the matrix's units]: a rounded zero (-1e-17) is no negative variance, a
#: negative variance (-1) or an off-diagonal term where both variances are zero is no
#: covariance. Zero variances mean "not reported" (ROS convention); REP 145's marker of a
#: missing IMU quantity (element 0 = -1) is judged by the IMU parser.
COVARIANCE_TOLERANCE = 1e-9
#: Unit quaternions (dead-reckoning pose, an IMU orientation it reports): ``|q|^2`` within
#: 1 +- this, the tolerance of tf2 (``QUATERNION_NORMALIZATION_TOLERANCE``). A zero or a
#: 1e300 quaternion is no rotation.
QUATERNION_NORM_TOLERANCE = 1e-2

# ------------------------------------------------------------------------ positions
#: Any coordinate of a map- or odom-frame position [m] (dead reckoning, camera matches):
#: a local frame is anchored near the drive; 1e7 m is more than the Earth's radius.
MAX_POSITION_M = 1.0e7

# ------------------------------------------------------------------ message bytes
#: Header strings and other variable parts of any input message [bytes] (frame names,
#: an image encoding, point field names): an Imu is ~330 bytes, an Odometry ~730, a
#: PointCloud2 header with its fields ~300. This bounds the serialised size of the
#: messages without arrays, checked before they are decoded.
MAX_MESSAGE_BYTES = 65536
#: Bytes per point of a cloud: a GNSS point is 48, a match 32; a layout with further
#: fields stays far below. Bounds a cloud to ~128 kB before it is decoded.
MAX_POINT_STEP_BYTES = 1024

# ---------------------------------------------------------------------------- camera
#: Matches per ``camera/matches`` cloud: camera_node's ``top_k`` range ends at 1000.
MAX_MATCHES = 1000
#: Retrieval score of a match: camera_node's similarity is in [0, 1]; the tolerance
#: covers its FLOAT32 rounding.
MIN_MATCH_SCORE = 0.0
MAX_MATCH_SCORE = 1.0 + 1e-6
#: Image size [px]. 4096 covers 4K cameras (3840 x 2160); a 4096 x 4096 bgr8 frame is
#: 50 MB, an 8000 x 8000 one 192 MB (two of them kept the process 0.5 GB larger).
MAX_IMAGE_WIDTH_PX = 4096
MAX_IMAGE_HEIGHT_PX = 4096
#: Smallest side [px]: OpenCV's ORB pyramid asserts when a side rounds to 0 px at its
#: coarsest level (a 1 px side with the default 8 levels at scale 1.2); 16 px stays above
#: it for up to 20 levels. Such small frames match nothing anyway (ORB keeps a 31 px
#: border free of features) but are harmless, so they are still accepted.
MIN_IMAGE_SIDE_PX = 16
#: Bytes per image row: 8-bit samples of at most 4 channels, row padding included.
MAX_IMAGE_STEP_BYTES = 4 * MAX_IMAGE_WIDTH_PX

__all__ = [name for name in dir() if name.isupper() and name != 'NS_PER_S']
