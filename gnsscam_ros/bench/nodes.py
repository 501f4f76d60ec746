"""Benchmarks of the ROS side: ``python -m gnsscam_ros.bench.nodes``.

1. **End-to-end latency**: pipeline_node runs in its own process (as deployed); this
   process replays the emulated drive (IMU, odometry, then each GNSS epoch on
   ``gnss/pseudoranges``) and times every epoch from publishing its pseudoranges to
   receiving its ``integrity_risk`` (one clock, this process), at ``--particles`` particles
   from the first epoch on (``acquisition_particles`` 0; see ``bench_latency``).
2. **camera_node throughput**: camera_node runs in its own process pinned to one CPU core
   (``sched_setaffinity``, ``opencv_threads`` 1) with a synthetic map database; this process
   offers 640x480 bgr8 frames at ``--fps`` and then as fast as it can, and counts the
   matches that come back (matched frames per second), the frames the node dropped and the
   process CPU time per frame; once with the default best-effort input (a ~0.9 MB frame
   travels as many UDP fragments and is lost with any of them) and once with
   ``input_reliable``.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from collections import deque
from pathlib import Path

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import TwistWithCovarianceStamped
from nav_msgs.msg import Odometry
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Image, Imu, PointCloud2

import msg_adapters as ma
from gnsscam_ros.datasets.emulated.drive import make_emulated_drive
from gnsscam_ros.live.launch import start_node_processes, write_params_file
from gnsscam_ros.nodes.runtime import stop_process
from gnsscam_ros.vision.database import MapDatabase, PositionTable
from gnsscam_ros.vision.features import OrbExtractor, OrbParams
from gnsscam_ros.vision.synthetic import perturb_view, synthetic_scene

RELIABLE = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=2000,
                      reliability=ReliabilityPolicy.RELIABLE)


class _Probe:
    def __init__(self, domain: int):
        self.ctx = Context()
        rclpy.init(context=self.ctx, domain_id=domain)
        self.node = rclpy.create_node('bench_probe', context=self.ctx)
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)

    def spin_until(self, condition, timeout_s: float, what: str) -> None:
        # spin_once returns as soon as a callback ran, so a long wait adds no latency; a
        # short one would rebuild the wait set in a loop and take a core from the nodes.
        deadline = time.monotonic() + timeout_s
        while not condition():
            if time.monotonic() > deadline:
                raise TimeoutError(f'timed out after {timeout_s} s waiting for {what}')
            self.executor.spin_once(timeout_sec=0.05)

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.shutdown(context=self.ctx)


def _env(domain: int, log_dir: str) -> dict:
    env = dict(os.environ)
    env.update(ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
               ROS_LOG_DIR=log_dir, OPENBLAS_NUM_THREADS='1')
    return env


# ============================================================================ latency
def _start_latency_nodes(particles: int, acquisition_particles: int, posteriors: int | None,
                         processes: bool, domain: int, log_dir: str) -> list:
    """The nodes of the latency bench: one pipeline_node, or the four node processes."""
    fusion_params = {'n_particles': particles, 'acquisition_particles': acquisition_particles,
                     'gnss_timeout_s': 30.0, 'odometry_wait_s': 0.5}
    if posteriors is not None:
        fusion_params['n_posteriors'] = posteriors
    params = {'fusion_node': fusion_params,
              'imu_node': {'input_queue_depth': 2000, 'source_timeout_s': 30.0}}
    if processes:
        return [proc for proc, _ in start_node_processes(params, domain, log_dir, False, '/')]
    params_file = write_params_file(Path(log_dir) / 'params.yaml', params)
    return [subprocess.Popen([sys.executable, '-m', 'gnsscam_ros.nodes.pipeline',
                              '--ros-args', '--params-file', str(params_file)],
                             env=_env(domain, log_dir), stdout=subprocess.DEVNULL,
                             stderr=subprocess.DEVNULL)]


def bench_latency(particles: int = 10_000, duration_s: float = 30.0, period_s: float = 0.0,
                  acquisition_particles: int = 0, domain: int = 61, seed: int = 3,
                  log=print, posteriors: int | None = 10, processes: bool = False) -> dict:
    """Pseudoranges -> integrity_risk latency through pipeline_node in another process.

    Args:
        particles: Filter particles N (per posterior).
        acquisition_particles: ``acquisition_particles`` of the filter; 0 (default)
            keeps N particles from the start, so every epoch measures the steady state
            (the filter default 10,000 enlarges sets smaller than that for ~100 m).
        posteriors: ``n_posteriors`` M of the filter (default 10, the yardstick of
            ``gnsscam_bench``'s rows); None: the filter default.
        duration_s: Length of the emulated drive replayed [s] (GNSS at 1 Hz).
        period_s: Wall time between the dead reckoning of an epoch's interval reaching
            the probe and the epoch being sent [s]; 0 = at once (the epoch then queues
            behind the interval's IMU and odometry, sent as one burst).
        domain: ROS domain id.
        seed: Emulated drive seed.
        log: Progress printer.
        processes: The four nodes as four processes (as ``ros2 run`` or a launch file
            starts them) instead of one pipeline_node, whose nodes share one interpreter
            lock.

    Returns:
        Latency statistics [ms], and fusion_node's own processing time per epoch (filter
        step and integrity_risk publication) from its diagnostics.
    """
    drive = make_emulated_drive(seed, faults=2, duration_s=duration_s)
    log_dir = tempfile.mkdtemp(prefix='gnsscam_bench_')
    procs = _start_latency_nodes(particles, acquisition_particles, posteriors, processes,
                                 domain, log_dir)
    probe = _Probe(domain)
    received: dict[int, float] = {}
    measured: dict[int, float] = {}       # gnss/measurements of the epoch seen here
    statuses: dict[int, str] = {}
    diagnostics: list = []
    newest_dr = [-1]

    def on_dead_reckoning(msg):
        newest_dr[0] = max(newest_dr[0], ma.stamp_to_ns(msg.header.stamp))

    def on_risk(msg):
        now = time.perf_counter()
        risk = ma.parse_integrity_risk(msg)
        if risk.epoch_stamp_ns is not None and risk.epoch_status is not None:
            received.setdefault(risk.epoch_stamp_ns, now)
            statuses[risk.epoch_stamp_ns] = risk.epoch_status

    def on_measurements(msg):
        measured.setdefault(ma.stamp_to_ns(msg.header.stamp), time.perf_counter())

    try:
        node = probe.node
        node.create_subscription(PointCloud2, 'gnss/measurements', on_measurements, RELIABLE)
        subs = [node.create_subscription(DiagnosticArray, 'integrity_risk', on_risk, RELIABLE),
                node.create_subscription(Odometry, 'odometry/dead_reckoning',
                                         on_dead_reckoning, RELIABLE)]
        node.create_subscription(DiagnosticArray, 'diagnostics', diagnostics.append, RELIABLE)
        pub_gnss = node.create_publisher(PointCloud2, 'gnss/pseudoranges', RELIABLE)
        pub_imu = node.create_publisher(Imu, 'imu/data', RELIABLE)
        pub_odo = node.create_publisher(TwistWithCovarianceStamped, 'odom/twist', RELIABLE)
        for pub in (pub_gnss, pub_imu, pub_odo):
            probe.spin_until(lambda: pub.get_subscription_count() > 0, 60.0,
                             f'pipeline_node on {pub.topic_name}')
        for sub in subs:
            probe.spin_until(lambda: sub.get_publisher_count() > 0, 60.0,
                             f'pipeline_node publishing {sub.topic_name}')
        # A best-effort reader drops samples of a writer it has not matched yet, even when
        # the writer already sees the reader: let discovery settle both ways.
        settle = time.perf_counter() + 1.0
        while time.perf_counter() < settle:
            probe.executor.spin_once(timeout_sec=0.01)
        motion = deque(_motion_messages(drive))
        sent: dict[int, float] = {}
        for i, epoch in enumerate(drive.gnss):
            while motion and motion[0][0] <= epoch.stamp_ns:
                _, topic, msg = motion.popleft()
                (pub_odo if topic == 'odom/twist' else pub_imu).publish(msg)
            # Let the dead reckoning reach the epoch first: a receiver delivers an epoch
            # after its time of validity, so the IMU is already there in a live system.
            try:
                probe.spin_until(lambda: newest_dr[0] >= epoch.stamp_ns, 5.0, '')
            except TimeoutError:
                log(f'epoch {i}: dead reckoning not received (first samples lost while '
                    'discovery settled?)')
            t_pause = time.perf_counter() + period_s
            while (left := t_pause - time.perf_counter()) > 0:
                probe.executor.spin_once(timeout_sec=left)
            msg = ma.gnss_epoch_to_pointcloud2(epoch)
            sent[epoch.stamp_ns] = time.perf_counter()
            pub_gnss.publish(msg)
            probe.spin_until(lambda: epoch.stamp_ns in received, 60.0,
                             f'integrity_risk of epoch {i}')
            log(f'epoch {i:3d}: {1e3 * (received[epoch.stamp_ns] - sent[epoch.stamp_ns]):7.1f}'
                f' ms  {statuses[epoch.stamp_ns]}')
        probe.spin_until(lambda: any(s.name == 'fusion_node: status' for m in diagnostics
                                     for s in m.status), 5.0, 'fusion diagnostics')
    finally:
        probe.close()
        rc = max(stop_process(proc, timeout_s=30.0) for proc in procs)
    fusion = {}
    for m in diagnostics:
        for st in m.status:
            if st.name == 'fusion_node: status':
                fusion = ma.status_values(st)
    return {'particles': particles, 'acquisition_particles': acquisition_particles,
            'period_s': period_s, 'posteriors': posteriors,
            **_latency_figures(sent, received, measured), 'node_processes': processes,
            'fusion_processing_p50_ms': float(fusion.get('processing_p50_ms', 'nan')),
            'pipeline_exit_code': rc}


def _motion_messages(drive) -> list[tuple[int, str, object]]:
    """The drive's odometry and IMU as ``(stamp_ns, topic, message)``, in stamp order."""
    odo, imu = drive.odometry, drive.imu
    out = [(int(t), 'odom/twist', ma.sample_to_twist(ma.TwistSample(
        int(t), odo.speed_mps[k], odo.yaw_rate_rps[k], odo.speed_var[k], odo.yaw_rate_var[k])))
        for k, t in enumerate(odo.stamp_ns)]
    out += [(int(t), 'imu/data', ma.sample_to_imu(ma.ImuSample(
        int(t), imu.accel_mps2[k], imu.gyro_rps[k]))) for k, t in enumerate(imu.stamp_ns)]
    return sorted(out, key=lambda e: (e[0], e[1] != 'odom/twist'))


def _latency_figures(sent: dict, received: dict, measured: dict) -> dict:
    """Latency statistics [ms] of the epochs after the first (initialisation), and the
    leg through gnss_node (pseudoranges -> gnss/measurements, as the probe sees it)."""
    stamps = sorted(sent)[1:]
    lat = [1e3 * (received[s] - sent[s]) for s in stamps]
    gnss_leg = [1e3 * (measured[s] - sent[s]) for s in stamps if s in measured]
    return {'epochs': len(lat), 'median_ms': float(np.median(lat)),
            'p90_ms': float(np.percentile(lat, 90)), 'max_ms': float(np.max(lat)),
            'gnss_leg_median_ms': float(np.median(gnss_leg)) if gnss_leg else float('nan')}


# ============================================================================= camera
def bench_camera(fps: float = 30.0, seconds: float = 5.0, n_database: int = 60,
                 domain: int = 62, cpu: int | None = 0, reliable: bool = False,
                 log=print) -> dict:
    """camera_node matched frames per second on one core.

    Args:
        fps: Offered frame rate of the first phase [1/s].
        seconds: Length of each phase [s].
        n_database: Images in the synthetic map database.
        domain: ROS domain id.
        cpu: CPU the camera_node process is pinned to (None: not pinned).
        reliable: camera_node's ``input_reliable`` (False: best-effort sensor QoS).
        log: Progress printer.

    Returns:
        Offered and matched frame rates and drops for the paced and the flood phase.
    """
    work = tempfile.mkdtemp(prefix='gnsscam_bench_cam_')
    images = [synthetic_scene(i, seed=11) for i in range(n_database)]
    ext = OrbExtractor(OrbParams())
    db = MapDatabase.build([ext.descriptors(im) for im in images],
                           [f'im{i:03d}.png' for i in range(n_database)],
                           PositionTable.from_columns(('east_m', 'north_m'), np.column_stack(
                               [np.arange(n_database) * 10.0, np.zeros(n_database)])),
                           branching=10, depth=4, seed=0)
    db_path = Path(work) / 'map.npz'
    db.save(db_path)
    rng = np.random.default_rng(0)
    frames = [perturb_view(images[i % n_database], rng) for i in range(50)]
    log(f'database: {n_database} images; frames 640x480 bgr8')

    def pin():
        if cpu is not None:
            os.sched_setaffinity(0, {cpu})

    proc = subprocess.Popen([sys.executable, '-m', 'gnsscam_ros.nodes.camera_node',
                             '--ros-args', '-p', f'database_path:={db_path}',
                             '-p', 'opencv_threads:=1', '-p', 'queue_size:=2',
                             '-p', 'input_queue_depth:=10', '-p', 'top_k:=5',
                             '-p', f'input_reliable:={str(reliable).lower()}'],
                            env=_env(domain, work), preexec_fn=pin,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    probe = _Probe(domain)
    got: list[float] = []
    diagnostics: list = []
    out = {}
    try:
        node = probe.node
        node.create_subscription(PointCloud2, 'camera/matches',
                                 lambda m: got.append(time.perf_counter()), RELIABLE)
        node.create_subscription(DiagnosticArray, 'diagnostics', diagnostics.append, RELIABLE)
        pub = node.create_publisher(Image, 'camera/image_raw', RELIABLE)
        probe.spin_until(lambda: pub.get_subscription_count() > 0, 60.0, 'camera_node')
        msgs = [ma.array_to_image(f, 0) for f in frames]
        stamp = [1]

        def cpu_s() -> float:
            # utime + stime of the camera_node process (all its threads) [s].
            fields = Path(f'/proc/{proc.pid}/stat').read_text().rsplit(')', 1)[1].split()
            return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')

        def offer(rate: float | None, length_s: float) -> dict:
            got.clear()
            cpu0 = cpu_s()
            start = time.perf_counter()
            sent = 0
            while time.perf_counter() - start < length_s:
                if rate is not None:
                    due = start + sent / rate
                    while time.perf_counter() < due:
                        probe.executor.spin_once(timeout_sec=max(0.0, min(
                            0.002, due - time.perf_counter())))
                msg = msgs[sent % len(msgs)]
                msg.header.stamp = ma.ns_to_stamp(stamp[0] * 1_000_000)
                stamp[0] += 1
                pub.publish(msg)
                sent += 1
                probe.executor.spin_once(timeout_sec=0.0)
            end = time.perf_counter()
            settle = end + 1.0
            while time.perf_counter() < settle:
                probe.executor.spin_once(timeout_sec=0.01)
            inside = [t for t in got if t <= end]
            cpu_ms = 1e3 * (cpu_s() - cpu0) / max(len(got), 1)
            return {'offered_fps': sent / (end - start),
                    'matched_fps': len(inside) / (end - start), 'sent': sent,
                    'matched': len(got), 'cpu_ms_per_matched_frame': cpu_ms,
                    'one_core_capacity_fps': 1e3 / cpu_ms}

        offer(fps, 1.0)                                  # warm-up
        out['paced'] = offer(fps, seconds)
        log(f"paced at {fps:g} fps: matched {out['paced']['matched_fps']:.1f} frames/s, "
            f"{out['paced']['cpu_ms_per_matched_frame']:.1f} ms CPU per frame")
        out['flood'] = offer(None, seconds)
        log(f"flooded at {out['flood']['offered_fps']:.0f} fps: matched "
            f"{out['flood']['matched_fps']:.1f} frames/s")
        probe.spin_until(lambda: len(diagnostics) > 0, 5.0, 'camera diagnostics')
        values = {}
        for m in diagnostics:
            for s in m.status:
                values = ma.status_values(s)
        out['node'] = {k: values.get(k) for k in ('received_images', 'dropped_frames',
                                                  'published_matches', 'processing_p50_ms',
                                                  'processing_mean_ms')}
    finally:
        probe.close()
        out['exit_code'] = stop_process(proc, timeout_s=30.0)
    out['pinned_cpu'] = cpu
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog='python -m gnsscam_ros.bench.nodes',
                                     description=__doc__.split('\n\n')[0])
    parser.add_argument('--particles', type=int, default=10_000)
    parser.add_argument('--acquisition-particles', type=int, default=0,
                        help='acquisition_particles of the filter (default 0)')
    parser.add_argument('--posteriors', type=int, default=10,
                        help='n_posteriors M of the filter (default 10; 0: the filter '
                             'default)')
    parser.add_argument('--duration-s', type=float, default=30.0,
                        help='emulated drive replayed for the latency [s]')
    parser.add_argument('--period-s', type=float, default=0.0,
                        help='wall time between an epoch\'s dead reckoning reaching the probe '
                             'and the epoch being sent (0, the default: at once, so the '
                             'epoch queues behind the burst of the interval\'s IMU and '
                             'odometry; a live receiver\'s epoch finds them processed) [s]')
    parser.add_argument('--processes', action='store_true',
                        help='the latency through the four nodes as four processes (default: '
                             'one pipeline_node)')
    parser.add_argument('--fps', type=float, default=30.0)
    parser.add_argument('--camera-seconds', type=float, default=5.0)
    parser.add_argument('--skip-latency', action='store_true')
    parser.add_argument('--skip-camera', action='store_true')
    parser.add_argument('--json', help='also write the results to this file')
    parser.add_argument('--quiet', action='store_true')
    args = parser.parse_args(argv)
    log = (lambda *a: None) if args.quiet else (lambda *a: print(*a, file=sys.stderr))
    results = {}
    if not args.skip_latency:
        results['latency'] = bench_latency(args.particles, args.duration_s,
                                           period_s=args.period_s,
                                           processes=args.processes,
                                           acquisition_particles=args.acquisition_particles,
                                           log=log, posteriors=args.posteriors or None)
        lat = results['latency']
        m = args.posteriors or 'the default'
        print(f"latency pseudoranges -> integrity_risk, N = {args.particles} (x M = {m} "
              f"posteriors): median {lat['median_ms']:.1f} ms, p90 {lat['p90_ms']:.1f} ms "
              f"over {lat['epochs']} epochs; fusion_node processing p50 "
              f"{lat['fusion_processing_p50_ms']:.1f} ms; pseudoranges -> gnss/measurements "
              f"median {lat['gnss_leg_median_ms']:.1f} ms")
    if not args.skip_camera:
        for reliable in (False, True):
            key = 'camera_reliable' if reliable else 'camera'
            results[key] = cam = bench_camera(args.fps, args.camera_seconds,
                                              reliable=reliable, log=log)
            qos = 'reliable input' if reliable else 'best-effort input (sensor QoS)'
            print(f"camera_node on one core, 640x480 bgr8, {qos}: "
                  f"{cam['paced']['matched_fps']:.1f} frames/s matched when offered "
                  f"{cam['paced']['offered_fps']:.1f}; {cam['flood']['matched_fps']:.1f} "
                  f"frames/s when flooded ({cam['flood']['offered_fps']:.0f} offered, oldest "
                  f"dropped: {cam['node']['dropped_frames']}); process CPU "
                  f"{cam['paced']['cpu_ms_per_matched_frame']:.1f} ms per frame = "
                  f"{cam['paced']['one_core_capacity_fps']:.0f} frames/s on a free core")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2))
    return 0


if __name__ == '__main__':
    sys.exit(main())
