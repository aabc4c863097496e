"""Helpers of the tests: waiting for conditions, ROS contexts, node processes, scenes."""

import contextlib
import os
import threading
import time
import traceback

from bench.common import stop_process  # noqa: F401 - the tests' name for it
import pytest

EXECUTOR_THREADS = 4  # of spun_context's executor, as many as the node's own main spins


def wait_for(predicate, timeout, what, detail=None):
    """
    Poll until ``predicate()`` is truthy and return its value.

    Fail after ``timeout`` seconds instead of hanging, with ``detail()`` (e.g. the node's
    counters and last rejection reason) in the message.
    """
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.02)
    pytest.fail(f'timed out after {timeout} s waiting for {what}'
                + (f'; node state: {detail()}' if detail else ''))


class CloudWire:
    """
    A test's side of /register_node: clouds out (reliable sources, latched targets).

    Records the node's ~/pose and the values and level of its last /diagnostics.
    """

    def __init__(self, context, name, depth):
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseStamped
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import PointCloud2

        reliable = QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE)
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.node = rclpy.create_node(name, context=context)
        self.source_pub = self.node.create_publisher(PointCloud2, 'source_cloud', reliable)
        self.target_pub = self.node.create_publisher(PointCloud2, 'target_cloud', latched)
        self.poses = []
        self.values = {}
        self.level = None
        self.node.create_subscription(PoseStamped, '/register_node/pose', self.poses.append,
                                      reliable)
        self.node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, 10)

    def _on_diag(self, msg):
        for status in msg.status:
            if status.hardware_id == '/register_node':
                self.values = {kv.key: kv.value for kv in status.values}
                self.level = status.level

    def pose_at(self, stamp_ns):
        return pose_at(self.poses, stamp_ns)


def bad_map(folder, case):
    """
    Write a map file that cannot be used into ``folder``; return its path.

    ``case``: 'missing' (no file), 'empty', 'unreadable' (a broken PLY header) or 'all_nan'.
    """
    import numpy as np

    path = folder / {'missing': 'nothere.ply', 'empty': 'empty.xyz',
                     'unreadable': 'broken.ply', 'all_nan': 'nan.npy'}[case]
    if case == 'empty':
        path.write_text('')
    elif case == 'unreadable':
        path.write_bytes(b'ply\nformat binary_little_endian 1.0\ngarbage\n')
    elif case == 'all_nan':
        np.save(path, np.full((100, 3), np.nan))
    return path


class InProcessRunner:
    """A ``cgags_ros.runtime.jobs.Runner`` that registers in this process (a ``ChildSession``)."""

    def __init__(self):
        from cgags_ros.runtime.process import ChildSession

        self.session, self.jobs = ChildSession(), []  # every job run, in order

    def run(self, job, timeout_s=None):
        self.jobs.append(job)
        return self.session.run(job)

    def supervise(self):
        return False

    def health(self, prefix='registration'):
        return {}

    def close(self):
        pass


class FakeRunner(InProcessRunner):
    """
    A stand-in for the registration process, for tests of the runtime's plumbing.

    A ``cgags_ros.runtime.jobs.Runner``: a pair's job is answered with ``register(source,
    target, config=...)``; a map loads as in the real process (a ``ChildSession`` of this
    one). It stands in for pairs only: a node or engine given one runs with
    ``tracking.enabled`` false.
    """

    def __init__(self, register):
        super().__init__()
        self.register = register

    def run(self, job, timeout_s=None):
        from cgags_ros.runtime.jobs import PairDone, PrepareMap, RegisterPair

        if isinstance(job, PrepareMap):
            return super().run(job)
        assert isinstance(job, RegisterPair), f'the stand-in registers pairs only: {job!r}'
        self.jobs.append(job)
        return PairDone(self.register(job.source, job.target, config=job.config))


def call(client, request, timeout, detail=None):
    """Call a service and return its answer; fail after ``timeout`` seconds."""
    assert client.wait_for_service(timeout_sec=30.0), client.srv_name
    future = client.call_async(request)
    wait_for(future.done, timeout, f'the answer of {client.srv_name}', detail)
    return future.result()


class Lifecycle:
    """/register_node's lifecycle services, called as nav2_lifecycle_manager calls them."""

    # configure answers once the registration process is warm (a cold numba cache is
    # compiled first) and the map is loaded
    CONFIGURE_S = 600.0

    def __init__(self, node):
        from lifecycle_msgs.srv import ChangeState, GetState

        self._change = node.create_client(ChangeState, '/register_node/change_state')
        self._get = node.create_client(GetState, '/register_node/get_state')

    def state(self):
        """Return the node's state label ('unconfigured', 'inactive', 'active', ...)."""
        from lifecycle_msgs.srv import GetState

        return call(self._get, GetState.Request(), 60.0).current_state.label

    def change(self, transition_id):
        """Request a transition (lifecycle_msgs/Transition id); return (success, state then)."""
        from lifecycle_msgs.srv import ChangeState

        request = ChangeState.Request()
        request.transition.id = transition_id
        return call(self._change, request, self.CONFIGURE_S).success, self.state()


