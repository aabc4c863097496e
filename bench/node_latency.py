"""
Latency of the ROS node: source-cloud receipt -> ~/pose publish, and queue boundedness.

Publishes the LiDAR bag's source clouds at a fixed rate (default 10 Hz, cycling through the
bag) against its target cloud (latched once), with the real pipeline, over real DDS in one
process, and prints a table:

    .venv/bin/python -m bench.node_latency --duration 20

Latency is measured inside the node (monotonic clock, from the source callback to the
publish of ~/pose), so it includes decoding, queueing, registration and covariance, not
DDS transport. "max pending" samples the pairing queue every 20 ms: it must never exceed
the pairs the engine keeps (``pairing.queue_depth``, or ``pairing.backlog`` when the
stream is tracked, as by default); the surplus shows up as dropped.queue_full. Sources are
published once the registration process reports ``registration.ready`` (its warm-up, 2-3 s
here, is timed separately): before that every pair waits and, at 10 Hz, ~25 of them were
dropped.
"""

from __future__ import annotations

import os
from pathlib import Path
import sys
import threading
import time

from bench.common import argument_parser
from cgags_ros.io.shared_data import shared_data_dir
import numpy as np


def main(argv: list[str] | None = None) -> int:
    parser = argument_parser(__spec__.name, __doc__)
    parser.add_argument('--bag', default=None, help='bag (default: shared data lidar bag)')
    parser.add_argument('--rate', type=float, default=10.0, help='source clouds per second')
    parser.add_argument('--duration', type=float, default=20.0, help='seconds of publishing')
    parser.add_argument('--voxel-size', type=float, default=0.4, help='metres')
    parser.add_argument('--queue-depth', type=int, default=None,
                        help="default: the node's default (pairing.queue_depth)")
    parser.add_argument('--registration-timeout', type=float, default=30.0,
                        help="0 runs the pipeline in the node's thread (no child process)")
    args = parser.parse_args(argv)

    # Before rclpy loads: a domain of its own, and no discovery beyond this host.
    os.environ.setdefault('ROS_DOMAIN_ID', '58')
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2

    from cgags_ros.io.bag import read_messages
    from cgags_ros.ros.outputs import to_rclpy_pointcloud2
    from cgags_ros.ros.node import RegisterNode

    bag = Path(args.bag) if args.bag else shared_data_dir() / 'bags' / 'lidar'
    sources, target = [], None
    for rec in read_messages(bag, ['/source_cloud', '/target_cloud']):
        if rec.topic == '/target_cloud' and target is None:
            target = to_rclpy_pointcloud2(rec.msg)
        elif rec.topic == '/source_cloud':
            sources.append(to_rclpy_pointcloud2(rec.msg))

    from cgags_ros.config.node import NodeConfig
    from cgags_ros.engine.pairing import queue_depth

    if args.queue_depth is None:
        args.queue_depth = NodeConfig().pairing.queue_depth
    rclpy.init()
    node = RegisterNode(parameter_overrides=[
        Parameter('voxel_size', value=args.voxel_size),
        Parameter('pairing.queue_depth', value=args.queue_depth),
        Parameter('pairing.target_durability', value='transient_local'),
        Parameter('runtime.registration_timeout', value=args.registration_timeout)])
    io = rclpy.create_node('bench_io')
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    target_pub = io.create_publisher(PointCloud2, 'target_cloud', latched)
    source_pub = io.create_publisher(PointCloud2, 'source_cloud', 10)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    executor.add_node(io)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    target_pub.publish(target)
    deadline = time.monotonic() + 30
    while not node.statistics().get('received_target') and time.monotonic() < deadline:
        time.sleep(0.05)
    # Steady state: sources only once the registration process has warmed up (a robot
    # starts the node before its sensors; until then pairs wait and the queue drops).
    warm_start = time.monotonic()
    while (args.registration_timeout > 0 and not node.statistics().get('registration.ready')
           and time.monotonic() < deadline + 120):
        time.sleep(0.05)
    warm_wait = time.monotonic() - warm_start

    # The pairs the engine keeps: queue_depth, or the tracking backlog when a stream is tracked.
    kept = queue_depth(node.engine.node_config, node.engine.pipeline_config)
    max_pending = 0
    period = 1.0 / args.rate
    start = time.monotonic()
    k = 0
    while time.monotonic() - start < args.duration:
        msg = sources[k % len(sources)]
        msg.header.stamp = node.get_clock().now().to_msg()  # unique stamps
        source_pub.publish(msg)
        k += 1
        next_t = start + k * period
        while time.monotonic() < next_t:
            max_pending = max(max_pending, node.engine.snapshot()['pairing']['pending'])
            time.sleep(0.02)
    time.sleep(3.0)  # let the last pairs finish
    stats = node.statistics()
    lat = np.array(node.engine.snapshot()['latencies'])

    executor.shutdown(timeout_sec=2.0)
    node.destroy_node()
    io.destroy_node()
    rclpy.try_shutdown()

    rows = [
        ('bag', str(bag.name)), ('rate (Hz)', f'{args.rate:g}'),
        ('duration (s)', f'{args.duration:g}'), ('voxel_size (m)', f'{args.voxel_size:g}'),
        ('queue_depth', str(args.queue_depth)),
        ('pairs kept (tracking: the backlog)', str(kept)),
        ('registration', 'child process' if args.registration_timeout > 0 else 'in thread'),
        ('waited for the registration process warm-up (s)', f'{warm_wait:.1f}'),
        ('sources published', str(k)),
        ('sources received', str(stats.get('received_source', 0))),
        ('poses published', str(stats.get('published', 0))),
        ('rejected (invalid etc.)', str(stats.get('rejected', 0))),
        ('dropped (queue_full)', str(stats.get('pairing.dropped.queue_full', 0))),
        ('max pending (<= pairs kept)', str(max_pending)),
        ('latency p50 (ms)', f'{1e3 * np.percentile(lat, 50):.0f}' if lat.size else 'n/a'),
        ('latency p95 (ms)', f'{1e3 * np.percentile(lat, 95):.0f}' if lat.size else 'n/a'),
        ('last total pipeline (ms)', f"{1e3 * stats.get('last_timing.total', float('nan')):.0f}"),
    ]
    width = max(len(r[0]) for r in rows)
    print(f"| {'metric'.ljust(width)} | value |")
    print(f"|{'-' * (width + 2)}|-------|")
    for name, value in rows:
        print(f'| {name.ljust(width)} | {value} |')
    bounded = max_pending <= kept
    print(f"\nqueue bounded: {'yes' if bounded else 'NO'}")
    return 0 if bounded else 1


if __name__ == '__main__':
    sys.exit(main())
