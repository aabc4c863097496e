"""
colcon build of cgags_ros in a scratch workspace, then the installed node over DDS.

The package is copied into ``ws/src/cgags_ros`` and built with the colcon of this
interpreter's environment. The test then checks the install layout, resolves the executable
the way ``ros2 run`` does (ament index), applies the environment that colcon's generated setup
scripts would (from its ``.dsv`` hook files, so no shell has to be sourced), and runs that
executable on one real pair of the lidar bag, comparing ``/register_node/pose`` with the
bag's ``/ground_truth``.
"""

import json
import os
from pathlib import Path
import re
import shutil
import signal
import subprocess
import sys
import time

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
import numpy as np
import pytest
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message
from rclpy.signals import SignalHandlerOptions
from rosbags.highlevel import AnyReader
from rosbags.typesys import get_typestore, Stores
from sensor_msgs.msg import PointCloud2

pytestmark = [pytest.mark.ros, pytest.mark.subprocess, pytest.mark.slow]
REPO = Path(__file__).resolve().parents[1]
PACKAGE = 'cgags_ros'
# What a source checkout of the package must ship for colcon; never .venv, build outputs, .git.
PACKAGE_FILES = ['package.xml', 'setup.py', 'setup.cfg', 'LICENSE', 'README.md']
PACKAGE_DIRS = ['resource', PACKAGE, 'config', 'launch', 'rviz']
# The benchmarks' data readers live in bench/datasets/, which is not installed.
BENCH_DATA = ('threedmatch.py', 'rigs.py', 'gt_pairs.py', 'synthetic.py')
COLCON = Path(sys.executable).parent / 'colcon'
# Distinct from test_register_node.py (47), test_replay.py (83) and bench/ (58).
DOMAIN_ID = 61
LIDAR_VOXEL = 0.4
MAX_RE_DEG, MAX_TE_M = 5.0, 0.6
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
RELIABLE = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE)
# Lines Python's -v import tracing writes to stderr; hidden when showing the node's errors.
VERBOSE_PREFIXES = ('#', 'import ', 'Processing ', 'Adding directory', 'Python 3', 'Type "help"')


def tail(text, limit=6000):
    return text if len(text) <= limit else '...\n' + text[-limit:]


def copy_package(dest: Path):
    ignore = shutil.ignore_patterns('__pycache__', '*.pyc', '*.egg-info')
    dest.mkdir(parents=True)
    for name in PACKAGE_FILES:
        shutil.copy2(REPO / name, dest / name)
    for name in PACKAGE_DIRS:
        shutil.copytree(REPO / name, dest / name, ignore=ignore)


def colcon_build(ws: Path):
    # A private COLCON_HOME: a developer's ~/.colcon defaults (symlink-install, mixins)
    # would otherwise change what gets installed. A sourced ROS underlay stays in effect.
    env = dict(os.environ, COLCON_HOME=str(ws / 'colcon_home'))
    try:
        proc = subprocess.run([str(COLCON), 'build', '--packages-select', PACKAGE],
                              cwd=ws, env=env, capture_output=True, text=True, timeout=300)
    except subprocess.TimeoutExpired as exc:
        pytest.fail(f'colcon build timed out after {exc.timeout} s:\n'
                    f'{tail(exc.stdout or "")}\n{build_log(ws)}')
    assert proc.returncode == 0, (
        f'colcon build failed ({proc.returncode}):\n{tail(proc.stdout)}\n{tail(proc.stderr)}\n'
        f'{build_log(ws)}')


def build_log(ws: Path):
    # Per-package logs need colcon-output; colcon-core always writes logger_all.log.
    for log in (ws / 'log' / 'latest_build' / PACKAGE / 'stdout_stderr.log',
                ws / 'log' / 'latest_build' / 'logger_all.log'):
        if log.is_file():
            return f'--- {log}:\n{tail(log.read_text())}'
    return f'(no colcon log under {ws / "log"})'


