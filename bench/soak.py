r"""
Soak test of the ROS node: memory, latency and the accounting invariant over a long run.

Starts ``python -m cgags_ros.register_node`` as users do (node process + registration
process), latches the LiDAR bag's first target and publishes its source scans cycled at a
fixed rate with fresh stamps, for ``--duration`` seconds. Every /diagnostics message is
checked against the accounting invariant (sources received = published + rejected +
dropped + pending, and likewise for targets); every ``--sample`` seconds the resident
memory of both processes (from /proc) and the node's latency percentiles are recorded.

    .venv/bin/python -m bench.soak --duration 600 \
        --output out/bench/soak.json --plot out/bench/soak.png

Target: RSS growth after warm-up (the first minute) <= 20 MB for node + registration
process, and the invariant holding at every sample.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
import signal
import subprocess
import sys
import threading
import time

from bench.common import argument_parser, output_path, pyplot, save_figure, write_json
from cgags_ros.io.shared_data import shared_data_dir

REPO = Path(__file__).resolve().parents[1]
DOMAIN_ID = '59'
WARM_UP_S = 60.0


def rss_mb(pid: int) -> float:
    """Return the resident memory of ``pid`` in MB (0 when it is gone)."""
    try:
        with open(f'/proc/{pid}/statm', encoding='ascii') as f:
            return int(f.read().split()[1]) * os.sysconf('SC_PAGE_SIZE') / 1e6
    except (OSError, ValueError, IndexError):
        return 0.0


def balanced(v: dict[str, str]) -> bool:
    """Tell whether one /diagnostics message's buckets balance."""
    n = {k: int(x) for k, x in v.items() if k.startswith(('sources.', 'targets.'))
         and x.lstrip('-').isdigit()}
    return (n['sources.received'] == n['sources.published'] + n['sources.rejected']
            + n['sources.dropped'] + n['sources.pending']
            and n['targets.received'] == n['targets.used'] + n['targets.rejected']
            + n['targets.dropped'] + n['targets.pending']
            and v.get('accounting.ok') == 'True')