def pose_at(poses, stamp_ns):
    """Return the first message of ``poses`` stamped ``stamp_ns``, or None."""
    return next((p for p in list(poses)
                 if p.header.stamp.sec * 10**9 + p.header.stamp.nanosec == stamp_ns), None)


def lidar_bag(data_dir):
    """Return the LiDAR bag: (records (topic, stamp, rclpy cloud) in log order, GT by stamp)."""
    from cgags_ros.io.bag import read_messages
    from cgags_ros.io.pointcloud2 import pose_to_transform
    from cgags_ros.ros.outputs import to_rclpy_pointcloud2

    records, gt = [], {}
    for rec in read_messages(data_dir / 'bags' / 'lidar'):
        if rec.topic == '/ground_truth':
            gt[rec.stamp_ns] = pose_to_transform(rec.msg)
        else:
            records.append((rec.topic, rec.stamp_ns, to_rclpy_pointcloud2(rec.msg)))
    return records, gt


def ros_values(**flat):
    """
    Return the node's ROS parameter values for configuration keys (their one names).

    Keys that are no ROS parameter go to a YAML file named by ``config_file``. Give dotted
    keys as ``**{'pairing.mode': 'synchronized'}``.
    """
    from pathlib import Path
    import tempfile

    from cgags_ros.config.node import ros_parameter_descriptions, ros_value
    import yaml

    names = ros_parameter_descriptions()
    ros = {k: ros_value(v) for k, v in flat.items() if k in names}
    rest = {k: ros_value(v) for k, v in flat.items() if k not in names}
    if rest:
        path = Path(tempfile.mkdtemp(prefix='cgags_test_')) / 'config_file.yaml'
        path.write_text(yaml.safe_dump(rest), encoding='utf-8')
        ros['config_file'] = str(path)
    return ros


def ros_overrides(**flat):
    """Return rclpy parameter overrides for flat configuration keys (see :func:`ros_values`)."""
    from rclpy.parameter import Parameter

    return [Parameter(k, value=v) for k, v in ros_values(**flat).items()]


def ros_args(**flat):
    """Return ``-p name:=value`` arguments for flat configuration keys."""
    return [a for k, v in ros_values(**flat).items() for a in ('-p', f'{k}:={v}')]


@contextlib.contextmanager
def spun_context(domain_id, make_io):
    """
    Yield (context, executor, io): an rclpy context on ``domain_id`` spun on a thread.

    A multi-threaded executor, as the node's own ``main`` spins: the clouds of a test's node
    are decoded while the diagnostics and services run.

    ``io = make_io(context)`` is the test's own node wrapper (publishers, recorders); its
    ``node`` is added to the executor. Everything is shut down on exit.
    """
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import MultiThreadedExecutor

    # rcl reads the discovery range when the context starts; every DDS test of this suite
    # stays on this machine, so setting it process-wide is what each module wants anyway.
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    context = Context()
    rclpy.init(context=context, domain_id=domain_id)
    io = make_io(context)
    executor = MultiThreadedExecutor(num_threads=EXECUTOR_THREADS, context=context)
    executor.add_node(io.node)

    done = threading.Event()

    def spin():
        # executor.spin() ends at the first exception a callback raised, and every later
        # test of the module would then wait on a recorder nobody spins. A callback caught
        # by a node's destruction (its handles gone mid-call) is such an exception: report
        # it and spin on, so that it fails no test but its own.
        while not done.is_set() and context.ok():
            try:
                executor.spin_once(timeout_sec=0.1)
            except Exception:  # noqa: B902 - reported, and the other nodes spin on
                if not done.is_set():
                    traceback.print_exc()

    thread = threading.Thread(target=spin, daemon=True)
    thread.start()
    try:
        yield context, executor, io
    finally:
        done.set()
        thread.join(timeout=5.0)
        executor.shutdown(timeout_sec=2.0)
        io.node.destroy_node()
        context.try_shutdown()


def box_room(rng, n, size=(6.0, 4.0, 2.5)):
    """Return ``n`` points on the inside walls, floor and ceiling of a box room at the origin."""
    import numpy as np

    half = np.array(size) / 2
    pts = rng.uniform(-half, half, size=(n, 3))
    axis = rng.integers(0, 3, size=n)
    side = rng.choice([-1.0, 1.0], size=n)
    pts[np.arange(n), axis] = side * half[axis]
    return pts


def merged_kitchen_map(data_dir, folder):
    """
    Write the redkitchen fragments 0 and 4 merged with their ground truth to ``folder``.

    :returns: (map path, merged points, (fragment 6, its GT to 0), (fragment 4, its GT)).
    """
    import numpy as np

    from bench.datasets.gt_pairs import find_pair
    from cgags_ros.geometry import apply_transform
    from cgags_ros.io.clouds import read_cloud

    base = data_dir / 'indoor_3dmatch'
    f4, f0, T40 = find_pair(base / 'gt_pairs.txt', 'cloud_bin_4.ply', 'cloud_bin_0.ply')
    frag4 = read_cloud(f4)
    merged = np.vstack([read_cloud(f0), apply_transform(T40, frag4)])
    path = folder / 'kitchen.npy'
    np.save(path, merged)
    demo = base / 'geotransformer_demo'
    return path, merged, (np.load(demo / 'src.npy'), np.load(demo / 'gt.npy')), (frag4, T40)
