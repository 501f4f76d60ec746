"""camera_node: match camera images against the geotagged map database.

Subscribes ``camera/image_raw`` (sensor_msgs/Image, mono8/bgr8/rgb8); publishes
``camera/matches`` (PointCloud2, frame ``map``: the top-k database images, best first, with
``x y z`` position, ``score`` and ``image_id``; stamp = image stamp).

Matching (ORB + vocabulary tree, ``gnsscam_ros.vision``) runs on a worker thread fed by a
bounded queue of ``queue_size`` frames: when images arrive faster than they can be matched
the *oldest* waiting frame is dropped and counted, so the node always works on recent
images and never builds an unbounded backlog. Empty images, unsupported encodings, wrong
buffer sizes, sides beyond the limits of ``msg_adapters.limits`` (checked from the
serialised header before the pixels are copied), invalid stamps, stamps far from the
stream (``msg_adapters.stamp_gate``) and stamps older than the last matched image are refused
and counted.

Every frame taken from the queue is answered on ``camera/matches``: a frame that cannot be
matched (no map database, a refused image, a matcher error) gets an *empty* cloud with its
stamp, as does a frame without any database match; a frame whose stamp is invalid or far
from the stream gets none. Downstream, fusion_node counts it as a
camera frame without a match, and a flow-controlled replay (``live.replay``) takes it as
the acknowledgement of the image instead of waiting for one that never comes. Only frames
older than the last answered one get no answer, so that ``camera/matches`` stays in stamp
order (a later answer covers them).

Without ``database_path`` (the default) the node runs and answers every frame empty; a
``database_path`` that does not name a readable map database stops it at start-up.

Exit codes: 0 stopped (Ctrl-C, shutdown), 1 failed while running, 2 a parameter refused at
start-up, 3 ``database_path`` missing or not a map database (one line on stderr each).
"""
from __future__ import annotations

import sys
import threading
import time
from collections import deque

import cv2
import numpy as np
from sensor_msgs.msg import Image

from gnsscam_ros.core.frames import LocalFrame
from gnsscam_ros.vision.database import MapDatabase
from gnsscam_ros.vision.errors import MapDatabaseError, VisionError
from msg_adapters import (OK, WARN, CameraMatches, MessageError, check_image,
                          check_serialized_image, image_to_array, matches_to_pointcloud2,
                          stamp_to_ns)
from msg_adapters.wire import IMAGE, MATCHES, RELIABLE

from .node_base import GnssCamNode, InputFileError
from .parameters import CAMERA_NODE, defaults_of
from .runtime import run_node

# Code defaults (nodes.parameters); config/camera_node.yaml documents the same values (a
# test checks).
DEFAULTS = defaults_of(CAMERA_NODE)


def _origin_ok(value) -> str | None:
    values = list(value)
    if len(values) != 3 or not np.all(np.isfinite(values)) or not -90 <= values[0] <= 90:
        return 'map_origin_llh must be [lat_deg, lon_deg, alt_m] with |lat| <= 90'
    return None


