"""The whole chain in one call: a bag replayed through the four nodes, their outputs
recorded (:func:`replay_through_nodes`), under a private namespace so that concurrent runs
on one machine never mix.
"""
from __future__ import annotations

import dataclasses
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import rclpy
from rclpy.context import Context

from ..bags import schema
from ..nodes.runtime import NodeSpinner, stop_process
from .launch import (FRESH_PROCESSES_SETTLE_S, LAYOUTS, REPLAY_NODE_PARAMETERS,
                     default_domain_id, make_nodes, merge_parameters, own_cpu_s,
                     private_namespace, process_cpu_s, start_node_processes, use_dds_profile)
from .player import MATCH_SETTLE_S, BagReplayer
from .record import BagRecorder, RecordSummary
from .summary import ReplaySummary

# Recorded topics a replay must see a subscriber on before it plays: the once-only and
# truth topics, which nothing else in the graph consumes.
_REPLAYED_FOR_THE_RECORDER = (schema.TRUTH, schema.ORIGIN, schema.INFO)


@dataclass(frozen=True)
class ReplayOptions:
    """How :func:`replay_through_nodes` runs the chain.

    Attributes:
        rate: Replay rate (0 = as fast as the nodes keep up).
        start_s: Skip this much of the bag [s].
        topics: Topics to replay (None: all).
        windows: Flow-control windows overriding ``flow.FLOW_RULES`` (by relative topic).
        wait_s: Longest wait for the nodes to come up [s].
        layout: Where the nodes run, one of :data:`.launch.LAYOUTS`:
            ``'processes'`` (default, fastest): each node is its own executable in a child
            process (``python -m gnsscam_ros.nodes.<node>``, as ``ros2 run`` starts them)
            with a generated ``--params-file``; the replay and the recorder run in this
            process. The nodes then run in parallel on separate cores and each spins a
            small executor. ``'threads'``: the nodes in this process, one single-threaded
            executor per node on its own thread (an rclpy executor rebuilds its wait set
            on every wake-up, at a cost that grows with the number of entities it serves:
            per-node executors keep it small); all share one GIL with the replay.
            ``'pipeline'``: ``pipeline_node`` (the four nodes in one process, one executor
            thread each) in a child process.
        parameters: Node parameters ``{node name: {name: value}}``, over
            :data:`.launch.REPLAY_NODE_PARAMETERS`.
        database: A loaded map database for camera_node (``'threads'`` only; child
            processes need ``camera_node.database_path``).
        domain_id: ROS domain (default :func:`.launch.default_domain_id`).
        namespace: ROS namespace of the nodes, the replay and the recorder (default: a
            private one per run, :func:`.launch.private_namespace`). The result bag
            stores the topics without it (``/pose``).
        log_dir: Folder for the child processes' ROS logs and stderr (default: a new
            temporary folder).
        record_topics: Topics to record (default ``record.DEFAULT_TOPICS``).
        settle_s: After the replay, wait until the recorder saw nothing new for this
            long [s].
    """

    rate: float = 0.0
    start_s: float = 0.0
    topics: list[str] | None = None
    windows: dict[str, int] | None = None
    wait_s: float = 60.0
    layout: str = 'processes'
    parameters: dict[str, dict] | None = None
    database: object = None
    domain_id: int | None = None
    namespace: str | None = None
    log_dir: str | Path | None = None
    record_topics: list[str] | None = None
    settle_s: float = 0.5