def apply_dsv(prefix: Path, dsv: Path, env: dict):
    """
    Apply a colcon ``.dsv`` hook file to ``env`` as colcon's setup scripts do.

    Values are relative to the install prefix (empty: the prefix itself). ``source`` lines
    list each hook once per shell; only the shell-independent ``.dsv`` variant is followed.
    """
    for line in dsv.read_text().splitlines():
        if not line.strip():
            continue
        kind, _, rest = line.partition(';')
        if kind == 'source':
            if rest.endswith('.dsv'):
                apply_dsv(prefix, prefix / rest, env)
            continue
        name, _, raw = rest.partition(';')
        values = [str(prefix / v) if v else str(prefix) for v in raw.split(';')]
        if kind.endswith('-if-exists'):
            values = [v for v in values if os.path.exists(v)]
            kind = kind[:-len('-if-exists')]
        parts = [p for p in env.get(name, '').split(os.pathsep) if p]
        if kind == 'prepend-non-duplicate':
            parts = [v for v in values if v not in parts] + parts
        elif kind == 'append-non-duplicate':
            parts += [v for v in values if v not in parts]
        elif kind == 'set':
            parts = values
        elif kind == 'set-if-unset':
            parts = parts or values
        else:
            raise AssertionError(f'{dsv}: unknown colcon dsv type {kind!r} in {line!r}')
        env[name] = os.pathsep.join(parts)


def installed_environment(prefix: Path):
    """Return the environment a shell gets by sourcing this install over the current one."""
    env = dict(os.environ)
    env.pop('ROS_LOCALHOST_ONLY', None)  # deprecated; conflicts with the discovery range
    apply_dsv(prefix, prefix / 'share' / PACKAGE / 'package.dsv', env)
    env.update(ROS_DOMAIN_ID=str(DOMAIN_ID), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
               PYTHONUNBUFFERED='1')
    return env


# Run in the installed environment: what `ros2 run` and the console script look up.
PROBE = """
import json
from importlib.metadata import distribution
from ament_index_python.packages import get_package_prefix
print(json.dumps({'prefix': get_package_prefix('cgags_ros'),
                  'dist': str(distribution('cgags_ros').locate_file(''))}))
"""


def read_lidar_pair(data_dir: Path):
    """Read the first target and source (rclpy messages) and the source's T_gt."""
    store = get_typestore(Stores.ROS2_JAZZY)
    clouds, gt = {'/source_cloud': [], '/target_cloud': []}, {}
    with AnyReader([data_dir / 'bags' / 'lidar'], default_typestore=store) as reader:
        for conn, _, raw in reader.messages():
            if conn.topic in clouds:
                # The bag holds ROS 2 CDR: rclpy reads it as is, no field-by-field copy.
                clouds[conn.topic].append(deserialize_message(bytes(raw), PointCloud2))
            elif conn.topic == '/ground_truth':
                msg = reader.deserialize(raw, conn.msgtype)
                p, q = msg.pose.position, msg.pose.orientation
                gt[stamp_ns(msg.header.stamp)] = pose_matrix([p.x, p.y, p.z],
                                                             [q.x, q.y, q.z, q.w])
    source, target = clouds['/source_cloud'][0], clouds['/target_cloud'][0]
    return source, target, gt[stamp_ns(source.header.stamp)]


def stamp_ns(stamp):
    return stamp.sec * 10**9 + stamp.nanosec


