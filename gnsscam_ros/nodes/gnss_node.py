"""gnss_node: validate pseudorange epochs, forward the usable satellites, snapshot fix.

Subscribes ``gnss/pseudoranges`` (PointCloud2, frame ``earth``); publishes
``gnss/measurements`` (the satellites that passed the checks, same layout, every epoch even
when too few remain, so that fusion_node can report the epoch as STALE at once) and
``gnss/fix`` (robust snapshot least-squares fix, NavSatFix, only for usable epochs).

Checks (``core.gnss_checks.check_epoch``): non-finite values, non-positive range or variance,
duplicated satellites, unknown system code, elevation and C/N0 masks, minimum satellite
count; whole messages with wrong fields or frame, more satellites or values beyond the
limits of ``msg_adapters.limits``, invalid stamps, stamps far from the stream
(``msg_adapters.stamp_gate``) or not after the previous epoch, are refused. Everything refused
is counted and reported on ``diagnostics``.

Exit codes: 0 stopped (Ctrl-C, shutdown), 1 failed while running, 2 a parameter refused at
start-up (one line on stderr naming it). An integer given for a float parameter is that
float.
"""
from __future__ import annotations

import sys
import time

import numpy as np
from sensor_msgs.msg import NavSatFix, NavSatStatus, PointCloud2

from gnsscam_ros.core.frames import LocalFrame, sagnac_corrected
from gnsscam_ros.core.gnss_checks import (IMPLAUSIBLE_RESIDUAL_RATIO, check_epoch,
                                          residual_ratio)
from gnsscam_ros.core.snapshot import solve_snapshot
from gnsscam_ros.core.types import GnssEpoch
from msg_adapters import (OK, WARN, GeodeticFix, MessageError, check_serialized_gnss,
                          fix_to_navsatfix, gnss_epoch_to_pointcloud2,
                          pointcloud2_to_gnss_epoch, service_bits)
from msg_adapters.wire import GNSS, GNSS_FIX, GNSS_MEASUREMENTS, KNOWN_SYSTEMS

from .node_base import GnssCamNode
from .parameters import GNSS_NODE, defaults_of
from .runtime import run_node

# Code defaults (nodes.parameters); config/gnss_node.yaml documents the same values (a test
# checks).
DEFAULTS = defaults_of(GNSS_NODE)


def fix_covariance_enu(epoch: GnssEpoch, ecef_m: np.ndarray, var_floor_m2: float
                       ) -> np.ndarray:
    """Geometry covariance of a snapshot fix in east, north, up [m^2].

    ``sigma^2 (H^T W H)^-1`` of the position-and-clocks least squares, H = line-of-sight
    unit vectors and one clock column per constellation, W = 1 / max(var, floor). The
    robust loss down-weights outliers, so this is an approximation (NavSatFix
    COVARIANCE_TYPE_APPROXIMATED).
    """
    frame = LocalFrame.from_ecef(ecef_m)
    los = frame.ecef_to_enu(sagnac_corrected(epoch.sv_pos_ecef_m, ecef_m))
    unit = los / np.linalg.norm(los, axis=1, keepdims=True)
    systems, sys_index = np.unique(epoch.system, return_inverse=True)
    h = np.zeros((epoch.n_sv, 3 + systems.size))
    h[:, :3] = -unit
    h[np.arange(epoch.n_sv), 3 + sys_index] = 1.0
    w = 1.0 / np.maximum(epoch.var_m2, var_floor_m2)
    info = h.T @ (h * w[:, None])
    return np.linalg.pinv(info)[:3, :3]


