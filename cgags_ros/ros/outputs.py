"""
The node's pose outputs: ~/pose, ~/pose_with_covariance, ~/aligned_cloud and /tf.

Frames and conventions as in :mod:`.node`: ``T`` maps source-frame points into the target
(map) frame; outputs carry the source's stamp and the target's (or ``pose_frame_id``'s)
frame.
"""

from __future__ import annotations

from typing import Any

from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
import numpy as np
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header

from .conversions import transform_to_pose, transform_to_transform_stamped, xyz_to_pointcloud2
from ..config.node import NodeConfig
from ..config.pipeline import PipelineConfig
from ..geometry import apply_transform
from ..pipeline.pairing import Pair


class Outputs:
    """Publishers of one node's estimate (and its TF broadcaster, when tf2_ros imports)."""

    def __init__(self, node: Any):
        self._node = node
        self._pose_pub = node.create_publisher(PoseStamped, '~/pose', 10)
        self._pose_cov_pub = node.create_publisher(PoseWithCovarianceStamped,
                                                   '~/pose_with_covariance', 10)
        self._aligned_pub = node.create_publisher(PointCloud2, '~/aligned_cloud', 1)
        self._tf_broadcaster: Any = None
        self._tf_missing_logged = False

    def _send(self, publisher: Any, msg: Any) -> None:
        self._node._send(publisher, msg)

    def publish(self, pair: Pair, T: np.ndarray, result: Any, pipe_cfg: PipelineConfig,
                cfg: NodeConfig, frame: str) -> np.ndarray:
        """Publish the pose, its covariance, the aligned cloud and TF; return the covariance."""
        source = pair.source.payload
        header = Header(stamp=source.header.stamp, frame_id=frame)
        pose = transform_to_pose(T)
        self._send(self._pose_pub, PoseStamped(header=header, pose=pose))
        cov_msg = PoseWithCovarianceStamped(header=header)
        cov_msg.pose.pose = pose
        cov = np.asarray(result.covariance, dtype=np.float64)
        cov_msg.pose.covariance = [float(v) for v in cov.ravel()]
        self._send(self._pose_cov_pub, cov_msg)
        if cfg.publish_aligned_cloud:
            aligned = apply_transform(T, source.xyz)
            self._send(self._aligned_pub, xyz_to_pointcloud2(aligned, header))
        if cfg.broadcast_tf:
            self._broadcast(T, header, cfg.tf_child_frame or source.header.frame_id)
        return cov

    def _broadcast(self, T: np.ndarray, header: Header, child: str) -> None:
        if self._tf_broadcaster is None:
            try:
                from tf2_ros import TransformBroadcaster
            except ImportError:
                if not self._tf_missing_logged:
                    self._tf_missing_logged = True
                    self._node.get_logger().warning(
                        'broadcast_tf is set but tf2_ros is not importable; no TF is broadcast')
                return
            self._tf_broadcaster = TransformBroadcaster(self._node)
        self._tf_broadcaster.sendTransform(transform_to_transform_stamped(T, header, child))
