r"""
How many large PointCloud2 messages cross DDS between two processes on one host.

A publisher process sends clouds best-effort (sensor-data QoS, as LiDAR drivers do) at a
fixed rate; a subscriber process (a bare rclpy subscription, or ``register_node`` itself
with ``--node``) counts what reaches its callback. Each process gets its own transport
settings, so the cause of a loss can be isolated (see docs/transport.md):

    flock /tmp/cgags-dds.lock .venv/bin/python -m bench.transport \
        --clouds kitti --rate 10 --count 100 --settings default shipped shm_16mb udp_4mb

``--settings`` names a setting for both processes, or ``PUB/SUB`` for one each:
``default`` (Fast DDS as shipped: shared memory with 512-KB segments, then UDP with the
kernel's default socket buffers), ``shipped`` (config/fastdds_large_data.xml), ``shm_16mb``
(shared memory only, 16-MB segment), ``shm_512kb`` (shared memory only, Fast DDS's default
segment), ``udp`` (UDPv4 only, default socket buffers), ``udp_4mb`` (UDPv4 only, 4-MB
socket buffers), ``udp_4mb_1400`` (the same with datagrams cut to 1400 bytes by RTPS, as
for a 1500-byte MTU link without IP fragmentation), ``large_data`` (Fast DDS's builtin
LARGE_DATA transports). ``--clouds`` is ``kitti`` (the 16 real scans with all their fields,
~4 MB each), ``bag`` (the LiDAR bag's source clouds, ~1.1 MB) or a size in MB (synthetic
xyz clouds).

The publisher runs as ``--role pub`` in a child process; so does the subscriber
(``--role sub``). Prints one JSON line per run and writes them all to ``--output``.

``--discovery SUBNET`` (ROS's default; LOCALHOST otherwise, as the tests run) changes
what Fast DDS does on one host. ``--netns PUB SUB`` runs the two in network namespaces
joined by a link, as two hosts (discovery range SUBNET; shared memory is then not used);
docs/transport.md sets them up.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
import signal
import subprocess
import sys
import tempfile
import threading
import time

from bench.common import argument_parser, output_path, write_json

REPO = Path(__file__).resolve().parents[1]
DOMAIN_ID = '79'  # --domain
SHIPPED = REPO / 'config' / 'fastdds_large_data.xml'

# name -> (transport descriptors, use_builtin_transports) of a generated profile
_UDP = '<transport_descriptor><transport_id>udp</transport_id><type>UDPv4</type>{}' \
       '</transport_descriptor>'
_SHM = '<transport_descriptor><transport_id>shm</transport_id><type>SHM</type>' \
       '<segment_size>{}</segment_size></transport_descriptor>'
PROFILES = {
    'shm_16mb': ([_SHM.format(16 * 2**20)], ['shm']),
    'shm_512kb': ([_SHM.format(512 * 2**10)], ['shm']),
    'udp': ([_UDP.format('')], ['udp']),
    'udp_4mb': ([_UDP.format('<sendBufferSize>4194304</sendBufferSize>'
                             '<receiveBufferSize>4194304</receiveBufferSize>')], ['udp']),
    'udp_4mb_1400': ([_UDP.format('<sendBufferSize>4194304</sendBufferSize>'
                                  '<receiveBufferSize>4194304</receiveBufferSize>'
                                  '<maxMessageSize>1400</maxMessageSize>')], ['udp']),
}
SETTINGS = ('default', 'shipped', 'large_data', *PROFILES)


def profile_xml(name: str) -> str:
    """Return a Fast DDS profile that uses only the transports of setting ``name``."""
    descriptors, ids = PROFILES[name]
    refs = ''.join(f'<transport_id>{i}</transport_id>' for i in ids)
    return ('<?xml version="1.0" encoding="UTF-8" ?>'
            '<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">'
            f'<transport_descriptors>{"".join(descriptors)}</transport_descriptors>'
            '<participant profile_name="bench" is_default_profile="true"><rtps>'
            f'<userTransports>{refs}</userTransports>'
            '<useBuiltinTransports>false</useBuiltinTransports>'
            '</rtps></participant></profiles>')


def setting_env(name: str, folder: Path, discovery: str) -> dict[str, str]:
    """Return the environment of one process under setting ``name``."""
    env = dict(os.environ, PYTHONUNBUFFERED='1', ROS_AUTOMATIC_DISCOVERY_RANGE=discovery,
               FASTRTPS_DEFAULT_PROFILES_FILE='')
    env.pop('FASTDDS_BUILTIN_TRANSPORTS', None)
    if name == 'shipped':
        env['FASTRTPS_DEFAULT_PROFILES_FILE'] = str(SHIPPED)
    elif name == 'large_data':
        env['FASTDDS_BUILTIN_TRANSPORTS'] = 'LARGE_DATA'
    elif name != 'default':
        path = folder / f'{name}.xml'
        path.write_text(profile_xml(name))
        env['FASTRTPS_DEFAULT_PROFILES_FILE'] = str(path)
    return env


# --- the clouds -------------------------------------------------------------------------------

def load_clouds(which: str) -> list:
    """Return the rclpy PointCloud2 messages to cycle through."""
    import numpy as np

    from cgags_ros.io.pcd import read_fields as read_pcd_fields
    from cgags_ros.io.shared_data import shared_data_dir
    from cgags_ros.ros.outputs import fields_to_pointcloud2, to_rclpy_pointcloud2

    if which == 'kitti':
        folder = shared_data_dir() / 'kitti' / 'seq00_16scans' / 'pcd'
        return [fields_to_pointcloud2(read_pcd_fields(p)) for p in sorted(folder.glob('*.pcd'))]
    if which == 'bag':
        from cgags_ros.io.bag import read_messages
        return [to_rclpy_pointcloud2(r.msg)
                for r in read_messages(shared_data_dir() / 'bags' / 'lidar', ['/source_cloud'])]
    n = int(float(which) * 1e6 / 12)
    rng = np.random.default_rng(0)
    table = np.zeros(n, dtype=[('x', '<f4'), ('y', '<f4'), ('z', '<f4')])
    for c in 'xyz':
        table[c] = rng.uniform(-50, 50, n)
    return [fields_to_pointcloud2(table)]


# --- the two roles ---------------------------------------------------------------------------

def _no_empty_profile() -> None:
    """Unset an empty FASTRTPS_DEFAULT_PROFILES_FILE (Fast DDS would log an error)."""
    if not os.environ.get('FASTRTPS_DEFAULT_PROFILES_FILE'):
        os.environ.pop('FASTRTPS_DEFAULT_PROFILES_FILE', None)


def run_sub(topic: str) -> int:
    """Count the clouds that reach a sensor-data subscription until 'stop' on stdin."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import PointCloud2

    _no_empty_profile()
    rclpy.init()
    node = rclpy.create_node('bench_transport_sub')
    stamps: set[int] = set()
    node.create_subscription(
        PointCloud2, topic,
        lambda m: stamps.add(m.header.stamp.sec * 10**9 + m.header.stamp.nanosec),
        qos_profile_sensor_data)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    threading.Thread(target=executor.spin, daemon=True).start()
    print('ready', flush=True)
    sys.stdin.readline()
    print(json.dumps({'received': len(stamps), 'stamps_ns': sorted(stamps)}), flush=True)
    os._exit(0)  # the executor thread may be inside a callback: no orderly shutdown needed


