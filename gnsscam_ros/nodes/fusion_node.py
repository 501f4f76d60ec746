"""fusion_node: the particle filter with integrity risk, one run per GNSS epoch.

Subscribes ``gnss/measurements`` (from gnss_node), ``odometry/dead_reckoning`` (from
imu_node) and ``camera/matches`` (from camera_node) and hands them to the epoch engine
(``core.engine.EpochEngine``, the same object every offline run uses). Each GNSS epoch after
the first fix waits until its inputs have reached its stamp: the dead reckoning (at most
``odometry_wait_s``; when none has ever arrived, only during the first
``odometry_timeout_s`` of GNSS: GNSS-only operation waits for nothing after that) and the
camera images due before it (at most ``camera_wait_s``; a camera ``camera_timeout_s``
behind has stopped). Then the filter runs with the motion of the interval since the
previous epoch and the best match of each image of that interval moved to the epoch.

Publishes, in this order, ``integrity_risk`` (DiagnosticArray: OK = integrity sufficient,
ERROR = alarm, STALE = no valid solution), ``pose`` (PoseWithCovarianceStamped, map),
``odometry/global`` (nav_msgs/Odometry, ``map_frame_id`` -> ``base_frame_id``: the same
pose and covariance, and the forward speed and yaw rate of the newest dead-reckoning state
at or before the epoch, for robot_localization / Nav2), ``fix`` (NavSatFix, WGS84) and
``particles`` (PoseArray, map). Without GNSS for ``gnss_timeout_s`` (at most 60 s), or
without any epoch processed for that long (every message refused, or waiting), it
publishes ``integrity_risk`` STALE every ``stale_report_period_s`` (at most 10 s): a
consumer never sees a stale OK.

A filter state that became invalid (non-finite or absurd: ``ParticleFilter.step`` returns
'invalid') is discarded: that epoch publishes ``integrity_risk`` STALE ('filter state
invalid (...): re-initialising from the next fix') and no pose, odometry, fix or
particles, every later verdict is STALE and says so until a fix has initialised the
filter again, and ``diagnostics`` counts ``filter_resets`` (WARN while re-initialising).
:meth:`FusionNode.reset_time_base` does the same when the inputs adopt a new time base.

``map/origin`` (NavSatFix, transient local: a late subscriber still gets it) carries the
geodetic origin of the ``map`` frame once it exists (``map_origin_llh`` at start-up, else
the first robust fix), so that ``pose`` and ``particles`` can be georeferenced; the
fields as the bag converter writes them (frame ``map``, status FIX, covariance unknown).
``diagnostics`` carries, besides the node status, ``fusion_node: integrity``: the latest
integrity verdict (level OK / ERROR / STALE as ``integrity_risk``, its message,
protection level and alert limit) for diagnostic_aggregator and rqt_robot_monitor. The
node status shows the consistency test of the cloud against the measurements
(``consistency_statistic_nats``, ``snapshot_separation_m``, ``recoveries``;
``core.consistency``) and is WARN while the cloud is inconsistent (integrity ERROR), and
the share of the GNSS error that persists (``persistent_error_share``,
``core.persistence``) with what the last epoch was worth in the likelihood
(``gnss_tempering``).

Every FilterConfig parameter (``FilterConfig.parameter_specs()``; all but
``extra_alert_limits_m``) is a node parameter of the same name;
all of them can be changed while running (validated as a whole FilterConfig; a refused
update keeps the old values), e.g. ``alert_limit_m`` and ``target_risk``. Sizes
(``n_particles``, ``n_posteriors``, ...) whose epoch would need more than the memory
budget (``core.config.EPOCH_MEMORY_BUDGET_BYTES``, 2 GiB) are refused with the estimate,
at start-up and while running. An integer given for a float parameter
(``-p alert_limit_m:=16``) is that float.

Exit codes: 0 stopped (Ctrl-C, shutdown), 1 failed while running, 2 a parameter refused at
start-up (``-p likelihood:=gauss``; one line on stderr naming it).
"""
from __future__ import annotations

