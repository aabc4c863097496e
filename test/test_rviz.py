"""
rviz/cgags.rviz shows the node's real outputs, and the launch file's ``rviz:=true`` starts it.

The topics and message types the view must show are taken from the code, not restated:
the node's outputs from :class:`cgags_ros.ros.outputs.Outputs` (built on a recording stand-in
for the node), its name and input topics from the launch file. ``launch`` and ``launch_ros``
are not installed in this environment, so the launch file is run against recording
stand-ins of their classes: what it builds (arguments, nodes, conditions, remappings) is
checked, not how ``ros2 launch`` executes it. test_colcon_build checks that setup.py
installs the config where the launch file looks for it.
"""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path
import sys
import types

from cgags_ros.config.node import NODE_NAME, NodeConfig
import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
RVIZ_CONFIG = REPO / 'rviz' / 'cgags.rviz'
LAUNCH_FILE = REPO / 'launch' / 'register_node.launch.py'
SHARE = '/opt/share/cgags_ros'  # what the stand-in ament index answers
# Message type -> the rviz_default_plugins display of it.
DISPLAYS = {
    'sensor_msgs/msg/PointCloud2': 'rviz_default_plugins/PointCloud2',
    'geometry_msgs/msg/PoseStamped': 'rviz_default_plugins/Pose',
    'geometry_msgs/msg/PoseWithCovarianceStamped': 'rviz_default_plugins/PoseWithCovariance',
    'geometry_msgs/msg/PoseArray': 'rviz_default_plugins/PoseArray',
}


# --- the launch file, run against stand-ins of launch / launch_ros ----------------------


class Recorded:
    """A stand-in launch class: keeps its arguments; equal when type and arguments are."""

    def __init__(self, *args, **kwargs):
        self.args, self.kwargs = args, kwargs

    def __eq__(self, other):
        return (type(self).__name__ == type(other).__name__ and self.args == other.args
                and self.kwargs == other.kwargs)

    def __hash__(self):
        return hash(type(self).__name__)

    def __repr__(self):
        return f'{type(self).__name__}{self.args}{self.kwargs}'


def stand_in(name: str) -> types.ModuleType:
    """Return a module whose every attribute is a :class:`Recorded` subclass of that name."""
    module = types.ModuleType(name)
    classes: dict[str, type] = {}

    def getattr_(attr):
        if attr.startswith('__'):
            raise AttributeError(attr)
        return classes.setdefault(attr, type(attr, (Recorded,), {}))

    module.__getattr__ = getattr_
    return module