def run_pub(topic: str, clouds: str, rate: float, count: int, node: bool) -> int:
    """Publish ``count`` clouds best-effort at ``rate`` Hz once a subscriber matched."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import DurabilityPolicy, qos_profile_sensor_data, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2

    from diagnostic_msgs.msg import DiagnosticArray

    msgs = load_clouds(clouds)
    _no_empty_profile()
    rclpy.init()
    io = rclpy.create_node('bench_transport_pub')
    pub = io.create_publisher(PointCloud2, topic, qos_profile_sensor_data)
    values: dict[str, str] = {}
    if node:
        target_pub = io.create_publisher(PointCloud2, 'target_cloud', QoSProfile(
            depth=1, reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL))

        def on_diag(msg):
            for status in msg.status:
                if status.hardware_id == '/register_node':
                    values.clear()
                    values.update({kv.key: kv.value for kv in status.values})
        io.create_subscription(DiagnosticArray, '/diagnostics', on_diag, 10)
    executor = SingleThreadedExecutor()
    executor.add_node(io)
    threading.Thread(target=executor.spin, daemon=True).start()
    deadline = time.monotonic() + 180  # a node's registration process warms up first
    while not pub.get_subscription_count() or (
            node and values.get('registration.ready') != 'True'):
        if time.monotonic() > deadline:
            print(json.dumps({'error': 'no subscriber ready in 180 s'}), flush=True)
            os._exit(1)
        time.sleep(0.05)
    time.sleep(1.0)  # let every locator of the match be known before the first message
    if node:
        target_pub.publish(msgs[0])
    start = time.monotonic()
    period_ns = int(round(1e9 / rate))
    t0 = time.time_ns()
    for k in range(count):
        time.sleep(max(0.0, start + k / rate - time.monotonic()))
        msg = msgs[k % len(msgs)]
        stamp = t0 + k * period_ns  # a regular sensor clock, as a LiDAR's
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp, 10**9)
        msg.header.frame_id = 'velodyne'
        pub.publish(msg)
    elapsed = time.monotonic() - start
    out = {'sent': count, 'bytes': len(msgs[0].data), 'publish_s': round(elapsed, 2)}
    if node:
        time.sleep(3.0)
        out.update({k: values.get(k) for k in ('sources.received', 'sources.lost_upstream',
                                               'sources.period_s', 'accounting.ok')})
    print(json.dumps(out), flush=True)
    os._exit(0)


# --- one measurement -------------------------------------------------------------------------

def measure(clouds: str, rate: float, count: int, setting: str, node: bool,
            folder: Path, netns: list[str] | None = None, discovery: str = 'LOCALHOST') -> dict:
    """Run one publisher/subscriber pair and return sent, received and the settings."""
    pub_set, _, sub_set = setting.partition('/')
    sub_set = sub_set or pub_set
    pub_ns, sub_ns = ([['ip', 'netns', 'exec', n] for n in netns] if netns else ([], []))
    me = [sys.executable, '-m', __spec__.name]
    discovery = 'SUBNET' if netns else discovery
    sub_env = setting_env(sub_set, folder, discovery)
    if node:
        sub = subprocess.Popen(
            sub_ns + [sys.executable, '-m', 'cgags_ros.register_node', '--ros-args',
                      '-p', 'voxel_size:=1.0',
                      '-p', 'pairing.target_durability:=transient_local',
                      '-p', 'output.diagnostics_period:=0.2'],
            cwd=REPO, env=sub_env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    else:
        sub = subprocess.Popen(sub_ns + me + ['--role', 'sub'], cwd=REPO, env=sub_env,
                               stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        while sub.stdout.readline().strip() != 'ready':
            pass
    pub = subprocess.run(pub_ns + me + ['--role', 'pub', '--clouds', clouds, '--rate',
                                        str(rate), '--count', str(count)]
                         + (['--node'] if node else []),
                         cwd=REPO, env=setting_env(pub_set, folder, discovery),
                         capture_output=True, text=True, timeout=240 + count / rate)
    lines = [ln for ln in pub.stdout.splitlines() if ln.startswith('{')]
    row = {'clouds': clouds, 'rate_hz': rate, 'pub': pub_set, 'sub': sub_set,
           'subscriber': 'register_node' if node else 'rclpy',
           'hosts': 'two (netns)' if netns else 'one', 'discovery': discovery}
    row.update(json.loads(lines[-1]) if lines else {'error': pub.stderr[-500:]})
    if node:
        sub.send_signal(signal.SIGINT)
        sub.wait(timeout=30)
        row['received'] = int(row.get('sources.received') or 0)
    else:
        time.sleep(2.0)  # the last message in flight
        out, _ = sub.communicate('stop\n', timeout=30)
        got = json.loads(out.strip().splitlines()[-1])
        # how far apart, in sensor periods, the received scans are (1: none lost between)
        steps = [round((b - a) * rate / 1e9) for a, b in zip(got['stamps_ns'],
                                                             got['stamps_ns'][1:])]
        row.update(received=got['received'],
                   intervals_in_periods={k: steps.count(k) for k in sorted(set(steps))})
    return row


def main(argv: list[str] | None = None) -> int:
    parser = argument_parser(__spec__.name, __doc__)
    parser.add_argument('--role', choices=('run', 'pub', 'sub'), default='run')
    parser.add_argument('--clouds', nargs='+', default=['kitti'])
    parser.add_argument('--rate', type=float, nargs='+', default=[10.0], help='Hz')
    parser.add_argument('--count', type=int, default=100, help='clouds per run')
    parser.add_argument('--settings', nargs='+', default=['default', 'shipped'])
    parser.add_argument('--node', action='store_true',
                        help='the subscriber is register_node (its sources.received)')
    parser.add_argument('--topic', default='source_cloud')
    parser.add_argument('--domain', default=DOMAIN_ID, help='ROS_DOMAIN_ID of the runs')
    parser.add_argument('--discovery', choices=('LOCALHOST', 'SUBNET'), default='LOCALHOST',
                        help='ROS_AUTOMATIC_DISCOVERY_RANGE on one host (--netns: SUBNET)')
    parser.add_argument('--netns', nargs=2, metavar=('PUB', 'SUB'),
                        help='network namespaces of the publisher and the subscriber')
    parser.add_argument('--output', type=Path, default=output_path('transport.json'),
                        help='one row a run (default: %(default)s)')
    args = parser.parse_args(argv)
    if args.role == 'sub':
        return run_sub(args.topic)
    if args.role == 'pub':
        return run_pub(args.topic, args.clouds[0], args.rate[0], args.count, args.node)
    os.environ['ROS_DOMAIN_ID'] = args.domain
    for s in args.settings:
        if any(part not in SETTINGS for part in s.split('/')):
            parser.error(f'unknown setting {s!r} (one of {", ".join(SETTINGS)}, or PUB/SUB)')
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for clouds in args.clouds:
            for rate in args.rate:
                for setting in args.settings:
                    row = measure(clouds, rate, args.count, setting, args.node, Path(tmp),
                                  args.netns, args.discovery)
                    print(json.dumps(row), flush=True)
                    rows.append(row)
    write_json(args.output, rows)
    return 0


if __name__ == '__main__':
    sys.exit(main())
