"""
The player of live replay: a replay client of register_node, not part of the node.

An rclpy context that publishes a bag's clouds into a register_node and records its poses
and /diagnostics; the functions at the end read the node's /diagnostics back (the string
values a DiagnosticStatus carries) under the key names :mod:`cgags_ros.ros.diagnostics`
defines.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any, Mapping

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped
import numpy as np
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2

from ..io.pointcloud2 import pose_to_transform, stamp_to_ns
from ..localizer.transport import use_large_data_profile
from ..ros.diagnostics import DROPPED, LAST, LAST_TIMING, PAIRING, REJECTED

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
    """An rclpy context with the player node: publishers, pose and diagnostics recorders."""

    def __init__(self, source_topic: str, target_topic: str, node_name: str, n_sources: int):
        use_large_data_profile()  # the clouds' publisher needs it as much as the node
        self.context = Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node('cgags_replay_player', context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        depth = max(1, min(n_sources, MAX_QUEUE))
        self.source_pub = self.node.create_publisher(
            PointCloud2, source_topic,
            QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE))
        self.target_pub = self.node.create_publisher(
            PointCloud2, target_topic,
            QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self.poses: dict[int, Received] = {}
        self.details: dict[int, dict[str, str]] = {}
        self.stats: dict[str, str] = {}
        self.last_progress = time.monotonic()
        self.node_id = '/' + node_name.lstrip('/')
        # ~/pose_with_covariance: the pose of ~/pose and its covariance, one message.
        self.pose_sub = self.node.create_subscription(
            PoseWithCovarianceStamped, f'{self.node_id}/pose_with_covariance', self._on_pose,
            100)
        self.node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diagnostics, 100)

    def _on_pose(self, msg: Any) -> None:
        stamp = stamp_to_ns(msg.header.stamp)
        cov = np.array(msg.pose.covariance, dtype=np.float64).reshape(6, 6)
        self.poses[stamp] = Received(pose_to_transform(msg), msg.header.frame_id,
                                     time.monotonic(), cov)
        self.last_progress = time.monotonic()

    def _on_diagnostics(self, msg: Any) -> None:
        for status in msg.status:
            if status.hardware_id != self.node_id:
                continue
            values = {kv.key: kv.value for kv in status.values}
            if values != self.stats:
                self.last_progress = time.monotonic()
            self.stats = values
            stamp = last_source_stamp_ns(values)
            if stamp is not None:
                self.details[stamp] = values

    def spin_for(self, seconds: float) -> None:
        """Spin the player's executor for ``seconds`` (at least once)."""
        end = time.monotonic() + max(seconds, 0.0)
        while True:
            left = end - time.monotonic()
            self.executor.spin_once(timeout_sec=max(min(left, 0.02), 0.0))
            if left <= 0:
                return

    def connected(self) -> bool:
        """Tell whether the node subscribes to both clouds and publishes its pose."""
        return (self.source_pub.get_subscription_count() > 0
                and self.target_pub.get_subscription_count() > 0
                and self.pose_sub.get_publisher_count() > 0)

    def accounted_sources(self) -> int | None:
        """
        Count the sources the node is done with, from its last diagnostics.

        That is published + rejected + dropped + waiting; None before any diagnostics.
        """
        return accounted_sources(self.stats) if self.stats else None

    def received_sources(self) -> int:
        return as_int(self.stats.get('received_source', '0'))

    def close(self) -> None:
        """Shut the player's executor, node and context down."""
        self.executor.shutdown()
        self.node.destroy_node()
        self.context.try_shutdown()


def accounted_sources(values: Mapping[str, str]) -> int:
    """Count the sources the node is done with: published + rejected + dropped + waiting."""
    return (sum(as_int(values.get(f'sources.{k}')) for k in ('published', 'rejected', 'dropped'))
            + as_int(values.get(f'{PAIRING}waiting_sources')))


def last_result(values: Mapping[str, str]) -> dict[str, Any]:
    """Return the last registration's fields (valid, reason, inliers, fitness, time_s)."""
    return {'valid': values.get(f'{LAST}valid', 'True') == 'True',
            'reason': values.get(f'{LAST}reason', ''),
            'inliers': as_int(values[f'{LAST}inliers']) if f'{LAST}inliers' in values else None,
            'fitness': as_float(values.get(f'{LAST}fitness')),
            'time_s': as_float(values.get(f'{LAST_TIMING}total'))}


def last_source_stamp_ns(values: Mapping[str, str]) -> int | None:
    """Return the source stamp of the last registration, or None before the first."""
    stamp = values.get(f'{LAST}source_stamp_ns')
    return int(stamp) if stamp else None


def nonzero_drops(values: Mapping[str, str]) -> list[str]:
    """Return 'key: value' for every rejection and pairing drop the node counted."""
    keys = [k for k in values if k.startswith((REJECTED, DROPPED))]
    return [f'{k}: {values[k]}' for k in sorted(keys) if as_int(values[k])]


def as_int(value: Any) -> int:
    """Read a counter published as text (0 when it is not a number)."""
    try:
        return int(float(value))
    except (TypeError, ValueError):
        return 0


def as_float(value: Any) -> float | None:
    """Read a number published as text (None when it is not one)."""
    try:
        return float(value)
    except (TypeError, ValueError):
        return None