class GnssNode(GnssCamNode):
    """Validates GNSS epochs and publishes the usable satellites and a snapshot fix.

    Args:
        node_name: Node name.
        **kwargs: Forwarded to ``rclpy.node.Node``.
    """

    def __init__(self, node_name: str = 'gnss_node', **kwargs):
        super().__init__(node_name, **kwargs)
        self.declare_node_parameters(GNSS_NODE)
        self._last_stamp_ns: int | None = None
        self._last_receipt: float | None = None
        self._last_fix_ecef: np.ndarray | None = None
        self._started = time.monotonic()
        self.pub_measurements = self.publisher(GNSS_MEASUREMENTS)
        self.pub_fix = self.publisher(GNSS_FIX)
        self.sub = self.subscribe_input(
            GNSS, self.on_epoch, 'received_pseudoranges', check_serialized_gnss,
            depth=self.param('input_queue_depth')).subscription
        self.parameters_declared()

    def ready_settings(self) -> dict:
        return {name: self.param(name) for name in ('elevation_mask_deg', 'cn0_mask_dbhz',
                                                    'min_satellites', 'input_frame_id')}

    def on_epoch(self, msg: PointCloud2) -> None:
        """Validate one epoch and publish what passes."""
        with self.stats.timed():
            self._last_receipt = time.monotonic()
            try:
                epoch = pointcloud2_to_gnss_epoch(msg, self.param('input_frame_id'))
            except MessageError as err:
                self.warn_rejected(GNSS, err.reason, str(err))
                return
            if self.admit_stamp(GNSS, epoch.stamp_ns) is None:
                return
            if self._last_stamp_ns is not None and epoch.stamp_ns <= self._last_stamp_ns:
                self.warn_rejected(GNSS, 'out_of_order',
                                   f'stamp {epoch.stamp_ns} ns not after {self._last_stamp_ns}')
                return
            self._last_stamp_ns = epoch.stamp_ns
            known = np.isin(epoch.system, KNOWN_SYSTEMS)
            if not known.all():
                self.stats.count('satellites_rejected_unknown_system', int((~known).sum()))
                epoch = epoch.subset(known)
            check = check_epoch(epoch, self.param('min_satellites'),
                                self.param('elevation_mask_deg'), self.param('cn0_mask_dbhz'))
            for reason, n in check.rejected.items():
                self.stats.count(f'satellites_rejected_{reason}', n)
            usable = epoch.subset(check.keep)
            self.pub_measurements.publish(gnss_epoch_to_pointcloud2(usable))
            self.stats.count('published_measurements')
            if not check.usable:
                self.stats.count('epochs_unusable')
                self.get_logger().warning(f'epoch {epoch.stamp_ns}: {check.reason}',
                                          throttle_duration_sec=5.0)
                return
            self._publish_fix(usable)

    def on_time_base_changed(self, topic: str, stamp_ns: int) -> None:
        # Epochs of the new time base are ordered among themselves only. The last fix
        # stays the start of the next solution: it is a position, not a time.
        self._last_stamp_ns = None

    def _publish_fix(self, epoch: GnssEpoch) -> None:
        var_floor = self.param('measurement_var_m2')
        try:
            fix = solve_snapshot(epoch, self._last_fix_ecef, measurement_var_m2=var_floor)
        except ValueError as err:
            self.stats.count('fix_failed')
            self.get_logger().warning(f'snapshot fix: {err}', throttle_duration_sec=5.0)
            return
        if not fix.converged or not np.all(np.isfinite(fix.ecef_m)):
            self.stats.count('fix_failed')
            return
        self._last_fix_ecef = fix.ecef_m
        ratio = residual_ratio(fix.residual_m, epoch.var_m2)
        if ratio > IMPLAUSIBLE_RESIDUAL_RATIO:
            self.stats.count('implausible_variance')
            self.get_logger().warning(
                f'epoch {epoch.stamp_ns}: post-fit residuals are {ratio:.1f} x the stated '
                'standard deviations: variances too small or corrections missing (input '
                'contract: msg_adapters/wire.py)', throttle_duration_sec=10.0)
        frame = LocalFrame.from_ecef(fix.ecef_m)
        lat, lon, alt = frame.origin_llh
        cov = fix_covariance_enu(epoch, fix.ecef_m, var_floor)
        self.pub_fix.publish(fix_to_navsatfix(GeodeticFix(
            stamp_ns=epoch.stamp_ns, lat_deg=lat, lon_deg=lon, alt_m=alt,
            covariance_enu_m2=cov, status=NavSatStatus.STATUS_FIX,
            service=service_bits(epoch.system), frame_id=self.param('fix_frame_id'),
            covariance_type=NavSatFix.COVARIANCE_TYPE_APPROXIMATED)))
        self.stats.count('published_fix')

    def validate_parameters(self, changes: dict) -> str | None:
        if 'min_satellites' in changes and changes['min_satellites'] < 4:
            return 'min_satellites must be >= 4 (position and clock)'
        return None

    def diagnostic_summary(self):
        since = time.monotonic() - (self._last_receipt or self._started)
        values = {'seconds_since_pseudoranges': since}
        if since > self.param('stale_timeout_s'):
            return WARN, f'no gnss/pseudoranges for {since:.1f} s', values
        return OK, 'receiving', values


def main(args=None) -> int:
    """``ros2 run gnsscam_ros gnss_node``; the exit code (module docstring)."""
    return run_node(GnssNode, args)


if __name__ == '__main__':
    sys.exit(main())
