"""
Guarded ``initialpose`` for Nav2/AMCL: the robot base's pose, only when every guard passes.

Quality guards (:func:`quality_refusal`): a valid, unambiguous estimate with at least
``initial_pose_min_inliers`` inliers, a best/runner-up candidate ratio of at least
``initial_pose_min_ratio`` and a fitness of at least ``initial_pose_min_fitness``. Then
``initial_pose_cooldown`` seconds since the last publish and, for scans registered in
continuous mode, at most ``initial_pose_max_auto`` publishes. Every publish and every
refusal is counted, refusals by reason (``initial_pose.refused.<reason>``).

The pose is the base's: ``T_map_base = T_map_sensor inv(T_base_sensor)`` with the
extrinsic from ``base_from_sensor``, or from TF (``base_frame`` <- the scan's frame) when
tf2_ros is importable; without either the sensor is taken as the base (said once). Its
covariance is the sensor pose's moved along the lever arm
(:func:`~cgags_ros.pipeline.covariance.moved_covariance`). With ``broadcast_map_to_odom``
and tf2_ros, each published pose also broadcasts Nav2's map -> odom from it and the
odom -> base transform at the scan's stamp.
"""

from __future__ import annotations

import collections
import threading
import time
from typing import Any

from geometry_msgs.msg import PoseWithCovarianceStamped
import numpy as np
from std_msgs.msg import Header

from .conversions import transform_to_pose, transform_to_transform_stamped
from ..config.node import NodeConfig, parse_pose7
from ..geometry import make_transform, quaternion_to_matrix
from ..pipeline.covariance import map_to_odom, moved_covariance


def extrinsic(cfg: NodeConfig) -> np.ndarray | None:
    """Return ``T_base_sensor`` of ``base_from_sensor`` (4x4, metres), None when unset."""
    values = parse_pose7(cfg.base_from_sensor)
    if values is None:
        return None
    return make_transform(quaternion_to_matrix(values[3:]), values[:3])


def quality_refusal(result: Any, cfg: NodeConfig) -> tuple[str, str]:
    """Return (reason key, message) why ``result`` is no confident pose, or ('', '')."""
    if result.ambiguous:
        return 'ambiguous', str(result.reason)
    if not result.valid:
        return 'invalid', str(result.reason)
    if result.num_inliers < cfg.initial_pose_min_inliers:
        return 'few_inliers', (f'{result.num_inliers} inliers < initial_pose_min_inliers '
                               f'{cfg.initial_pose_min_inliers}')
    ratio = float(result.runner_up_ratio)
    if ratio < cfg.initial_pose_min_ratio:
        return 'low_ratio', (f'best/runner-up ratio {ratio:.2f} < initial_pose_min_ratio '
                             f'{cfg.initial_pose_min_ratio:g}')
    fitness = float(result.fitness)
    if fitness < cfg.initial_pose_min_fitness:
        return 'low_fitness', (f'fitness {fitness:.3f} < initial_pose_min_fitness '
                               f'{cfg.initial_pose_min_fitness:g}')
    return '', ''


