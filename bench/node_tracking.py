r"""
The node at a LiDAR's rate over DDS: real KITTI scans at 10 Hz, scan-to-map, tracked or not.

Run from the repository root (where other DDS programs run, in a network and /dev/shm
namespace of its own, as the DDS tests run)::

    .venv/bin/python -m bench.node_tracking --duration 60 \
        [--voxels 0.3 0.5 1.0] [--tracking on off] [--orders pingpong looped] \
        [--repos . /tmp/main --rounds 2] [--publisher-nice -10] \
        [--output out/bench/node_tracking.json]

For each voxel size and tracking setting a ``register_node`` process is started as users run
it (``python -m cgags_ros.register_node``, registration in its child process, the default
queue depth); with ``--repos`` the node runs from each checkout in turn (an A/B against
another revision: ``git worktree add /tmp/main main``), ``--rounds`` times, so that the
machine's drift falls on both alike; this process publishes scan 0 of ``<shared
data>/kitti/seq00_16scans`` latched on ``target_cloud`` (transient local: the map) and then,
per order, the 16 scans (~4 MB PointCloud2 each, all their fields) on ``source_cloud`` with
sensor-data QoS at ``--rate`` for ``--duration`` seconds, stamped by a regular sensor clock.
Both processes load the shipped Fast DDS profile (``config/fastdds_large_data.xml`` through
FASTRTPS_DEFAULT_PROFILES_FILE). Orders: ``pingpong`` (0..15, 14..1, ...: smooth motion,
reversing at the ends) and ``looped`` (0..15, 0..15, ...: a 12 m jump back every 16 scans).

Per cell: scans sent, poses published, latency from publishing a scan to receiving its
``~/pose`` (p50/p95, this host's monotonic clock), the paths of the registered scans from
``~/result`` (tracked/global, and why each global one was), what the node dropped (queue
full, skipped catching up) or rejected, and every
published pose against ``pseudo_gt.txt`` (scan k in scan 0's frame): the worst rotation and
translation error, how many are within 1 deg / 0.2 m, how many beyond 5 deg / 0.6 m; and the
median stage times the node reports (``timings``) of tracked and of global scans, and the
median of a tracked scan's latency minus its registration time: what transport, decoding,
queueing, the transfer to the registration process and back, and publishing cost; and the
node's own latency (its receipt of a scan to the result), of all scans from /diagnostics
and of the tracked ones from ``~/result``'s ``latency_s`` (where the node reports it). The
machine may be loaded by other work: compare cells of one run, and note the load average
printed with the table.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
import subprocess
import sys
import threading
import time
from typing import Any

from bench.common import (argument_parser, machine, output_path, stop_process, write_json,
                          write_text)
import numpy as np
import yaml

REPO = Path(__file__).resolve().parents[1]
PROFILE = REPO / 'config' / 'fastdds_large_data.xml'
DOMAIN_ID = 67  # this bench's ROS domain
SCANS = 16
STAGES = ('downsample', 'refinement', 'validation', 'total')


def orders(count: int) -> dict[str, list[int]]:
    """Return the scan indices of each order, ``count`` scans long."""
    pingpong = list(range(SCANS)) + list(range(SCANS - 2, 0, -1))
    return {'pingpong': [pingpong[i % len(pingpong)] for i in range(count)],
            'looped': [i % SCANS for i in range(count)]}


def dds_environment(domain_id: int) -> dict[str, str]:
    """Return this environment with the shipped profile, ``domain_id`` and local discovery."""
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain_id), PYTHONUNBUFFERED='1',
               ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
               FASTRTPS_DEFAULT_PROFILES_FILE=str(PROFILE))
    env.pop('FASTDDS_BUILTIN_TRANSPORTS', None)
    return env


def start_node(ros_args: list[str], env: dict[str, str], log_path: Path,
               repo: Path = REPO) -> tuple[subprocess.Popen, Any]:
    """
    Start ``python -m cgags_ros.register_node --ros-args ROS_ARGS``; return it and its log.

    ``repo``: the checkout whose ``cgags_ros`` runs (``-m`` imports from the working
    directory first).
    """
    log = open(log_path, 'w+', encoding='utf-8')
    proc = subprocess.Popen([sys.executable, '-m', 'cgags_ros.register_node', '--ros-args']
                            + ros_args, cwd=repo, env=dict(env, PYTHONPATH=str(repo)),
                            stdout=log, stderr=subprocess.STDOUT, text=True,
                            preexec_fn=None if _niceness() == _STARTED_NICENESS else _as_started)
    return proc, log


def _niceness() -> int:
    return os.getpriority(os.PRIO_PROCESS, 0)


_STARTED_NICENESS = _niceness()


def _as_started() -> None:
    """Give the node the niceness this process started with (``--publisher-nice``)."""
    os.setpriority(os.PRIO_PROCESS, 0, _STARTED_NICENESS)


def revision(repo: Path) -> str:
    """Return the short commit of ``repo`` (with '+' when its tree has changes)."""
    def git(*args: str) -> str:
        return subprocess.run(['git', '-C', str(repo), *args], capture_output=True,
                              text=True).stdout.strip()

    changed = git('status', '--porcelain', '--untracked-files=no')
    return git('rev-parse', '--short', 'HEAD') + ('+' if changed else '')


class StreamClient:
    """
    The sensor's and the observer's side: publishes scans and the map, records the node.

    ``sent`` maps a scan's stamp (ns) to (monotonic publish time, scan index); ``poses`` a
    stamp to (monotonic receipt time, 4x4 pose) from ``~/pose``; ``results`` a stamp to its
    ``~/result`` record; ``diagnostics`` holds the node's last /diagnostics values (text).
    """

    def __init__(self, context: Any, reliable: bool = False, node_name: str = 'register_node'):
        import rclpy
        from rclpy.qos import (DurabilityPolicy, qos_profile_sensor_data, QoSProfile,
                               ReliabilityPolicy)
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseStamped
        from sensor_msgs.msg import PointCloud2
        from std_msgs.msg import String

        self.node = rclpy.create_node('tracking_stream', context=context)
        source_qos = (QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE) if reliable
                      else qos_profile_sensor_data)
        self.source_pub = self.node.create_publisher(PointCloud2, 'source_cloud', source_qos)
        self.target_pub = self.node.create_publisher(PointCloud2, 'target_cloud', QoSProfile(
            depth=1, reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL))
        deep = QoSProfile(depth=200, reliability=ReliabilityPolicy.RELIABLE)
        self.node.create_subscription(PoseStamped, f'/{node_name}/pose', self._on_pose, deep)
        self.node.create_subscription(String, f'/{node_name}/result', self._on_result, deep)
        self.node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, 10)
        self._hardware_id = f'/{node_name}'
        self._lock = threading.Lock()
        self.sent: dict[int, tuple[float, int]] = {}
        self.poses: dict[int, tuple[float, np.ndarray]] = {}
        self.results: dict[int, dict[str, Any]] = {}
        self.diagnostics: dict[str, str] = {}

    def _on_pose(self, msg: Any) -> None:
        from cgags_ros.io.pointcloud2 import pose_to_transform

        now = time.monotonic()
        stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
        with self._lock:
            self.poses[stamp] = (now, pose_to_transform(msg))

    def _on_result(self, msg: Any) -> None:
        record = json.loads(msg.data)
        with self._lock:
            self.results[int(record['source_stamp_ns'])] = record

    def _on_diag(self, msg: Any) -> None:
        for status in msg.status:
            if status.hardware_id == self._hardware_id:
                values = {kv.key: kv.value for kv in status.values}
                with self._lock:
                    self.diagnostics = values

    def forget(self) -> None:
        """Drop the last node's /diagnostics (before another node starts)."""
        with self._lock:
            self.diagnostics = {}

    def value(self, key: str) -> str | None:
        """Return the node's last /diagnostics value of ``key``."""
        with self._lock:
            return self.diagnostics.get(key)

    def play(self, msgs: list, indices: list[int], rate: float) -> list[int]:
        """Publish ``msgs[k]`` for k in ``indices`` at ``rate`` Hz; return their stamps (ns)."""
        period_ns = int(round(1e9 / rate))
        t0, start = time.time_ns(), time.monotonic()
        stamps = []
        for i, k in enumerate(indices):
            time.sleep(max(0.0, start + i / rate - time.monotonic()))
            msg = msgs[k]
            stamp = t0 + i * period_ns  # a regular sensor clock, as a LiDAR's
            msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp, 10**9)
            msg.header.frame_id = 'velodyne'
            with self._lock:
                self.sent[stamp] = (time.monotonic(), k)
            self.source_pub.publish(msg)
            stamps.append(stamp)
        return stamps

    def settle(self, stamps: list[int], quiet_s: float = 5.0, limit_s: float = 120.0) -> None:
        """Wait until every stamp has a ~/result record, or nothing new came for ``quiet_s``."""
        deadline, last, seen = time.monotonic() + limit_s, time.monotonic(), -1
        while time.monotonic() < deadline:
            with self._lock:
                done = sum(s in self.results for s in stamps)
            if done == len(stamps):
                return
            if done != seen:
                seen, last = done, time.monotonic()
            elif time.monotonic() - last > quiet_s:
                return
            time.sleep(0.05)