def replay_through_nodes(bag: str | Path, result_bag: str | Path | None = None,
                         options: ReplayOptions | None = None, **overrides
                         ) -> tuple[ReplaySummary, RecordSummary | None]:
    """Replay a bag through the four nodes and record their outputs (one call).

    Args:
        bag: The dataset bag.
        result_bag: Bag to record the outputs into (must not exist); None: no recording.
        options: How to run (default :class:`ReplayOptions`).
        **overrides: Fields of :class:`ReplayOptions` replacing those of ``options``
            (``rate=0.0, layout='threads'``, ...).

    Returns:
        ``(replay summary, record summary or None)``.

    Raises:
        KeyboardInterrupt: Ctrl-C (or a ROS shutdown) interrupted the replay; the partial
            result bag is removed.
        BagError: Unreadable bag or result bag problems.
        RuntimeError: A child process died during the replay.
        ValueError: Unknown layout.
        TypeError: An override that is not a field of :class:`ReplayOptions`.
    """
    opts = dataclasses.replace(options or ReplayOptions(), **overrides)
    if opts.layout not in LAYOUTS:
        raise ValueError(f'unknown layout {opts.layout!r}; use one of {LAYOUTS}')
    params = merge_parameters(REPLAY_NODE_PARAMETERS, opts.parameters or {})
    domain = default_domain_id() if opts.domain_id is None else int(opts.domain_id)
    if opts.layout != 'threads':
        use_dds_profile(opts.log_dir if opts.log_dir is not None else tempfile.mkdtemp(
            prefix='gnsscam_dds_'))
    ns = opts.namespace or private_namespace()
    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain)
    nodes: list = []
    procs: list = []
    recorder = None
    spinner = None
    try:
        if opts.layout == 'threads':
            nodes = make_nodes(ctx, ns, params, opts.database)
        else:
            procs = start_node_processes(params, domain, opts.log_dir,
                                         opts.layout == 'pipeline', ns)
        if result_bag is not None:
            recorder = BagRecorder(result_bag, topics=opts.record_topics, context=ctx,
                                   namespace=ns, strip_namespace=True)
        spinner = NodeSpinner(nodes + ([recorder] if recorder is not None else []), ctx)
        summary = _play(bag, opts, ctx, ns, recorder is not None)
        if summary.interrupted:
            # Ctrl-C (or a shutdown) cut the replay short: the recording is partial and
            # is removed below, the nodes are stopped; the caller stops as on Ctrl-C.
            raise KeyboardInterrupt
        for proc, name in procs:
            summary.cpu_s[name] = process_cpu_s(proc.pid)
        for proc, name in procs:
            if proc.poll() is not None:
                raise RuntimeError(f'{name} exited with status {proc.returncode} during '
                                   'the replay')
        if recorder is None:
            return summary, None
        _wait_until_quiet(recorder, opts.settle_s)
        return summary, recorder.close()
    except BaseException:
        if recorder is not None:
            recorder.abort()
        raise
    finally:
        if spinner is not None:
            spinner.stop()
        for node in nodes + ([recorder] if recorder is not None else []):
            node.destroy_node()
        rclpy.try_shutdown(context=ctx)
        for proc, _ in procs:
            stop_process(proc)


def _play(bag: str | Path, opts: ReplayOptions, ctx: Context, namespace: str,
          recording: bool) -> ReplaySummary:
    """Play the bag into the running graph; the summary with this process's CPU time."""
    required = ()
    if recording:
        wanted = [schema.relative(t.split(':')[0])
                  for t in (opts.record_topics or _REPLAYED_FOR_THE_RECORDER)]
        required = tuple(t for t in wanted if t in _REPLAYED_FOR_THE_RECORDER)
    replayer = BagReplayer(bag, rate=opts.rate, start_s=opts.start_s, topics=opts.topics,
                           windows=opts.windows, wait_s=opts.wait_s, context=ctx,
                           namespace=namespace, require_subscribers=required,
                           settle_s=MATCH_SETTLE_S if opts.layout == 'threads'
                           else FRESH_PROCESSES_SETTLE_S)
    cpu0 = own_cpu_s()
    try:
        summary = replayer.play()
    finally:
        replayer.destroy_node()
    summary.cpu_s['replay'] = own_cpu_s() - cpu0
    return summary


def _wait_until_quiet(recorder: BagRecorder, settle_s: float) -> None:
    """Wait until the recorder has seen nothing new for ``settle_s`` (the last outputs of
    the nodes are in flight when the replay ends), at most ``max(10, 4 settle_s)`` s."""
    last, quiet_since = -1, time.monotonic()
    deadline = time.monotonic() + max(10.0, 4 * settle_s)
    while time.monotonic() - quiet_since < settle_s and time.monotonic() < deadline:
        total = sum(recorder.summary.counts.values())
        if total != last:
            last, quiet_since = total, time.monotonic()
        time.sleep(0.05)
