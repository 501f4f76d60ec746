"""imu_node: dead reckoning from the IMU and (when present) the vehicle odometry.

Subscribes ``imu/data`` (sensor_msgs/Imu) and ``odom/twist``
(geometry_msgs/TwistWithCovarianceStamped, optional); publishes
``odometry/dead_reckoning`` (nav_msgs/Odometry, frame ``odom``): planar poses integrated at
every input sample stamp and published one per ``output_period_s`` of stamp time (default
0.1 s: 10 Hz from 100 Hz IMU), by :class:`gnsscam_ros.core.motion.DeadReckoner` (the same
code an offline run uses). Speed comes from the odometry while it is received, else from the
integrated forward acceleration; yaw rate from ``yaw_rate_source`` while it is received,
else the other source.

A source is *active* while its messages keep arriving (``source_timeout_s``, wall time);
states are emitted up to the newest stamp every active source has reached, so the output
does not depend on how the two streams interleave. Messages with non-finite values,
values beyond the limits of ``msg_adapters.limits`` (speeds, rates, accelerations,
variances), invalid stamps, stamps far from their stream (``msg_adapters.stamp_gate``) or not
after their stream's previous one are refused and counted; a new time base (a replay
started again) restarts the dead reckoning.

Exit codes: 0 stopped (Ctrl-C, shutdown), 1 failed while running, 2 a parameter refused at
start-up (``-p yaw_rate_source:=compass``; one line on stderr naming it). An integer given
for a float parameter is that float.
"""
from __future__ import annotations

import sys
import time

from geometry_msgs.msg import TwistWithCovarianceStamped
from sensor_msgs.msg import Imu

from gnsscam_ros.core.motion import IMU, ODOMETRY, DeadReckoner, DeadReckoningConfig
from msg_adapters import (OK, WARN, MessageError, check_serialized_size,
                          dead_reckoning_to_odometry, imu_to_sample, twist_to_sample)
from msg_adapters.wire import DEAD_RECKONING, IMU as IMU_TOPIC, TWIST

from .node_base import GnssCamNode, ParameterError
from .parameters import IMU_NODE, defaults_of
from .runtime import run_node

# Code defaults (nodes.parameters; the dead-reckoning ones are DeadReckoningConfig's);
# config/imu_node.yaml documents the same values (a test checks).
DEFAULTS = defaults_of(IMU_NODE)
#: Node parameters that are DeadReckoningConfig fields (same names).
_DR_PARAMETERS = tuple(spec.name for spec in DeadReckoningConfig.parameter_specs())