import math
import sys
import time
from dataclasses import replace

import numpy as np
from nav_msgs.msg import Odometry
from sensor_msgs.msg import NavSatStatus, PointCloud2

from gnsscam_ros.core.engine import (CAMERA, DEAD_RECKONING, DROPPED_OLDEST,
                                     ESTIMATE_STATUSES, NO_MATCH, EpochEngine, EpochReport,
                                     InputTiming, best_match)
from gnsscam_ros.core.filter import INVALID, REJECTED, UPDATED, EpochResult, FilterConfig
from gnsscam_ros.core.verdict import IntegrityVerdict
from gnsscam_ros.core.frames import LocalFrame
from gnsscam_ros.core.motion import OUT_OF_ORDER, RESET
from gnsscam_ros.core.particles import SYSTEMATIC
from gnsscam_ros.core.warmup import warm_up_kernels
from msg_adapters import (OK, STALE, WARN, GeodeticFix, GlobalOdometry, MessageError,
                          PoseEstimate, check_serialized_gnss,
                          check_serialized_matches, check_serialized_size, fix_to_navsatfix,
                          global_odometry_to_msg, integrity_risk_to_msg, make_status,
                          odometry_to_dead_reckoning, particles_to_posearray_cdr,
                          pointcloud2_to_gnss_epoch, pointcloud2_to_matches, pose_covariance,
                          pose_to_msg, service_bits)
from msg_adapters.geometry import UNESTIMATED_VAR
from msg_adapters.integrity import VERDICT_LEVELS
from msg_adapters.wire import (DEAD_RECKONING as DEAD_RECKONING_TOPIC, EARTH_FRAME, FIX,
                               GNSS_MEASUREMENTS, INTEGRITY, MATCHES, ODOMETRY_GLOBAL, ORIGIN,
                               PARTICLES, POSE)

from .memory import keep_epoch_memory
from .node_base import GnssCamNode, ParameterError
from .parameter_reference import FUSION_NODE
from .parameters import defaults_of
from .runtime import run_node

#: Engine counters shown on diagnostics (besides the node's own): resets of the filter and
#: of the time base, inputs the engine refused, camera matches beyond its bounds.
ENGINE_COUNTS = ('filter_resets', 'time_base_resets', 'refused_gnss', 'refused_dead_reckoning',
                 'refused_camera', 'camera_over_limit', 'camera_dropped')
#: Node parameters that are fields of the engine's InputTiming (same names).
TIMING_PARAMETERS = tuple(spec.name for spec in InputTiming.parameter_specs())
# Every filter parameter's default, meaning, unit and range: its part's field metadata
# (gnsscam_ros/core/config.py). FilterConfig fields that are not node parameters are for
# evaluation only.
NOT_PARAMETERS = tuple(s.name for s in FilterConfig.parameter_specs() if not s.node_parameter)
FILTER_PARAMETERS = tuple(s.name for s in FilterConfig.parameter_specs() if s.node_parameter)

# Code defaults (nodes.parameter_reference: FilterConfig's, fusion_node's own,
# InputTiming's); config/fusion_node.yaml documents the same values (a test checks).
DEFAULTS = defaults_of(FUSION_NODE)


def _origin_ok(value) -> str | None:
    return (None if len(value) == 3 and np.all(np.isfinite(value))
            else 'map_origin_llh must be 3 finite numbers')


def yaw_variance(yaw_rad: np.ndarray, log_w: np.ndarray) -> float:
    """Circular variance of weighted headings as an angle variance ``-2 ln R`` [rad^2]."""
    w = np.exp(log_w - np.max(log_w))
    w /= w.sum()
    r = float(np.hypot(w @ np.cos(yaw_rad), w @ np.sin(yaw_rad)))
    return float(-2.0 * np.log(max(r, 1e-12)))