def pose_matrix(position, quaternion_xyzw):
    x, y, z, w = np.asarray(quaternion_xyzw, dtype=float) / np.linalg.norm(quaternion_xyzw)
    T = np.eye(4)
    T[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                 [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                 [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    T[:3, 3] = position
    return T


def rotation_error_deg(R, R_gt):
    cos = (np.trace(R_gt.T @ R) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


class Wire:
    """The test's side of DDS, in its own context and domain, spun from the test thread."""

    def __init__(self):
        self.context = Context()
        rclpy.init(context=self.context, domain_id=DOMAIN_ID,
                   signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node('colcon_build_test_io', context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.target_pub = self.node.create_publisher(PointCloud2, 'target_cloud', LATCHED)
        self.source_pub = self.node.create_publisher(PointCloud2, 'source_cloud', RELIABLE)
        self.poses = []
        self.diag = {}
        self.pose_sub = self.node.create_subscription(
            PoseStamped, '/register_node/pose', self.poses.append, 10)
        self.node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, 10)

    def _on_diag(self, msg):
        for status in msg.status:
            self.diag[status.hardware_id] = {kv.key: kv.value for kv in status.values}

    def spin_until(self, predicate, timeout, what, detail=lambda: ''):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            value = predicate()
            if value:
                return value
            self.executor.spin_once(timeout_sec=0.05)
        pytest.fail(f'timed out after {timeout} s waiting for {what}; {detail()}')

    def close(self):
        self.executor.shutdown(timeout_sec=2.0)
        self.node.destroy_node()
        self.context.try_shutdown()


def stop(proc, timeout=20.0):
    """SIGINT (Ctrl-C of `ros2 run`), then SIGKILL; reap the whole session either way."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    try:  # the node's registration process, should it have outlived the node
        os.killpg(proc.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass


def node_output(stdout_file, stderr_file):
    stdout_file.seek(0)
    stderr_file.seek(0)
    out, err = stdout_file.read(), stderr_file.read()
    errors = '\n'.join(line for line in err.splitlines()
                       if not line.startswith(VERBOSE_PREFIXES))
    return out, err, f'node stdout:\n{tail(out)}\nnode stderr (without import trace):\n' \
                     f'{tail(errors)}'


def run_node_on_pair(exe: Path, env: dict, tmp_path: Path, source, target):
    """Run ``exe``, publish one pair to it and return its pose; always stop the node."""
    # -v traces every import (stderr), so the node's own process shows which copy it ran;
    # the node's log goes to stdout to keep it apart.
    node_env = dict(env, PYTHONVERBOSE='1', RCUTILS_LOGGING_USE_STDOUT='1')
    argv = [str(exe), '--ros-args', '-p', f'voxel_size:={LIDAR_VOXEL}',
            # Deterministic delivery across processes: with the defaults (best-effort
            # sources, volatile target) a 1 MB cloud can be lost on a loaded machine or
            # when sent right at discovery.
            '-p', 'pairing.source_qos:=reliable',
            '-p', 'pairing.target_durability:=transient_local',
            '-p', 'output.diagnostics_period:=0.2']
    source_stamp = stamp_ns(source.header.stamp)
    # Files, not pipes: a full pipe would block the node.
    with open(tmp_path / 'node.out', 'w+') as out_file, \
            open(tmp_path / 'node.err', 'w+') as err_file:
        proc = subprocess.Popen(argv, cwd=tmp_path, env=node_env, stdout=out_file,
                                stderr=err_file, text=True, start_new_session=True)
        wire = None
        try:
            wire = Wire()

            def state():
                return (f'node exit code {proc.poll()}, diagnostics '
                        f'{wire.diag.get("/register_node")}\n'
                        f'{node_output(out_file, err_file)[2]}')

            wire.spin_until(lambda: proc.poll() is not None or (
                wire.source_pub.get_subscription_count() and
                wire.target_pub.get_subscription_count() and
                wire.pose_sub.get_publisher_count()), 60, 'discovery of the node', state)
            # A writer can see the match before the node's reader does; a sample sent in
            # between is lost even when reliable, so also wait until the node reports itself.
            wire.spin_until(lambda: proc.poll() is not None or '/register_node' in wire.diag,
                            30, "the node's first diagnostics", state)
            assert proc.poll() is None, f'node exited early\n{state()}'

            wire.target_pub.publish(target)
            wire.source_pub.publish(source)
            pose = wire.spin_until(
                lambda: proc.poll() is not None or next(
                    (p for p in wire.poses if stamp_ns(p.header.stamp) == source_stamp), None),
                90, 'the pose of the lidar source', state)
            assert isinstance(pose, PoseStamped), f'node exited\n{state()}'
        finally:
            if wire is not None:
                wire.close()
            stop(proc)
        _, err, shown = node_output(out_file, err_file)
    return pose, proc.returncode, err, shown


def test_colcon_build_installs_a_runnable_node(tmp_path, data_dir, monkeypatch):
    if not COLCON.is_file():
        pytest.skip(f'colcon is not installed in this environment ({COLCON} missing; '
                    'pip install -r requirements-dev.txt)')
    ws = tmp_path / 'ws'
    copy_package(ws / 'src' / PACKAGE)
    colcon_build(ws)

    prefix = ws / 'install' / PACKAGE  # colcon's default isolated install layout
    listing = '\n'.join(sorted(str(p.relative_to(ws)) for p in (ws / 'install').rglob('*')
                               if '__pycache__' not in p.parts))
    exe = prefix / 'lib' / PACKAGE / 'register_node'
    assert exe.is_file() and os.access(exe, os.X_OK), listing
    for rel in [f'share/{PACKAGE}/package.xml', f'share/{PACKAGE}/config/register_node.yaml',
                f'share/{PACKAGE}/config/fastdds_large_data.xml',
                f'share/{PACKAGE}/launch/register_node.launch.py',
                f'share/{PACKAGE}/rviz/cgags.rviz',
                f'share/ament_index/resource_index/packages/{PACKAGE}']:
        assert (prefix / rel).is_file(), f'{rel} not installed:\n{listing}'

    env = installed_environment(prefix)
    site = [Path(p) for p in env['PYTHONPATH'].split(os.pathsep)
            if Path(p).is_relative_to(prefix) and (Path(p) / PACKAGE / '__init__.py').is_file()]
    assert site, f'PYTHONPATH from the hooks has no {PACKAGE} of {prefix}: {env["PYTHONPATH"]}'
    # Every module of the source tree is installed (a subpackage that find_packages misses,
    # e.g. one without __init__.py, would be absent).
    sources = {p.relative_to(ws / 'src' / PACKAGE) for p in
               (ws / 'src' / PACKAGE / PACKAGE).rglob('*.py')}
    installed = {p.relative_to(site[0]) for p in (site[0] / PACKAGE).rglob('*.py')}
    assert sources == installed, (f'not installed: {sorted(map(str, sources - installed))}, '
                                  f'not in the source: {sorted(map(str, installed - sources))}')
    shipped = sorted(str(p) for p in installed if p.name in BENCH_DATA)
    assert not shipped, f'data readers of the benchmarks installed: {shipped}'
    probe = subprocess.run([sys.executable, '-c', PROBE], env=env, cwd=tmp_path,
                           capture_output=True, text=True, timeout=60)
    assert probe.returncode == 0, probe.stderr
    found = json.loads(probe.stdout.strip().splitlines()[-1])
    assert Path(found['prefix']) == prefix, found
    assert Path(found['dist']).is_relative_to(prefix), found  # not the repo's editable install
    # ros2 run: <get_package_prefix(pkg)>/lib/<pkg>/<executable>
    resolved = Path(found['prefix']) / 'lib' / PACKAGE / 'register_node'
    assert resolved == exe

    source, target, T_gt = read_lidar_pair(data_dir)
    # The test's participant (rclpy.init reads this) stays on this host like the node.
    monkeypatch.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    monkeypatch.delenv('ROS_LOCALHOST_ONLY', raising=False)

    pose, returncode, err, shown = run_node_on_pair(resolved, env, tmp_path, source, target)
    assert pose.header.frame_id == target.header.frame_id
    p, q = pose.pose.position, pose.pose.orientation
    T = pose_matrix([p.x, p.y, p.z], [q.x, q.y, q.z, q.w])
    rot = rotation_error_deg(T[:3, :3], T_gt[:3, :3])
    te = float(np.linalg.norm(T[:3, 3] - T_gt[:3, 3]))
    assert rot <= MAX_RE_DEG and te <= MAX_TE_M, f'lidar: RE {rot:.2f} deg, TE {te:.3f} m'

    assert returncode == 0, f'exit code {returncode} after SIGINT\n{shown}'
    assert 'Traceback' not in err, shown
    # Every cgags_ros module the node (and its registration process) loaded came from the
    # install, none from the source tree or the venv's editable install of it.
    # Found anywhere in a line: the node and its registration process write to one stderr,
    # and one's trace can land inside a line of the other's.
    loaded = sorted({path.strip() for path in re.findall(r"# code object from '?([^'#\n]+)", err)
                     if f'/{PACKAGE}/' in path})
    assert loaded, f'no {PACKAGE} module in the import trace\n{shown}'
    outside = [path for path in loaded if not Path(path).is_relative_to(prefix)]
    assert not outside, f'modules loaded from outside {prefix}: {outside}'
