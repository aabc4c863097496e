"""
register_node as a managed node over real DDS: transitions through lifecycle_msgs services.

The node starts unconfigured (``autostart: false``), as under a lifecycle manager, and the
test drives it with ``change_state``/``get_state`` like nav2_lifecycle_manager does. The
real pipeline runs in its registration process on the LiDAR bag; poses are checked against
the bag's ground truth. Its own services are listed for the node and answered.
"""

from __future__ import annotations

from pathlib import Path

from cgags_ros.config.pipeline import load_yaml
from cgags_ros.geometry import rotation_error_deg, translation_error
from cgags_ros.io.pointcloud2 import pose_to_transform
from cgags_ros.runtime.procfs import running
import pytest

rclpy = pytest.importorskip('rclpy')

from cgags_ros.ros.node import RegisterNode  # noqa: E402, I100
from lifecycle_msgs.msg import Transition  # noqa: E402
from rcl_interfaces.srv import ListParameters  # noqa: E402
from std_srvs.srv import Empty, Trigger  # noqa: E402
from waiting import (call, CloudWire, lidar_bag, Lifecycle, ros_overrides,  # noqa: E402
                     spun_context, wait_for)

pytestmark = pytest.mark.ros
DOMAIN_ID = 91  # distinct from the other DDS test modules
REPO = Path(__file__).resolve().parents[1]
PARAMS = {'autostart': False, 'voxel_size': 0.4, 'pairing.source_qos': 'reliable',
          'pairing.source_depth': 50, 'pairing.target_durability': 'transient_local',
          'pairing.queue_depth': 10,
          'output.diagnostics_period': 0.1, 'runtime.registration_timeout': 120.0,
          # the guards of a relocalization answer, loose enough for a 6-scan bag
          'relocalization.min_ratio': 1.0, 'relocalization.min_fitness': 0.0}


class Wire(CloudWire):
    """The test's side: clouds out, lifecycle and service clients, poses and diagnostics in."""

    def __init__(self, context):
        super().__init__(context, 'lifecycle_io', 50)
        self.lifecycle = Lifecycle(self.node)
        self.relocalize = self.node.create_client(Trigger, '/register_node/relocalize')
        self.reinit = self.node.create_client(Empty, '/reinitialize_global_localization')

    def call(self, client, request, timeout=60.0):
        return call(client, request, timeout, lambda: self.values)

    def transition(self, transition_id):
        success, state = self.lifecycle.change(transition_id)
        assert success, transition_id
        return state


@pytest.fixture(scope='module')
def wire():
    with spun_context(DOMAIN_ID, Wire) as spun:
        yield spun


def check(pose, gt, stamp):
    T = pose_to_transform(pose)
    re, te = rotation_error_deg(T, gt[stamp]), translation_error(T, gt[stamp])
    assert re < 5.0 and te < 0.6, f'RE {re:.2f} deg, TE {te:.3f} m'


@pytest.fixture(scope='module')
def scans(data_dir):
    """Return the LiDAR bag: (target cloud, [(stamp, source cloud)], GT by source stamp)."""
    records, gt = lidar_bag(data_dir)
    target = next(m for t, _, m in records if t == '/target_cloud')
    return target, [(s, m) for t, s, m in records if t == '/source_cloud'], gt


def test_both_services_are_the_nodes_own_and_answer(wire, scans):
    """~/relocalize and reinitialize_global_localization: listed for the node, answered."""
    context, executor, io = wire
    target, sources, gt = scans
    io.poses.clear()
    io.values = {}
    node = RegisterNode(context=context,
                        parameter_overrides=ros_overrides(**dict(PARAMS, autostart=True)))
    executor.add_node(node)
    try:
        services = dict(io.node.get_service_names_and_types_by_node('register_node', '/'))
        wait_for(lambda: services.update(io.node.get_service_names_and_types_by_node(
            'register_node', '/')) or ('/reinitialize_global_localization' in services
                                       and '/register_node/relocalize' in services),
                 60, 'the services in the graph', lambda: sorted(services))
        assert services['/register_node/relocalize'] == ['std_srvs/srv/Trigger']
        assert services['/reinitialize_global_localization'] == ['std_srvs/srv/Empty']
        assert services['/register_node/change_state'] == ['lifecycle_msgs/srv/ChangeState']
        assert 'register_node_relocalize' not in io.node.get_node_names()  # no hidden node
        wait_for(lambda: io.source_pub.get_subscription_count()
                 and io.target_pub.get_subscription_count(), 30, 'discovery')
        io.target_pub.publish(target)

        # Nav2's call: answered at once, the next registration relocalizes
        io.call(io.reinit, Empty.Request(), timeout=30.0)
        stamp, msg = sources[1]
        io.source_pub.publish(msg)
        check(wait_for(lambda: io.pose_at(stamp), 120, 'the pose', lambda: io.values), gt,
              stamp)
        wait_for(lambda: io.values.get('relocalize.succeeded') == '1', 30,
                 'the reinitialize request answered', lambda: io.values)
        assert io.values['relocalize.calls'] == '1'

        # ~/relocalize waits for the next registration and answers its summary
        future = io.relocalize.call_async(Trigger.Request())
        wait_for(lambda: io.values.get('relocalize.calls') == '2', 30, 'the call queued')
        stamp, msg = sources[2]
        io.source_pub.publish(msg)
        wait_for(future.done, 120, 'the ~/relocalize answer', lambda: io.values)
        answer = future.result()
        assert answer.success and answer.message.startswith('localized:'), answer.message
        check(io.pose_at(stamp), gt, stamp)
    finally:
        executor.remove_node(node)
        node.destroy_node()