class CameraNode(GnssCamNode):
    """Camera map-matching node.

    Args:
        node_name: Node name.
        database: An already loaded database (tests, pipelines); overrides
            ``database_path``.
        **kwargs: Forwarded to ``rclpy.node.Node``.

    Raises:
        InputFileError: ``database_path`` names a file that is not a readable map database
            (the message names it).
        ParameterError: A parameter refused at start-up.
    """

    def __init__(self, node_name: str = 'camera_node', database: MapDatabase | None = None,
                 **kwargs):
        super().__init__(node_name, **kwargs)
        self.declare_node_parameters(CAMERA_NODE, {'map_origin_llh': _origin_ok})
        cv2.setNumThreads(int(self.param('opencv_threads')))
        self.database = database
        if self.database is None and self.param('database_path'):
            try:
                self.database = MapDatabase.load(self.param('database_path'))
            except MapDatabaseError as err:
                raise InputFileError(f'{node_name}: database_path: {err}') from err
        self._positions = None
        if self.database is not None:
            if self.param('use_map_origin'):
                frame = LocalFrame(*self.param('map_origin_llh'))
                self._positions = self.database.positions_in(frame)
            else:
                self._positions = self.database.positions.enu_m.copy()
        # Frames waiting for the matcher: (time base, Image) or (time base, stamp [ns]) of
        # a refused frame that gets an empty answer.
        self._queue: deque = deque()
        self._cond = threading.Condition()
        self._stop = False
        self._time_base = 0               # counts new time bases (executor thread)
        self._worker_time_base = 0        # the one _last_stamp_ns belongs to (worker)
        self._last_stamp_ns: int | None = None
        self._last_receipt: float | None = None
        self._started = time.monotonic()
        self.pub = self.publisher(MATCHES)
        self.sub = self.subscribe_input(
            IMAGE, self.on_image, 'received_images', check_serialized_image,
            depth=self.param('input_queue_depth'),
            reliability=RELIABLE if self.param('input_reliable') else None).subscription
        self._worker = threading.Thread(target=self._work, name=f'{node_name}_matcher',
                                        daemon=True)
        self._worker.start()
        self.parameters_declared()

    def ready_settings(self) -> dict:
        if self.database is None:
            return {'database': "none (every frame answered empty; set database_path)"}
        return {'database': self.param('database_path') or 'given',
                'database_images': len(self.database), 'top_k': self.param('top_k'),
                'map_origin': (f'{list(self.param("map_origin_llh"))}'
                               if self.param('use_map_origin') else 'database frame')}

    # ------------------------------------------------------------------- callbacks
    def on_image(self, msg: Image) -> None:
        """Check a frame's header fields and queue it for the matcher (cheap: the executor
        thread never matches).

        A frame refused for its content (encoding, size) is still answered, empty, at its
        stamp; one whose stamp is invalid or far from the stream gets no answer (an answer
        at such a stamp would put camera/matches out of order for every later frame).
        """
        self._last_receipt = time.monotonic()
        try:
            check_image(msg)
            refused = None
        except MessageError as err:
            if err.reason == 'stamp':
                self.warn_rejected(IMAGE, err.reason, str(err))
                return
            refused = err
        stamp_ns = stamp_to_ns(msg.header.stamp)
        if self.admit_stamp(IMAGE, stamp_ns) is None:
            return
        if refused is not None:
            self.warn_rejected(IMAGE, refused.reason, str(refused))
        with self._cond:
            if len(self._queue) >= self.param('queue_size'):
                self._queue.popleft()
                self.stats.count('dropped_frames')
            self._queue.append((self._time_base, msg if refused is None else stamp_ns))
            self._cond.notify()

    def on_time_base_changed(self, topic: str, stamp_ns: int) -> None:
        # Frames of the old time base still waiting are dropped; the matcher forgets the
        # last answered stamp before it takes the first frame of the new one.
        with self._cond:
            self._time_base += 1
            self.stats.count('dropped_frames', len(self._queue))
            self._queue.clear()

    def _work(self) -> None:
        try:
            self._serve()
        except Exception as err:     # noqa: BLE001 - the matcher must not die unseen
            if self.context.ok():
                self.fail(f'camera matcher failed: {type(err).__name__}: {err}')

    def _serve(self) -> None:
        while True:
            with self._cond:
                while not self._queue and not self._stop:
                    self._cond.wait(timeout=0.5)
                if self._stop:
                    return
                time_base, item = self._queue.popleft()
                current = self._time_base
            if not self.context.ok():
                return                   # shut down (Ctrl-C): nowhere to publish
            if time_base != current:
                continue                 # queued before a new time base (counted there)
            if time_base != self._worker_time_base:
                self._worker_time_base = time_base
                self._last_stamp_ns = None
            if isinstance(item, int):
                self._answer_unmatched(item)
                continue
            try:
                self.process(item)
            except Exception as err:     # keep matching: one bad frame must not stop it
                if not self.context.ok():
                    return               # the context went down while publishing
                self.warn_rejected(IMAGE, 'error', repr(err))
                self._answer_unmatched(stamp_to_ns(item.header.stamp))

    def process(self, msg: Image) -> CameraMatches | None:
        """Match one frame (header fields checked by :meth:`on_image`) and publish its
        top-k.

        Returns:
            The published matches: empty for a frame without a match or one that cannot
            be matched (no database, refused image); None for a frame older than the last
            answered one (refused, nothing published).
        """
        with self.stats.timed():
            stamp_ns = stamp_to_ns(msg.header.stamp)
            if self._last_stamp_ns is not None and stamp_ns < self._last_stamp_ns:
                self.warn_rejected(IMAGE, 'out_of_order',
                                   f'stamp {stamp_ns} ns before {self._last_stamp_ns}')
                return None
            if self.database is None:
                self.warn_rejected(IMAGE, 'no_database',
                                   'no map database loaded (database_path)')
                return self._answer_unmatched(stamp_ns)
            try:
                image, encoding = image_to_array(msg)
                found = self.database.query(image, top_k=int(self.param('top_k')),
                                            encoding='rgb8' if encoding == 'rgb8' else 'bgr8')
            except MessageError as err:
                self.warn_rejected(IMAGE, err.reason, str(err))
                return self._answer_unmatched(stamp_ns)
            except VisionError as err:
                self.warn_rejected(IMAGE, 'vision', str(err))
                return self._answer_unmatched(stamp_ns)
            self._last_stamp_ns = stamp_ns
            idx = np.array([m.index for m in found], dtype=np.int64)
            matches = CameraMatches(
                stamp_ns=stamp_ns, position_m=self._positions[idx].reshape(-1, 3),
                score=np.array([m.score for m in found], dtype=float), image_id=idx,
                frame_id=self.param('map_frame_id'))
            self.pub.publish(matches_to_pointcloud2(matches))
            self.stats.count('published_matches')
            if not len(matches):
                self.stats.count('frames_without_match')
            return matches

    def _answer_unmatched(self, stamp_ns: int) -> CameraMatches | None:
        """Publish an empty ``camera/matches`` at a frame's stamp (the frame yields no
        match); nothing for a frame older than the last answered one."""
        if self._last_stamp_ns is not None and stamp_ns < self._last_stamp_ns:
            return None
        self._last_stamp_ns = stamp_ns
        matches = CameraMatches(stamp_ns=stamp_ns, position_m=np.zeros((0, 3)),
                                score=np.zeros(0), image_id=np.zeros(0, dtype=np.int64),
                                frame_id=self.param('map_frame_id'))
        self.pub.publish(matches_to_pointcloud2(matches))
        self.stats.count('published_matches')
        self.stats.count('frames_without_match')
        return matches

    # ---------------------------------------------------------------- housekeeping
    def diagnostic_summary(self):
        with self._cond:
            waiting = len(self._queue)
        values = {'queue_length': waiting, 'database_images':
                  0 if self.database is None else len(self.database)}
        if self.database is None:
            # Running without a camera map is supported (GNSS and odometry alone): a
            # degraded mode to be seen, not a failure.
            return WARN, 'no map database: matching off', values
        since = time.monotonic() - (self._last_receipt or self._started)
        if since > self.param('stale_timeout_s'):
            return WARN, f'no camera/image_raw for {since:.1f} s', values
        return OK, 'matching', values

    def destroy_node(self):
        with self._cond:
            self._stop = True
            self._cond.notify_all()
        if self._worker.is_alive():
            self._worker.join(timeout=5.0)
        return super().destroy_node()


def main(args=None) -> int:
    """``ros2 run gnsscam_ros camera_node``; the exit code (module docstring)."""
    return run_node(CameraNode, args)


if __name__ == '__main__':
    sys.exit(main())