@pytest.fixture
def launch_description(monkeypatch):
    """Return the launch module and the actions its description holds (stand-ins)."""
    for name in ('launch', 'launch.actions', 'launch.conditions', 'launch.substitutions',
                 'launch_ros', 'launch_ros.actions', 'launch_ros.parameter_descriptions'):
        monkeypatch.setitem(sys.modules, name, stand_in(name))
    index = types.ModuleType('ament_index_python.packages')
    index.get_package_share_directory = lambda package: {'cgags_ros': SHARE}[package]
    monkeypatch.setitem(sys.modules, 'ament_index_python.packages', index)
    spec = importlib.util.spec_from_file_location('register_node_launch', LAUNCH_FILE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    description = module.generate_launch_description()
    assert type(description).__name__ == 'LaunchDescription'
    return module, description.args[0]


def of_type(actions, name):
    return [a for a in actions if type(a).__name__ == name]


def config(name):
    return sys.modules['launch.substitutions'].LaunchConfiguration(name)


def arguments(actions):
    return {a.args[0]: a.kwargs for a in of_type(actions, 'DeclareLaunchArgument')}


def nodes(actions, package):
    return [a.kwargs for a in of_type(actions, 'Node') if a.kwargs['package'] == package]


def test_launch_declares_rviz_off_by_default(launch_description):
    _, actions = launch_description
    declared = arguments(actions)
    assert declared['rviz']['default_value'] == 'false'
    assert declared['rviz_fixed_frame']['default_value'] == NodeConfig().map.frame


def test_rviz_true_starts_rviz2_with_the_installed_config(launch_description):
    _, actions = launch_description
    [viewer] = nodes(actions, 'rviz2')
    assert viewer['executable'] == 'rviz2'
    assert viewer['condition'] == sys.modules['launch.conditions'].IfCondition(config('rviz'))
    argv = viewer['arguments']
    installed = argv[argv.index('-d') + 1]
    # setup.py installs rviz/*.rviz into share/cgags_ros/rviz (test_colcon_build checks it).
    assert installed == os.path.join(SHARE, 'rviz', RVIZ_CONFIG.name) and RVIZ_CONFIG.is_file()
    assert argv[argv.index('-f') + 1] == config('rviz_fixed_frame')
    assert viewer['namespace'] == config('namespace')


def test_exactly_one_register_node_runs_and_rviz_gets_the_aligned_cloud(launch_description):
    _, actions = launch_description
    conditions = sys.modules['launch.conditions']
    by_condition = {type(n['condition']).__name__: n for n in nodes(actions, 'cgags_ros')}
    assert set(by_condition) == {'IfCondition', 'UnlessCondition'}
    for node in by_condition.values():
        assert node['condition'] in (conditions.IfCondition(config('rviz')),
                                     conditions.UnlessCondition(config('rviz')))
        assert node['name'] == NODE_NAME and node['executable'] == 'register_node'
    with_rviz, without = by_condition['IfCondition'], by_condition['UnlessCondition']
    assert with_rviz['parameters'][-1]['output.publish_aligned_cloud'] is True
    assert 'output.publish_aligned_cloud' not in without['parameters'][-1]
    # Otherwise the two are the same node.
    strip = {'condition', 'parameters'}
    assert ({k: v for k, v in with_rviz.items() if k not in strip}
            == {k: v for k, v in without.items() if k not in strip})
    assert with_rviz['parameters'][:-1] == without['parameters'][:-1]


# --- the node's real topics ---------------------------------------------------------------


class RecordingNode:
    """Stands in for the node while :class:`Outputs` creates its publishers."""

    def __init__(self):
        self.publishers: dict[str, tuple[type, object]] = {}

    def create_publisher(self, msg_type, topic, qos):
        self.publishers[topic] = (msg_type, qos)
        return object()

    create_lifecycle_publisher = create_publisher


def type_name(msg_type) -> str:
    module = msg_type.__module__.split('.')  # e.g. geometry_msgs.msg._pose_stamped
    return f'{module[0]}/msg/{msg_type.__name__}'


def reliable(qos) -> bool:
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    profile = QoSProfile(depth=qos) if isinstance(qos, int) else qos
    return profile.reliability == ReliabilityPolicy.RELIABLE


@pytest.fixture(scope='module')
def node_outputs():
    """Return ``{fully qualified topic: (message type name, reliable)}`` of the node."""
    pytest.importorskip('rclpy')
    from cgags_ros.ros.outputs import Outputs

    node = RecordingNode()
    Outputs(node)
    out = {}
    for topic, (msg_type, qos) in node.publishers.items():
        name = f'/{NODE_NAME}/{topic[2:]}' if topic.startswith('~/') else (
            topic if topic.startswith('/') else f'/{topic}')
        out[name] = (type_name(msg_type), reliable(qos))
    return out


@pytest.fixture(scope='module')
def rviz():
    """Return the parsed rviz/cgags.rviz."""
    return yaml.safe_load(RVIZ_CONFIG.read_text())


def displays(rviz):
    return rviz['Visualization Manager']['Displays']


def topic_displays(rviz):
    return {d['Topic']['Value']: d for d in displays(rviz) if isinstance(d.get('Topic'), dict)}


def input_topics(launch_description):
    """Return ``{role: absolute topic}`` of source and target in the default namespace."""
    _, actions = launch_description
    declared = arguments(actions)
    return {role: '/' + declared[f'{role}_topic']['default_value'].lstrip('/')
            for role in ('source', 'target')}


def test_fixed_frame_is_the_map_frame(rviz):
    # The pose and candidates are in the target cloud's frame; `map` unless the launch's
    # rviz_fixed_frame says otherwise.
    assert rviz['Visualization Manager']['Global Options']['Fixed Frame'] == \
        NodeConfig().map.frame


def test_rviz_shows_target_aligned_source_pose_candidates_and_tf(rviz, node_outputs,
                                                                 launch_description):
    shown = topic_displays(rviz)
    by_type = {}
    for topic, (msg_type, _) in node_outputs.items():
        by_type.setdefault(msg_type, []).append(topic)
    expected = {
        input_topics(launch_description)['target']: 'rviz_default_plugins/PointCloud2',
        f'/{NODE_NAME}/aligned_cloud': 'rviz_default_plugins/PointCloud2',
        f'/{NODE_NAME}/pose': 'rviz_default_plugins/Pose',
        f'/{NODE_NAME}/candidates': 'rviz_default_plugins/PoseArray',
    }
    for topic, display in expected.items():
        assert topic in shown, f'no display of {topic}: {sorted(shown)}'
        assert shown[topic]['Class'] == display and shown[topic]['Enabled'], shown[topic]
    assert f'/{NODE_NAME}/aligned_cloud' in by_type['sensor_msgs/msg/PointCloud2']
    assert any(d['Class'] == 'rviz_default_plugins/TF' and d['Enabled'] for d in displays(rviz))


def test_every_topic_of_the_view_is_a_real_topic_of_its_type(rviz, node_outputs,
                                                             launch_description):
    inputs = {topic: ('sensor_msgs/msg/PointCloud2', role)
              for role, topic in input_topics(launch_description).items()}
    for topic, display in topic_displays(rviz).items():
        if topic in inputs:
            msg_type = inputs[topic][0]
            # The node takes the target reliably (so its publisher is reliable); sources
            # are sensor data, often best effort, which a reliable reader never matches.
            publisher_reliable = inputs[topic][1] == 'target'
        else:
            assert topic in node_outputs, f'{display["Name"]}: {topic} is no topic of the node'
            msg_type, publisher_reliable = node_outputs[topic]
        assert display['Class'] == DISPLAYS[msg_type], (topic, msg_type)
        if display['Topic']['Reliability Policy'] == 'Reliable':
            assert publisher_reliable, f'{topic}: a reliable reader never matches its writer'
        assert display['Topic']['Durability Policy'] == 'Volatile', topic  # matches any writer


def test_rviz_follows_the_launch_namespace_and_topics(rviz, launch_description):
    module, actions = launch_description
    [viewer] = nodes(actions, 'rviz2')
    remapped = dict(viewer['remappings'])
    inputs = input_topics(launch_description)
    for topic in topic_displays(rviz):
        assert topic.startswith('/'), topic
        if topic in inputs.values():
            role = next(r for r, t in inputs.items() if t == topic)
            assert remapped[topic] == config(f'{role}_topic'), topic
        else:
            # Relative replacement: resolved in RViz's namespace, the node's.
            assert remapped[topic] == topic.lstrip('/'), topic
    assert set(module.RVIZ_NODE_TOPICS) == {
        t.rsplit('/', 1)[1] for t in topic_displays(rviz) if t.startswith(f'/{NODE_NAME}/')}