def kitti_messages() -> list:
    """Return the 16 KITTI scans as PointCloud2 messages with all their fields."""
    from bench.transport import load_clouds

    return load_clouds('kitti')


def pseudo_ground_truth() -> np.ndarray:
    """Return (16, 4, 4): scan k's pose in scan 0's frame."""
    from bench.datasets.rigs import KITTI_SCANS
    from cgags_ros.io.shared_data import shared_data_dir

    path = (shared_data_dir() / KITTI_SCANS).parent / 'pseudo_gt.txt'
    return np.loadtxt(path).reshape(-1, 4, 4)


def summarize(client: StreamClient, stamps: list[int], truth: np.ndarray) -> dict[str, Any]:
    """Return one cell's numbers for the scans published with ``stamps``."""
    from cgags_ros.geometry import rotation_error_deg, translation_error

    latencies, rot, trans, overheads, node_tracked = [], [], [], [], []
    paths = {'tracked': 0, 'global': 0}
    outcomes: dict[str, int] = {}
    global_because: dict[str, int] = {}
    stages: dict[str, dict[str, list[float]]] = {p: {s: [] for s in STAGES} for p in paths}
    for stamp in stamps:
        sent_at, k = client.sent[stamp]
        record = client.results.get(stamp)
        if record is not None:
            why = record['outcome'] + (f".{record['cause']}" if record['cause'] else '')
            outcomes[why] = outcomes.get(why, 0) + 1
            if record.get('path') in paths:
                paths[record['path']] += 1
                because = record.get('stats', {}).get('global_because')
                if record['path'] == 'global' and because:
                    why = because.split(' (')[0]  # without the numbers
                    global_because[why] = global_because.get(why, 0) + 1
                for stage in STAGES:
                    if stage in record.get('timings', {}):
                        stages[record['path']][stage].append(record['timings'][stage])
        pose = client.poses.get(stamp)
        if pose is None:
            continue
        latencies.append(pose[0] - sent_at)
        if record is not None and record.get('path') == 'tracked':
            overheads.append(latencies[-1] - record['timings'].get('total', np.nan))
            if record.get('latency_s') is not None:
                node_tracked.append(record['latency_s'])
        rot.append(rotation_error_deg(pose[1], truth[k]))
        trans.append(translation_error(pose[1], truth[k]))
    rot_a, trans_a, lat = np.array(rot), np.array(trans), np.array(latencies)
    scans = []  # per scan: publish to pose, in the node, registering (ms; None: none)
    for stamp in stamps:
        sent_at, k = client.sent[stamp]
        record, pose = client.results.get(stamp) or {}, client.poses.get(stamp)
        node_s, total_s = record.get('latency_s'), record.get('timings', {}).get('total')
        scans.append([k, record.get('path'),
                      None if pose is None else round(1e3 * (pose[0] - sent_at), 1),
                      None if node_s is None else round(1e3 * node_s, 1),
                      None if total_s is None else round(1e3 * total_s, 1)])
    return {
        'scans': scans,
        'sent': len(stamps), 'published': len(latencies),
        'results': sum(s in client.results for s in stamps),
        'latency_p50_ms': _ms(lat, 50), 'latency_p95_ms': _ms(lat, 95),
        'within_100ms': int(np.sum(lat <= 0.1)),
        'tracked': paths['tracked'], 'global': paths['global'], 'outcomes': outcomes,
        'global_because': global_because,
        'within_1deg_20cm': int(np.sum((rot_a <= 1.0) & (trans_a <= 0.2))),
        'beyond_5deg_60cm': int(np.sum((rot_a > 5.0) | (trans_a > 0.6))),
        'max_rotation_deg': float(rot_a.max()) if rot_a.size else None,
        'max_translation_m': float(trans_a.max()) if trans_a.size else None,
        'tracked_overhead_ms': _ms(np.array(overheads), 50),
        # The node's own latency, from its callback's receipt of a scan to the result (its
        # recent scans, /diagnostics): the rest of the latency above is outside the node.
        'node_latency_p50_ms': _seconds_ms(client.value('latency_p50_s')),
        'node_latency_p95_ms': _seconds_ms(client.value('latency_p95_s')),
        'node_tracked_latency_p50_ms': _ms(np.array(node_tracked), 50),
        'node_tracked_latency_p95_ms': _ms(np.array(node_tracked), 95),
        'periodic_checks': client.value('tracking.periodic_checks'),
        'checks_rss_mb': client.value('memory.checks_rss_mb'),
        'registration_rss_mb': client.value('memory.registration_rss_mb'),
        'node_rss_mb': client.value('memory.node_rss_mb'),  # its DDS histories included
        'stage_median_ms': {p: {s: _ms(np.array(v), 50) for s, v in by.items()}
                            for p, by in stages.items()},
    }