def main(argv: list[str] | None = None) -> int:  # noqa: C901 - one linear script
    """Start the node, publish, sample, report."""
    parser = argument_parser(__spec__.name, __doc__)
    parser.add_argument('--duration', type=float, default=600.0, help='seconds of publishing')
    parser.add_argument('--rate', type=float, default=10.0, help='source scans per second')
    parser.add_argument('--voxel-size', type=float, default=0.4, help='metres')
    parser.add_argument('--sample', type=float, default=5.0, help='seconds between samples')
    parser.add_argument('--output', type=Path, default=output_path('soak.json'),
                        help='samples and summary (default: %(default)s)')
    parser.add_argument('--plot', type=Path, default=output_path('soak.png'),
                        help='RSS and latency over time (default: %(default)s)')
    args = parser.parse_args(argv)

    os.environ.update(ROS_DOMAIN_ID=DOMAIN_ID, ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PoseStamped
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2

    from cgags_ros.io.bag import read_messages
    from cgags_ros.ros.outputs import to_rclpy_pointcloud2

    sources, target = [], None
    for rec in read_messages(shared_data_dir() / 'bags' / 'lidar'):
        if rec.topic == '/target_cloud' and target is None:
            target = to_rclpy_pointcloud2(rec.msg)
        elif rec.topic == '/source_cloud':
            sources.append(to_rclpy_pointcloud2(rec.msg))

    args.output.parent.mkdir(parents=True, exist_ok=True)
    log = open(args.output.with_suffix('.node.log'), 'w')
    proc = subprocess.Popen(
        [sys.executable, '-m', 'cgags_ros.register_node', '--ros-args',
         '-p', f'voxel_size:={args.voxel_size}',
         '-p', 'pairing.target_durability:=transient_local'],
        cwd=REPO, env=dict(os.environ, PYTHONUNBUFFERED='1'), stdout=log,
        stderr=subprocess.STDOUT)
    rclpy.init()
    io = rclpy.create_node('soak_io')
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    target_pub = io.create_publisher(PointCloud2, 'target_cloud', latched)
    source_pub = io.create_publisher(PointCloud2, 'source_cloud', 10)
    state = {'diag': {}, 'messages': 0, 'unbalanced': 0, 'poses': 0}

    def on_diag(msg):
        for status in msg.status:
            if status.hardware_id == '/register_node':
                values = {kv.key: kv.value for kv in status.values}
                state['diag'] = values
                state['messages'] += 1
                state['unbalanced'] += not balanced(values)

    io.create_subscription(DiagnosticArray, '/diagnostics', on_diag, 10)
    io.create_subscription(PoseStamped, '/register_node/pose',
                           lambda _: state.__setitem__('poses', state['poses'] + 1), 10)
    executor = SingleThreadedExecutor()
    executor.add_node(io)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    samples = []
    try:
        deadline = time.monotonic() + 60
        while not (source_pub.get_subscription_count() and int(state['diag'].get(
                'registration.pid', 0))) and time.monotonic() < deadline:
            time.sleep(0.1)
        target_pub.publish(target)
        start = time.monotonic()
        next_sample = start
        k = 0
        while time.monotonic() - start < args.duration:
            msg = sources[k % len(sources)]
            msg.header.stamp = io.get_clock().now().to_msg()
            source_pub.publish(msg)
            k += 1
            now = time.monotonic()
            if now >= next_sample:
                d = state['diag']
                registration = int(d.get('registration.pid', 0))
                samples.append({
                    't_s': now - start, 'sent': k, 'node_rss_mb': rss_mb(proc.pid),
                    'registration_rss_mb': rss_mb(registration) if registration else 0.0,
                    'published': int(d.get('published', 0)),
                    'dropped': int(d.get('sources.dropped', 0)),
                    'rejected': int(d.get('sources.rejected', 0)),
                    'p50_ms': 1e3 * float(d.get('latency_p50_s', 'nan')),
                    'p95_ms': 1e3 * float(d.get('latency_p95_s', 'nan')),
                    'balanced': balanced(d) if d else None})
                next_sample += args.sample
            time.sleep(max(0.0, start + k / args.rate - time.monotonic()))
        time.sleep(3.0)
    finally:
        final = dict(state['diag'])
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
        executor.shutdown(timeout_sec=2.0)
        spinner.join(timeout=5.0)
        io.destroy_node()
        rclpy.try_shutdown()
        log.close()

    after = [s for s in samples if s['t_s'] >= WARM_UP_S] or samples
    total = [s['node_rss_mb'] + s['registration_rss_mb'] for s in after]
    summary = {
        'duration_s': args.duration, 'rate_hz': args.rate, 'voxel_size': args.voxel_size,
        'sources_sent': k, 'poses_received': state['poses'],
        'diagnostics_messages': state['messages'], 'unbalanced_messages': state['unbalanced'],
        'final': {key: final.get(key) for key in (
            'sources.received', 'sources.published', 'sources.rejected', 'sources.dropped',
            'sources.pending', 'sources.lost_upstream', 'transport.profile',
            'registration.crashes', 'accounting.ok')},
        'rss_after_warm_up_mb': {'first': total[0], 'last': total[-1],
                                 'max': max(total), 'growth': total[-1] - total[0]},
        'node_exit_code': proc.returncode}
    write_json(args.output, {'summary': summary, 'samples': samples})
    print(json.dumps(summary, indent=1))
    print(f'wrote {args.output}, {plot(samples, args.plot)}')
    ok = state['unbalanced'] == 0 and summary['rss_after_warm_up_mb']['growth'] <= 20.0
    return 0 if ok else 1


def plot(samples: list[dict], path: Path) -> Path:
    """Write RSS (node, registration process, total) and latency (p50, p95) over time as a PNG."""
    plt = pyplot()

    t = [s['t_s'] / 60 for s in samples]
    fig, (a, b) = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    a.plot(t, [s['node_rss_mb'] for s in samples], label='node')
    a.plot(t, [s['registration_rss_mb'] for s in samples], label='registration process')
    a.plot(t, [s['node_rss_mb'] + s['registration_rss_mb'] for s in samples], label='total')
    a.set_ylabel('RSS [MB]')
    a.legend()
    b.plot(t, [s['p50_ms'] for s in samples], label='p50')
    b.plot(t, [s['p95_ms'] for s in samples], label='p95')
    b.set_ylabel('latency [ms]')
    b.set_xlabel('time [min]')
    b.legend()
    fig.tight_layout()
    return save_figure(fig, path, dpi=90)


if __name__ == '__main__':
    sys.exit(main())