class ImuNode(GnssCamNode):
    """Dead reckoning node.

    Args:
        node_name: Node name.
        **kwargs: Forwarded to ``rclpy.node.Node``.
    """

    def __init__(self, node_name: str = 'imu_node', **kwargs):
        super().__init__(node_name, **kwargs)
        self.declare_node_parameters(IMU_NODE)
        try:
            config = self._dr_config({})
        except ValueError as err:        # DeadReckoningConfig's own checks
            raise ParameterError(f'{node_name}: {err}') from err
        self.dead_reckoner = DeadReckoner(config)
        self._receipt: dict[str, float] = {}
        self._started = time.monotonic()
        self.pub = self.publisher(DEAD_RECKONING, self.param('output_queue_depth'))
        depth = self.param('input_queue_depth')
        self.sub_imu = self.subscribe_input(IMU_TOPIC, self.on_imu, 'received_imu',
                                            check_serialized_size, depth).subscription
        self.sub_twist = self.subscribe_input(TWIST, self.on_twist, 'received_odom_twist',
                                              check_serialized_size, depth).subscription
        self.parameters_declared()

    def ready_settings(self) -> dict:
        return {name: self.param(name) for name in ('yaw_rate_source', 'output_period_s',
                                                    'source_timeout_s')}

    def _dr_config(self, changes: dict) -> DeadReckoningConfig:
        values = {name: changes.get(name, self.param(name)) for name in _DR_PARAMETERS}
        return DeadReckoningConfig(**values)

    def on_imu(self, msg: Imu) -> None:
        """Buffer an IMU sample and publish the states it releases."""
        with self.stats.timed():
            try:
                sample = imu_to_sample(msg)
            except MessageError as err:
                self.warn_rejected(IMU_TOPIC, err.reason, str(err))
                return
            if self.admit_stamp(IMU_TOPIC, sample.stamp_ns) is None:
                return
            try:
                self.dead_reckoner.add_imu(sample.stamp_ns, sample.accel_mps2[0],
                                           sample.gyro_rps[2])
            except ValueError as err:       # stamp not after the previous one
                self.warn_rejected(IMU_TOPIC, 'out_of_order', str(err))
                return
            self._receipt[IMU] = time.monotonic()
            self._advance()

    def on_twist(self, msg: TwistWithCovarianceStamped) -> None:
        """Buffer an odometry sample and publish the states it releases."""
        with self.stats.timed():
            try:
                s = twist_to_sample(msg)
            except MessageError as err:
                self.warn_rejected(TWIST, err.reason, str(err))
                return
            if self.admit_stamp(TWIST, s.stamp_ns) is None:
                return
            try:
                self.dead_reckoner.add_odometry(s.stamp_ns, s.speed_mps, s.yaw_rate_rps,
                                                s.speed_var, s.yaw_rate_var)
            except ValueError as err:       # stamp not after the previous one
                self.warn_rejected(TWIST, 'out_of_order', str(err))
                return
            self._receipt[ODOMETRY] = time.monotonic()
            self._advance()

    def on_time_base_changed(self, topic: str, stamp_ns: int) -> None:
        # The dead reckoning starts again at its origin on the new time base; fusion_node
        # sees the restart (a reset of the dead reckoning) and treats the step as unknown
        # motion, as when imu_node itself restarts. Which sources are active is learnt
        # anew too: one that fed the old time base may not be part of the new one.
        self.dead_reckoner = DeadReckoner(self.dead_reckoner.config)
        self._receipt.clear()

    def active_sources(self) -> set[str]:
        """Sources whose messages arrived within ``source_timeout_s`` (wall time)."""
        now, timeout = time.monotonic(), self.param('source_timeout_s')
        return {s for s, t in self._receipt.items() if now - t <= timeout}

    def _advance(self) -> None:
        odom_frame, base_frame = self.param('odom_frame_id'), self.param('base_frame_id')
        for state in self.dead_reckoner.advance(self.active_sources()):
            try:
                msg = dead_reckoning_to_odometry(state, odom_frame, base_frame)
            except MessageError as err:
                # The inputs are within the limits, so this should not happen; if it does,
                # a dead reckoning that cannot be published must not stay: start again
                # (fusion_node sees a restart, as of a restarted imu_node).
                self.stats.count('dead_reckoning_invalid')
                self.get_logger().error(f'dead reckoning not publishable ({err}): '
                                        'restarted at its origin', throttle_duration_sec=5.0)
                self.dead_reckoner = DeadReckoner(self.dead_reckoner.config)
                return
            self.pub.publish(msg)
            self.stats.count('published_dead_reckoning')

    def validate_parameters(self, changes: dict) -> str | None:
        if any(name in _DR_PARAMETERS for name in changes):
            try:
                self._dr_config(changes)
            except ValueError as err:
                return str(err)
        return None

    def apply_parameters(self, changes: dict) -> None:
        if any(name in _DR_PARAMETERS for name in changes):
            self.dead_reckoner.config = self._dr_config({})

    def diagnostic_summary(self):
        active = self.active_sources()
        values = {'imu_active': IMU in active, 'odometry_active': ODOMETRY in active}
        if IMU not in active and ODOMETRY not in active:
            return WARN, 'no imu/data or odom/twist (stale inputs)', values
        if IMU not in active:
            return WARN, 'odometry only: no imu/data', values
        return OK, 'imu + odometry' if ODOMETRY in active else 'imu only', values


def main(args=None) -> int:
    """``ros2 run gnsscam_ros imu_node``; the exit code (module docstring)."""
    return run_node(ImuNode, args)


if __name__ == '__main__':
    sys.exit(main())