def _seconds_ms(text: str | None) -> float | None:
    return None if text is None else round(1e3 * float(text), 1)


def _ms(values: np.ndarray, q: float) -> float | None:
    return round(1e3 * float(np.percentile(values, q)), 1) if values.size else None


def run_node(client: StreamClient, msgs: list, truth: np.ndarray, voxel: float,
             tracking: bool, names: list[str], duration: float, rate: float,
             folder: Path, queue_depth: int, keys: dict[str, Any],
             repo: Path = REPO) -> list[dict[str, Any]]:
    """
    Start a node for one voxel size and tracking setting; stream each order through it.

    ``keys``: configuration keys for the node's ``config_file`` (none when empty); ``repo``:
    the checkout the node runs from.
    """
    args = ['-p', f'voxel_size:={voxel}', '-p', 'pairing.target_durability:=transient_local',
            '-p', f"tracking.enabled:={'true' if tracking else 'false'}",
            '-p', f'pairing.queue_depth:={queue_depth}', '-p', 'output.diagnostics_period:=0.5']
    if keys:
        config_file = write_text(folder / 'node_tracking_config.yaml', yaml.safe_dump(keys))
        args += ['-p', f'config_file:={config_file}']
    log_path = folder / f"node_{voxel:g}_{'on' if tracking else 'off'}.log"
    # A node stopped before leaves its match and its last /diagnostics behind a while.
    _wait(lambda: not client.source_pub.get_subscription_count(), 60, 'the last node gone')
    client.forget()
    proc, log = start_node(args, dds_environment(DOMAIN_ID), log_path, repo)
    cells = []
    try:
        _wait(lambda: client.value('registration.ready') == 'True', 300, 'the node warm', proc)
        _wait(lambda: client.source_pub.get_subscription_count(), 60, 'the match', proc)
        client.target_pub.publish(msgs[0])
        _wait(lambda: client.value('targets.received') == '1', 60, 'the map received', proc)
        count = int(round(duration * rate))
        for name in names:
            time.sleep(1.0)  # a gap longer than tracking.max_age between the orders
            stamps = client.play(msgs, orders(count)[name], rate)
            client.settle(stamps)
            cell = {'revision': revision(repo), 'voxel_size': voxel, 'tracking': tracking,
                    'order': name,
                    'duration_s': duration, 'rate_hz': rate, 'queue_depth': queue_depth,
                    'config_file': keys,
                    'load_average': os.getloadavg()[0],
                    'publisher_niceness': _niceness(),
                    **summarize(client, stamps, truth)}
            print(json.dumps({k: v for k, v in cell.items() if k != 'scans'}), flush=True)
            cells.append(cell)
    finally:
        stop_process(proc, log)
    return cells