def test_transitions_through_lifecycle_services(wire, scans):
    """
    Drive configure, activate, deactivate, activate, deactivate, cleanup over DDS.

    Inactive: sources are counted (rejected.inactive), no pose is published.
    Active: poses match ground truth. After cleanup the registration process is gone.
    """
    context, executor, io = wire
    target, sources, gt = scans
    io.poses.clear()
    io.values = {}
    node = RegisterNode(context=context,
                        parameter_overrides=ros_overrides(**PARAMS))
    executor.add_node(node)
    try:
        assert io.lifecycle.state() == 'unconfigured'
        assert node.engine is None
        assert io.transition(Transition.TRANSITION_CONFIGURE) == 'inactive'
        pid = node.engine.runner.pid
        assert pid and running(pid)
        assert node.engine.runner.ready  # configure waited for its warm-up
        wait_for(lambda: io.source_pub.get_subscription_count()
                 and io.target_pub.get_subscription_count(), 30, 'discovery')
        io.target_pub.publish(target)
        stamp, msg = sources[0]
        io.source_pub.publish(msg)
        values = wait_for(lambda: io.values.get('sources.received') == '1' and io.values, 30,
                          'the inactive source counted')
        assert values['rejected.inactive'] == '1' and values['active'] == 'False'
        assert values['targets.pending'] == '1' and values['accounting.ok'] == 'True'
        assert io.pose_at(stamp) is None

        for step, k in (('first activation', 1), ('re-activation', 3)):
            assert io.transition(Transition.TRANSITION_ACTIVATE) == 'active'
            stamp, msg = sources[k]
            io.source_pub.publish(msg)
            check(wait_for(lambda: io.pose_at(stamp), 120, f'the pose after {step}',
                           lambda: io.values), gt, stamp)
            assert io.transition(Transition.TRANSITION_DEACTIVATE) == 'inactive'
            stamp, msg = sources[k + 1]
            io.source_pub.publish(msg)
            wait_for(lambda: io.values.get('sources.received') == str(k + 2), 30,
                     'the source while inactive counted')
            assert io.pose_at(stamp) is None
        values = wait_for(lambda: io.values.get('rejected.inactive') == '3'
                          and io.values, 10, 'three inactive sources')
        assert values['sources.published'] == '2' and values['accounting.ok'] == 'True'
        assert len(io.poses) == 2

        assert io.transition(Transition.TRANSITION_CLEANUP) == 'unconfigured'
        assert node.engine is None
        wait_for(lambda: not running(pid), 10, 'the registration process to end')
    finally:
        executor.remove_node(node)
        node.destroy_node()


def test_at_most_26_parameters_and_each_is_in_the_generated_yaml(wire):
    """The node's parameters, listed over DDS: a short list, all in config/register_node.yaml."""
    context, executor, io = wire
    node = RegisterNode(context=context, parameter_overrides=ros_overrides(autostart=False))
    executor.add_node(node)
    try:
        client = io.node.create_client(ListParameters, '/register_node/list_parameters')
        names = set(io.call(client, ListParameters.Request()).result.names)
        # rclpy's own: the clock source and the type-description service switch
        ours = names - {'use_sim_time', 'start_type_description_service'}
        assert 10 <= len(ours) <= 26, sorted(ours)
        shipped = load_yaml(REPO / 'config' / 'register_node.yaml')
        assert ours == set(shipped)
        assert list(shipped)[0] == 'voxel_size'
    finally:
        executor.remove_node(node)
        node.destroy_node()