class InitialPose:
    """The ``initialpose`` publisher, its guards and counters."""

    def __init__(self, node: Any):
        self._node = node
        self._pub = node.create_publisher(PoseWithCovarianceStamped, 'initialpose', 10)
        self._lock = threading.Lock()
        self.counts: collections.Counter[str] = collections.Counter()
        self._last_publish: float | None = None
        self._tf_buffer: Any = None
        self._tf_broadcaster: Any = None
        self._tf_said = False

    def offer(self, result: Any, T: np.ndarray, cov: np.ndarray, stamp: Any, sensor_frame: str,
              cfg: NodeConfig, automatic: bool) -> tuple[bool, str]:
        """
        Publish the base pose of ``T`` (map <- sensor) if every guard passes.

        :returns: (published, why not or what was published).
        """
        key, why = quality_refusal(result, cfg)
        now = time.monotonic()
        with self._lock:
            if not key and self._last_publish is not None \
                    and now - self._last_publish < cfg.initial_pose_cooldown:
                key, why = 'cooldown', (f'{now - self._last_publish:.1f} s since the last '
                                        f'publish < initial_pose_cooldown '
                                        f'{cfg.initial_pose_cooldown:g} s')
            if not key and automatic and self.counts['auto'] >= cfg.initial_pose_max_auto:
                key, why = 'max_auto', (f'{self.counts["auto"]} automatic publishes = '
                                        f'initial_pose_max_auto {cfg.initial_pose_max_auto}')
        base = None if key else self._base_from_sensor(cfg, sensor_frame)
        if not key and base is None:
            key, why = 'no_extrinsic', (f'no TF {cfg.base_frame} <- {sensor_frame} (set '
                                        'base_from_sensor)')
        with self._lock:
            if key:
                self.counts[f'refused.{key}'] += 1
                return False, why
            self.counts['published'] += 1
            self.counts['auto'] += automatic
            self._last_publish = now
        sensor_base = np.linalg.inv(base)
        T_map_base = T @ sensor_base
        msg = PoseWithCovarianceStamped(header=Header(stamp=stamp, frame_id=cfg.map_frame))
        msg.pose.pose = transform_to_pose(T_map_base)
        cov_base = moved_covariance(cov, T, sensor_base)
        msg.pose.covariance = [float(v) for v in cov_base.ravel()]
        self._node._send(self._pub, msg)
        if cfg.broadcast_map_to_odom:
            self._broadcast_map_to_odom(T_map_base, msg.header, cfg)
        return True, f'initial pose published in {cfg.map_frame}'

    def _broadcast_map_to_odom(self, T_map_base: np.ndarray, header: Header,
                               cfg: NodeConfig) -> None:
        if not self._tf_ready():
            return
        T_odom_base = self._lookup(cfg.odom_frame, cfg.base_frame, header.stamp)
        if T_odom_base is None:
            with self._lock:
                self.counts['map_to_odom.no_odom_tf'] += 1
            return
        if self._tf_broadcaster is None:
            from tf2_ros import TransformBroadcaster

            self._tf_broadcaster = TransformBroadcaster(self._node)
        self._tf_broadcaster.sendTransform(transform_to_transform_stamped(
            map_to_odom(T_map_base, T_odom_base), header, cfg.odom_frame))
        with self._lock:
            self.counts['map_to_odom.broadcast'] += 1

    def _tf_ready(self) -> bool:
        """Start the TF listener once; False (said once) when tf2_ros is not importable."""
        if self._tf_buffer is not None:
            return True
        try:
            from tf2_ros import Buffer, TransformListener
        except ImportError:
            if not self._tf_said:
                self._tf_said = True
                self._node.get_logger().warning(
                    'tf2_ros is not importable: no TF lookup of the extrinsic and no '
                    'map -> odom broadcast (the sensor pose stands for the base pose unless '
                    'base_from_sensor is set)')
            return False
        self._tf_buffer = Buffer()
        self._tf_listener = TransformListener(self._tf_buffer, self._node)
        return True

    def _lookup(self, parent: str, child: str, stamp: Any = None) -> np.ndarray | None:
        from rclpy.time import Time

        try:
            tf = self._tf_buffer.lookup_transform(
                parent, child, Time.from_msg(stamp) if stamp is not None else Time())
        except Exception:  # noqa: BLE001 - tf2's lookup errors have no common base here
            return None
        r, t = tf.transform.rotation, tf.transform.translation
        return make_transform(quaternion_to_matrix((r.x, r.y, r.z, r.w)), (t.x, t.y, t.z))

    def _base_from_sensor(self, cfg: NodeConfig, sensor_frame: str) -> np.ndarray | None:
        T = extrinsic(cfg)
        if T is not None:
            return T
        if not self._tf_ready():
            return np.eye(4)
        return self._lookup(cfg.base_frame, sensor_frame)

    def statistics(self) -> dict[str, int]:
        """Return ``initial_pose.*`` counters for /diagnostics."""
        with self._lock:
            return {f'initial_pose.{k}': v for k, v in sorted(self.counts.items())}