def _wait(predicate: Any, timeout: float, what: str,
          proc: subprocess.Popen | None = None) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        ended = proc is not None and proc.poll() is not None
        if ended or time.monotonic() > deadline:
            raise RuntimeError(f'gave up waiting for {what} (node ended: {ended})')
        time.sleep(0.05)


def table(cells: list[dict[str, Any]]) -> str:
    """Return the Markdown table of docs/benchmarks.md."""
    lines = ['| revision | voxel | tracking | order | sent | published | latency p50 / p95 ms | '
             'node p50 / p95 ms (tracked) | tracked / global | dropped | worst | '
             'within 1° / 0.2 m; beyond 5° / 0.6 m | '
             'tracked ms: downsample / refinement / gates / total; latency - total | '
             'global total ms |',
             '|---|---|---|---|---|---|---|---|---|---|---|---|---|---|']
    for c in cells:
        tracked, glob = c['stage_median_ms']['tracked'], c['stage_median_ms']['global']
        dropped = sum(v for k, v in c['outcomes'].items() if k.startswith('dropped'))
        worst = ('' if c['max_rotation_deg'] is None else
                 f"{c['max_rotation_deg']:.2f}° / {100 * c['max_translation_m']:.1f} cm")
        stages = ' / '.join(_text(tracked[s]) for s in STAGES)
        node = (f"{_text(c['node_latency_p50_ms'])} / {_text(c['node_latency_p95_ms'])}"
                + (f" ({_text(c['node_tracked_latency_p50_ms'])} / "
                   f"{_text(c['node_tracked_latency_p95_ms'])})"
                   if c.get('node_tracked_latency_p95_ms') is not None else ''))
        lines.append(
            f"| {c.get('revision', '')} | {c['voxel_size']:g} m | "
            f"{'on' if c['tracking'] else 'off'} | {c['order']} | "
            f"{c['sent']} | {c['published']} | {_text(c['latency_p50_ms'])} / "
            f"{_text(c['latency_p95_ms'])} | {node} | {c['tracked']} / {c['global']} | "
            f'{dropped} | '
            f"{worst} | {c['within_1deg_20cm']}; {c['beyond_5deg_60cm']} | {stages}; "
            f"{_text(c['tracked_overhead_ms'])} | "
            f"{_text(glob['total'])} |")
    return '\n'.join(lines)