def published_particles(particles: np.ndarray, log_w: np.ndarray, max_count: int
                        ) -> np.ndarray:
    """The particle cloud to publish: all of it, or a weighted deterministic subsample of
    ``max_count`` (systematic pointers at (k + 1/2) / K; never the filter's random
    generator, so publishing cannot change the filter's run)."""
    return particles[SYSTEMATIC.subsample(log_w, max_count)]


class FusionNode(GnssCamNode):
    """Particle filter node.

    Args:
        node_name: Node name.
        **kwargs: Forwarded to ``rclpy.node.Node``.
    """

    def __init__(self, node_name: str = 'fusion_node', **kwargs):
        # Compile (or load from the cache) the epoch kernels before the node exists: it
        # appears in the graph ready, and its first epoch is not a compilation (the
        # warm-up runs every likelihood, so the parameters are not needed yet).
        kernel_warm_up_s = warm_up_kernels()
        super().__init__(node_name, **kwargs)
        self.kernel_warm_up_s = kernel_warm_up_s
        # Ranges of the waits and timeouts (InputTiming, MAX_GNSS_TIMEOUT_S): a longer
        # one would hide a stopped input behind the last verdict. ROS ranges are closed
        # and finite: FilterConfig refuses an open bound itself.
        self.declare_node_parameters(FUSION_NODE, {'map_origin_llh': _origin_ok})
        seed = self.param('seed')
        rng = np.random.default_rng(None if seed < 0 else seed)
        frame = LocalFrame(*self.param('map_origin_llh')) if self.param(
            'use_map_origin') else None
        try:
            config = self._filter_config({})
        except ValueError as err:        # FilterConfig's own checks (likelihood, ...)
            raise ParameterError(f'{node_name}: {err}') from err
        self.engine = EpochEngine(config, frame=frame, rng=rng, timing=InputTiming(
            **{name: self.param(name) for name in TIMING_PARAMETERS}))
        self._camera_count = 0
        self._started = time.monotonic()
        self._last_gnss_receipt: float | None = None
        self._last_verdict: float | None = None         # of an epoch [wall s]
        self._last_dr_receipt: float | None = None
        self._last_stale_report = -math.inf
        self.last_result: EpochResult | None = None
        self.last_verdict: IntegrityVerdict | None = None
        self.origin_published = False

        self.pub_integrity = self.publisher(INTEGRITY)
        self.pub_pose = self.publisher(POSE)
        self.pub_odometry = self.publisher(ODOMETRY_GLOBAL)
        self.pub_origin = self.publisher(ORIGIN)
        self.pub_fix = self.publisher(FIX)
        self.pub_particles = self.publisher(PARTICLES)
        depth = self.param('input_queue_depth')
        # Through InputTopic: decoded and size-checked there, losses (queue overwrites
        # while an epoch runs) and undecodable messages counted on diagnostics.
        self.sub_gnss = self.subscribe_input(
            GNSS_MEASUREMENTS, self.on_gnss, 'received_measurements', check_serialized_gnss,
            depth).subscription
        self.sub_dr = self.subscribe_input(
            DEAD_RECKONING_TOPIC, self.on_dead_reckoning, 'received_dead_reckoning',
            check_serialized_size, self.param('odometry_queue_depth')).subscription
        self.sub_camera = self.subscribe_input(
            MATCHES, self.on_matches, 'received_matches', check_serialized_matches,
            depth).subscription
        self._timer = self.create_timer(0.02, self.on_timer)
        if self.engine.frame is not None:
            self.publish_origin(self.now_ns())
        self.parameters_declared()

    def ready_settings(self) -> dict:
        cfg = self.engine.config
        origin = (f'map_origin_llh {list(self.param("map_origin_llh"))}'
                  if self.param('use_map_origin') else 'first robust fix')
        return {'n_particles': cfg.n_particles, 'likelihood': cfg.likelihood,
                'alert_limit_m': cfg.alert_limit_m, 'target_risk': cfg.target_risk,
                'satellite_limit': cfg.satellite_limit, 'map_origin': origin,
                'seed': self.param('seed'), 'kernels_ready_s': round(self.kernel_warm_up_s, 2)}

    # gnss/measurements, odometry/dead_reckoning and camera/matches come from the other
    # nodes, each in stamp order: going back together is a new time base upstream.
    ordered_inputs = True

    def reset_time_base(self, reason: str) -> None:
        """The inputs adopt a new time base (their stamps jumped on purpose): drop what is
        buffered and start the filter again from the next fix (``EpochEngine.
        reset_time_base``); integrity_risk is STALE until then. Counted on diagnostics
        (``time_base_resets``)."""
        self.engine.reset_time_base(reason)
        self.get_logger().warning(f'time base reset ({reason}): inputs buffered before it '
                                  'dropped, the filter re-initialises from the next fix')

    # ------------------------------------------------------------------ parameters
    def _filter_config(self, changes: dict) -> FilterConfig:
        values = {name: changes.get(name, self.param(name)) for name in FILTER_PARAMETERS}
        return FilterConfig(**values)

    def validate_parameters(self, changes: dict) -> str | None:
        if any(name in FILTER_PARAMETERS for name in changes):
            try:
                replace(self.engine.config, **{k: v for k, v in changes.items()
                                               if k in FILTER_PARAMETERS})
            except (ValueError, TypeError) as err:
                return str(err)
        return None

    def apply_parameters(self, changes: dict) -> None:
        timing = {k: v for k, v in changes.items() if k in TIMING_PARAMETERS}
        if timing:
            self.engine.timing = replace(self.engine.timing, **timing)
        filter_changes = {k: v for k, v in changes.items() if k in FILTER_PARAMETERS}
        if filter_changes:
            self.engine.set_parameters(**filter_changes)
            self.get_logger().info(f'filter parameters changed: {filter_changes}')

    # ------------------------------------------------------------------- callbacks
    def on_gnss(self, msg: PointCloud2) -> None:
        """Queue a GNSS epoch and process what is ready."""
        try:
            # gnss_node publishes checked satellites only (no NaN, non-positive variance,
            # duplicate or unknown system), in the ECEF frame whatever its input's name.
            epoch = pointcloud2_to_gnss_epoch(msg, EARTH_FRAME, GNSS_MEASUREMENTS,
                                              checked=True)
        except MessageError as err:
            self.warn_rejected(GNSS_MEASUREMENTS, err.reason, str(err))
            return
        if self.admit_stamp(GNSS_MEASUREMENTS, epoch.stamp_ns) is None:
            return
        now = time.monotonic()
        self._last_gnss_receipt = now
        outcome = self.engine.add_gnss(epoch, now)
        if outcome == OUT_OF_ORDER:
            self.warn_rejected(GNSS_MEASUREMENTS, 'out_of_order',
                               f'stamp {epoch.stamp_ns} ns not after the queued epoch')
            return
        if outcome == DROPPED_OLDEST:
            self.stats.count('dropped_epochs')
        self.process_ready()

    def on_dead_reckoning(self, msg: Odometry) -> None:
        """Buffer a dead-reckoning state; an epoch waiting for it may now run."""
        try:
            state = odometry_to_dead_reckoning(msg, frame_id=self.param('odom_frame_id'),
                                               child_frame_id=self.param('base_frame_id'))
        except MessageError as err:
            self.warn_rejected(DEAD_RECKONING_TOPIC, err.reason, str(err))
            return
        if self.admit_stamp(DEAD_RECKONING_TOPIC, state.stamp_ns) is None:
            return
        now = time.monotonic()
        outcome = self.engine.add_dead_reckoning(state, now)
        if outcome == OUT_OF_ORDER:
            self.warn_rejected(DEAD_RECKONING_TOPIC, 'out_of_order',
                               f'stamp {state.stamp_ns} ns not after the previous state')
            return
        if outcome == RESET:
            # A restarted dead reckoner begins again at its origin: the step is not
            # motion. The interval stays uncovered and the filter treats it as unknown.
            self.stats.count('dead_reckoning_resets')
            self.get_logger().warning(
                f'dead reckoning reset at {state.stamp_ns} ns (restarted imu_node?): the '
                'motion across it is treated as unknown, integrity ERROR until the '
                'protection level recovers')
        self._last_dr_receipt = now
        if self.engine.queue:
            self.process_ready()

    def on_matches(self, msg: PointCloud2) -> None:
        """Buffer the best match of a camera image for the next epoch."""
        try:
            matches = pointcloud2_to_matches(msg, self.param('map_frame_id'))
        except MessageError as err:
            self.warn_rejected(MATCHES, err.reason, str(err))
            return
        if self.admit_stamp(MATCHES, matches.stamp_ns) is None:
            return
        measurement = best_match(matches.stamp_ns, matches.position_m, matches.score,
                                 self._camera_count)
        outcome = self.engine.add_camera(matches.stamp_ns, measurement, time.monotonic())
        if outcome == OUT_OF_ORDER:
            self.warn_rejected(MATCHES, 'out_of_order',
                               f'stamp {matches.stamp_ns} ns before the previous image')
            return
        self._camera_count += 1
        if outcome == NO_MATCH:
            self.stats.count('camera_without_match')
        if self.engine.queue:
            self.process_ready()

    def on_time_base_changed(self, topic: str, stamp_ns: int) -> None:
        """An input adopted a new time base (a replay started again): what the engine
        keeps of the old one (queued epochs, motion, camera matches, the filter's last
        epoch) can never be combined with the new stamps."""
        self.reset_time_base(f'{topic}: new time base at {stamp_ns} ns')

    def on_reset(self, reason: str) -> None:
        """``~/reset``: the engine's time-base reset (queued epochs, motion, camera
        matches, the particle filter); the next usable fix initialises the filter."""
        self.reset_time_base(reason)

    def on_timer(self) -> None:
        """Run epochs whose wait for their inputs is over; report STALE without GNSS."""
        if not self.context.ok():
            return                       # shutting down (Ctrl-C): nothing to publish to
        if self.engine.queue:
            self.process_ready()
        now = time.monotonic()
        since = now - (self._last_gnss_receipt or self._started)
        # GNSS arriving is not enough: if none of it makes an epoch (refused, or waiting),
        # the last verdict must not stand as current either.
        since_verdict = now - (self._last_verdict or self._started)
        timeout = self.param('gnss_timeout_s')
        if (max(since, since_verdict) > timeout
                and now - self._last_stale_report >= self.param('stale_report_period_s')):
            self._last_stale_report = now
            self.stats.count('stale_reports')
            why = (f'no GNSS measurements for {since:.1f} s' if since > timeout else
                   f'no epoch processed for {since_verdict:.1f} s')
            self.publish_integrity(self.engine.stale_verdict(self.now_ns(), f'stale: {why}'))

    # --------------------------------------------------------------------- epochs
    def process_ready(self) -> None:
        """Run every queued epoch that is ready, oldest first, and publish its outputs."""
        start = time.perf_counter()
        for report in self.engine.ready_reports(time.monotonic()):
            self.publish_report(report, start)
            start = time.perf_counter()

    def publish_report(self, report: EpochReport, start: float) -> None:
        """The outputs of one processed epoch (``start``: when its processing began)."""
        result, epoch = report.result, report.epoch
        self.last_result = result
        self.stats.count(f'epochs_{result.status}')
        # Satellites the filter's own checks dropped (its masks, core limits, the count
        # limit): counted as gnss_node counts its own.
        for reason, n in result.rejected.items():
            self.stats.count(f'satellites_rejected_{reason}', int(n))
        if DEAD_RECKONING in report.late:
            self.stats.count('odometry_late')
        if CAMERA in report.late:
            self.stats.count('camera_late')
        if result.status == REJECTED:
            self.warn_rejected(GNSS_MEASUREMENTS, 'filter_rejected', result.reason)
            self.stats.add_time(time.perf_counter() - start)
            return
        if result.status == INVALID:
            # Nothing of the broken state is published; the verdict (STALE) says why.
            self.get_logger().error(f'epoch {result.stamp_ns} ns: {result.reason}',
                                    throttle_duration_sec=5.0)
        if not self.origin_published and self.engine.frame is not None:
            self.publish_origin(epoch.stamp_ns, service_bits(epoch.system))
        self.publish_integrity(report.verdict)
        self._last_verdict = time.monotonic()
        self.stats.add_time(time.perf_counter() - start)
        if result.status in ESTIMATE_STATUSES:
            try:
                self._publish_estimate(report)
            except MessageError as err:
                # The filter checks its state after every epoch; should an estimate still
                # not encode, it is dropped and counted rather than ending the node.
                self.stats.count('estimates_not_published')
                self.get_logger().error(f'epoch {result.stamp_ns} ns: estimate not '
                                        f'published: {err}', throttle_duration_sec=5.0)

    def publish_integrity(self, verdict: IntegrityVerdict) -> None:
        """``integrity_risk``: the engine's verdict, encoded as it is."""
        self.pub_integrity.publish(integrity_risk_to_msg(verdict))
        self.last_verdict = verdict
        self.stats.count('published_integrity_risk')

    def publish_origin(self, stamp_ns: int, service: int = 0) -> None:
        """``map/origin`` (latched): the geodetic origin of the filter's map frame."""
        lat, lon, alt = (float(v) for v in self.engine.frame.origin_llh)
        self.pub_origin.publish(fix_to_navsatfix(GeodeticFix(
            stamp_ns=stamp_ns, lat_deg=lat, lon_deg=lon, alt_m=alt, covariance_enu_m2=None,
            status=NavSatStatus.STATUS_FIX, service=service,
            frame_id=self.param('map_frame_id'))))
        self.origin_published = True
        self.stats.count('published_map_origin')
        self.get_logger().info(f'map frame origin: lat {lat:.8f} deg, lon {lon:.8f} deg, '
                               f'alt {alt:.3f} m (published on map/origin)')

    def extra_statuses(self) -> list:
        """``<node>: integrity``: the latest integrity verdict as a diagnostics status."""
        verdict, cfg = self.last_verdict, self.engine.config
        if verdict is None:
            level, message = STALE, 'no integrity verdict yet'
            values = {'protection_level_m': math.nan,
                      'alert_limit_m': float(cfg.alert_limit_m)}
        else:
            level, message = VERDICT_LEVELS[verdict.level], verdict.message
            values = {'protection_level_m': float(verdict.protection_level_m),
                      'alert_limit_m': float(verdict.alert_limit_m),
                      'risk_bound': float(verdict.risk_bound),
                      'target_risk': float(verdict.target_risk),
                      'epoch_stamp': ('' if verdict.epoch_stamp_ns is None
                                      else int(verdict.epoch_stamp_ns))}
        return [make_status(f'{self.get_name()}: integrity', level, message, values,
                            hardware_id='gnsscam_ros')]

    def _publish_estimate(self, report: EpochReport) -> None:
        result, epoch, cloud = report.result, report.epoch, report.cloud
        map_frame = self.param('map_frame_id')
        yaw_var = yaw_variance(cloud.particles[:, 3], cloud.log_w)
        cov = np.asarray(result.covariance_m2, dtype=float)
        pose_cov = pose_covariance(cov, yaw_var)
        self.pub_pose.publish(pose_to_msg(PoseEstimate(
            stamp_ns=result.stamp_ns, position_m=result.position_enu_m, yaw_rad=result.yaw_rad,
            covariance=pose_cov, frame_id=map_frame)))
        speed, yaw_rate, speed_var, yaw_rate_var = (
            self.engine.twist_at(result.stamp_ns)
            or (0.0, 0.0, UNESTIMATED_VAR, UNESTIMATED_VAR))
        self.pub_odometry.publish(global_odometry_to_msg(GlobalOdometry(
            stamp_ns=result.stamp_ns, position_m=result.position_enu_m, yaw_rad=result.yaw_rad,
            pose_covariance=pose_cov, speed_mps=speed, yaw_rate_rps=yaw_rate,
            speed_var=speed_var, yaw_rate_var=yaw_rate_var, frame_id=map_frame,
            child_frame_id=self.param('base_frame_id'))))
        if result.status == UPDATED:
            lat, lon, alt = self.engine.frame.enu_to_geodetic(result.position_enu_m)
            self.pub_fix.publish(fix_to_navsatfix(GeodeticFix(
                stamp_ns=result.stamp_ns, lat_deg=float(lat), lon_deg=float(lon),
                alt_m=float(alt), covariance_enu_m2=cov, status=NavSatStatus.STATUS_FIX,
                service=service_bits(epoch.system), frame_id=self.param('fix_frame_id'))))
        published = published_particles(cloud.particles, cloud.log_w,
                                        self.param('max_published_particles'))
        # Serialised with numpy: building N Pose objects would cost more than the epoch.
        self.pub_particles.publish(particles_to_posearray_cdr(published, result.stamp_ns,
                                                              map_frame))

    def diagnostic_summary(self):
        now = time.monotonic()
        since_gnss = now - (self._last_gnss_receipt or self._started)
        since_dr = (math.inf if self._last_dr_receipt is None
                    else now - self._last_dr_receipt)
        values = {'seconds_since_gnss': since_gnss, 'seconds_since_dead_reckoning': since_dr,
                  'gnss_queue_length': len(self.engine.queue),
                  'camera_buffer_length': len(self.engine.camera),
                  'n_particles': self.engine.config.n_particles,
                  'alert_limit_m': self.engine.config.alert_limit_m,
                  'target_risk': self.engine.config.target_risk}
        values['dead_reckoning_resets'] = self.engine.motion.resets
        values['satellite_limit'] = self.engine.config.satellite_limit
        values.update({key: self.engine.counts.get(key, 0) for key in ENGINE_COUNTS})
        if self.last_result is not None:
            values['last_status'] = self.last_result.status
            values['protection_level_m'] = (math.nan if self.last_result.protection_level_m
                                            is None else self.last_result.protection_level_m)
            values['motion_unknown_s'] = self.last_result.motion_unknown_s
            consistency = self.last_result.consistency
            values['consistency_statistic_nats'] = consistency.statistic_nats
            values['snapshot_separation_m'] = consistency.separation_m
            values['recoveries'] = self.last_result.recoveries
            # How much of the GNSS error persists (core.persistence): how much each epoch
            # is worth in the likelihood.
            values['persistent_error_share'] = self.last_result.persistent_share
            values['gnss_tempering'] = self.last_result.tempering
        if since_gnss > self.param('gnss_timeout_s'):
            return WARN, f'stale input: no GNSS for {since_gnss:.1f} s', values
        if self.engine.reinitialising:
            return WARN, self.engine.reinitialising, values
        if since_dr > self.param('odometry_timeout_s'):
            return WARN, ('no dead reckoning: motion unknown, the protection level grows '
                          'and integrity is ERROR'), values
        if self.last_result is not None and self.last_result.motion_unknown_s > 0.0:
            return WARN, ('dead reckoning did not cover the last interval (lost or reset): '
                          'integrity ERROR'), values
        if self.last_result is not None and self.last_result.consistency.inconsistent:
            return WARN, ('the particle cloud is inconsistent with the measurements '
                          '(recovering): integrity ERROR'), values
        return OK, 'running', values


def main(args=None) -> int:
    """``ros2 run gnsscam_ros fusion_node``; the exit code (module docstring)."""
    keep_epoch_memory()
    return run_node(FusionNode, args)


if __name__ == '__main__':
    sys.exit(main())
