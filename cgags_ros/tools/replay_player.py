"""
The player of live replay: a client of register_node over DDS, not part of the node.

An rclpy context that publishes a bag's clouds into a register_node and records what the
node answers: its poses (``~/pose_with_covariance``) and, for every source it is done with,
its result (``~/result``, the JSON of :class:`~cgags_ros.engine.interface.PairResult`).
It also reads and sets the node's parameters through its parameter services, as
rqt_reconfigure and ``ros2 param`` do (``cgags-tune --live``).
"""

from __future__ import annotations

import dataclasses
import json
import time
from typing import Any

from geometry_msgs.msg import PoseWithCovarianceStamped
import numpy as np
from rcl_interfaces.srv import GetParameters, SetParameters
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter, parameter_value_to_python
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import String

from ..engine.transport import use_large_data_profile
from ..io.pointcloud2 import pose_to_transform, stamp_to_ns

MAX_QUEUE = 1000  # the node config's upper bound for depths


@dataclasses.dataclass
class Received:
    """
    A pose from the node: 4x4 source->target, its frame, when it arrived (s).

    ``covariance`` is the node's 6x6 pose covariance (ROS order, metres and radians).
    """

    transform: np.ndarray
    frame_id: str
    receipt_s: float
    covariance: np.ndarray | None = None


class LiveSession:
    """An rclpy context with the player node: cloud publishers, pose and result recorders."""

    def __init__(self, source_topic: str, target_topic: str, node_name: str, n_sources: int):
        use_large_data_profile()  # the clouds' publisher needs it as much as the node
        self.context = Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node('cgags_replay_player', context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        depth = max(1, min(n_sources, MAX_QUEUE))
        reliable = QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE)
        self.source_pub = self.node.create_publisher(PointCloud2, source_topic, reliable)
        self.target_pub = self.node.create_publisher(
            PointCloud2, target_topic,
            QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self.poses: dict[int, Received] = {}
        self.results: list[dict[str, Any]] = []  # ~/result, in arrival order
        self.last_progress = time.monotonic()
        self.node_id = '/' + node_name.lstrip('/')
        # ~/pose_with_covariance: the pose of ~/pose and its covariance, one message.
        self.pose_sub = self.node.create_subscription(
            PoseWithCovarianceStamped, f'{self.node_id}/pose_with_covariance', self._on_pose,
            100)
        self.result_sub = self.node.create_subscription(
            String, f'{self.node_id}/result', self._on_result, reliable)
        self._clients: dict[str, Any] = {}  # the node's parameter services, once used

    def _on_pose(self, msg: Any) -> None:
        stamp = stamp_to_ns(msg.header.stamp)
        cov = np.array(msg.pose.covariance, dtype=np.float64).reshape(6, 6)
        self.poses[stamp] = Received(pose_to_transform(msg), msg.header.frame_id,
                                     time.monotonic(), cov)
        self.last_progress = time.monotonic()

    def _on_result(self, msg: Any) -> None:
        self.results.append(json.loads(msg.data))
        self.last_progress = time.monotonic()

    def results_by_stamp(self) -> dict[int, dict[str, Any]]:
        """Return the results of sources with a stamp, by it (the last one of a stamp)."""
        return {r['source_stamp_ns']: r for r in self.results if r['source_stamp_ns']}

    def spin_for(self, seconds: float) -> None:
        """Spin the player's executor for ``seconds`` (at least once)."""
        end = time.monotonic() + max(seconds, 0.0)
        while True:
            left = end - time.monotonic()
            self.executor.spin_once(timeout_sec=max(min(left, 0.02), 0.0))
            if left <= 0:
                return

    def connected(self) -> bool:
        """Tell whether the node subscribes to both clouds and publishes its pose and results."""
        return (self.source_pub.get_subscription_count() > 0
                and self.target_pub.get_subscription_count() > 0
                and self.pose_sub.get_publisher_count() > 0
                and self.result_sub.get_publisher_count() > 0)

    def get_parameters(self, names: list[str], timeout_s: float) -> dict[str, Any]:
        """
        Return the node's values of ``names`` (through its ``get_parameters`` service).

        :raises TimeoutError: the service did not answer within ``timeout_s``.
        """
        request = GetParameters.Request(names=list(names))
        response = self._call(GetParameters, 'get_parameters', request, timeout_s)
        return {name: parameter_value_to_python(value)
                for name, value in zip(names, response.values)}

    def set_parameters(self, values: dict[str, Any], timeout_s: float) -> list[str]:
        """
        Set the node's parameters (its ``set_parameters`` service); return why any was refused.

        Each parameter is set on its own, as rqt_reconfigure does: the list holds the reason
        of each one the node refused (out of range, read-only, a wrong type), empty when all
        were set.

        :raises TimeoutError: the service did not answer within ``timeout_s``.
        """
        request = SetParameters.Request(
            parameters=[Parameter(k, value=v).to_parameter_msg() for k, v in values.items()])
        response = self._call(SetParameters, 'set_parameters', request, timeout_s)
        return [f'{name}: {result.reason or "refused"}'
                for name, result in zip(values, response.results) if not result.successful]

    def _call(self, kind: Any, service: str, request: Any, timeout_s: float) -> Any:
        client = self._clients.get(service)
        if client is None:
            client = self._clients[service] = self.node.create_client(
                kind, f'{self.node_id}/{service}')
        end = time.monotonic() + timeout_s
        while not client.service_is_ready():
            if time.monotonic() > end:
                raise TimeoutError(f'no {self.node_id}/{service} service within '
                                   f'{timeout_s:g} s')
            self.spin_for(0.05)
        future = client.call_async(request)
        while not future.done():
            if time.monotonic() > end:
                raise TimeoutError(f'{self.node_id}/{service} did not answer within '
                                   f'{timeout_s:g} s')
            self.spin_for(0.02)
        return future.result()

    def close(self) -> None:
        """Shut the player's executor, node and context down."""
        self.executor.shutdown()
        self.node.destroy_node()
        self.context.try_shutdown()