def _text(value: float | None) -> str:
    return '' if value is None else f'{value:.0f}'


def main(argv: list[str] | None = None) -> int:
    parser = argument_parser(__spec__.name, __doc__)
    parser.add_argument('--voxels', type=float, nargs='+', default=[0.3, 0.5, 1.0])
    parser.add_argument('--tracking', nargs='+', choices=('on', 'off'), default=['on', 'off'])
    parser.add_argument('--orders', nargs='+', choices=('pingpong', 'looped'),
                        default=['pingpong', 'looped'])
    parser.add_argument('--duration', type=float, default=60.0, help='seconds per order')
    parser.add_argument('--rate', type=float, default=10.0, help='scans per second')
    parser.add_argument('--queue-depth', type=int, default=None,
                        help="pairing.queue_depth (default: the node's)")
    parser.add_argument('--set', action='append', default=[], metavar='KEY=VALUE',
                        help="a key of the node's config_file (repeatable), e.g. --set "
                        'pairing.backlog=1 (a queue of one pair: the stream restarts from '
                        'the newest scan after a global registration)')
    parser.add_argument('--repos', nargs='+', type=Path, default=[REPO],
                        help='checkouts to run the node from, alternated (default: this one)')
    parser.add_argument('--rounds', type=int, default=1,
                        help='times each checkout runs each cell, alternated')
    parser.add_argument('--publisher-nice', type=int, default=None, metavar='N',
                        help='run this process (the publisher and its DDS threads) at niceness '
                        'N, the node at the one it was started with: negative N needs root')
    parser.add_argument('--output', default=None,
                        help='default: out/bench/node_tracking.json')
    args = parser.parse_args(argv)
    if args.publisher_nice is not None:  # before rclpy starts the DDS threads, which inherit it
        os.setpriority(os.PRIO_PROCESS, 0, args.publisher_nice)

    for key, value in dds_environment(DOMAIN_ID).items():  # before rclpy loads
        os.environ[key] = value
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor

    from cgags_ros.config.fields import parse_key_values
    from cgags_ros.config.node import configs_from_parameters, NodeConfig

    queue_depth = args.queue_depth or NodeConfig().pairing.queue_depth
    keys = parse_key_values(args.set)
    configs_from_parameters(keys)  # a typo fails here, not in the node
    msgs, truth = kitti_messages(), pseudo_ground_truth()
    context = Context()
    rclpy.init(context=context, domain_id=DOMAIN_ID)
    client = StreamClient(context)
    # Single-threaded: a multi-threaded executor's own loop kept this process's publishing
    # thread from waking on time, and the scans went out late and in bursts (tracking.md).
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(client.node)
    threading.Thread(target=executor.spin, daemon=True).start()
    out = Path(args.output) if args.output else output_path('node_tracking.json')
    out.parent.mkdir(parents=True, exist_ok=True)
    cells = []
    try:
        for _ in range(args.rounds):
            for voxel in args.voxels:
                for tracking in args.tracking:
                    for repo in args.repos:
                        cells += run_node(client, msgs, truth, voxel, tracking == 'on',
                                          args.orders, args.duration, args.rate, out.parent,
                                          queue_depth, keys, repo.resolve())
    finally:
        executor.shutdown(timeout_sec=2.0)
        client.node.destroy_node()
        context.try_shutdown()
    write_json(out, {'machine': machine(), 'cells': cells})
    print(table(cells))
    print(f'load average at the end: {os.getloadavg()}; wrote {out}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
