"""
The guards of the ``initialpose`` for Nav2/AMCL: the robot base's pose, only when all pass.

ROS-free. Quality guards (:func:`quality_refusal`): a valid, unambiguous estimate with at
least ``initial_pose_min_inliers`` inliers, a best/runner-up candidate ratio of at least
``initial_pose_min_ratio`` and a fitness of at least ``initial_pose_min_fitness``. Then
``initial_pose_cooldown`` seconds since the last publish and, for scans registered without
a relocalization request, at most ``initial_pose_max_auto`` publishes. Every publish and
every refusal is counted, refusals by reason (``initial_pose.refused.<reason>``).

The pose is the base's: ``T_map_base = T_map_sensor inv(T_base_sensor)`` with the
extrinsic from ``base_from_sensor``, or else from the node's TF lookup (``base_frame`` <-
the scan's frame). Its covariance is the sensor pose's moved along the lever arm
(:func:`~cgags_ros.pipeline.covariance.moved_covariance`).
"""

from __future__ import annotations

import collections
import threading
import time
from typing import Callable

import numpy as np

from ..config.node import NodeConfig, parse_pose7
from ..geometry import make_transform, quaternion_to_matrix
from ..pipeline.covariance import moved_covariance
from ..pipeline.result import PipelineResult

# (base frame, sensor frame) -> T_base_sensor (4x4, metres), or None when unknown
ExtrinsicLookup = Callable[[str, str], 'np.ndarray | None']


def extrinsic(cfg: NodeConfig) -> np.ndarray | None:
    """Return ``T_base_sensor`` of ``base_from_sensor`` (4x4, metres), None when unset."""
    values = parse_pose7(cfg.base_from_sensor)
    if values is None:
        return None
    return make_transform(quaternion_to_matrix(values[3:]), values[:3])


def quality_refusal(result: PipelineResult, cfg: NodeConfig) -> tuple[str, str]:
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


class InitialPoseGuard:
    """Decides whether an estimate becomes an initial pose; counts publishes and refusals."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.counts: collections.Counter[str] = collections.Counter()
        self._last_publish: float | None = None

    def offer(self, result: PipelineResult, T: np.ndarray, cov: np.ndarray, sensor_frame: str,
              cfg: NodeConfig, automatic: bool, lookup: ExtrinsicLookup
              ) -> tuple[str, np.ndarray | None, np.ndarray | None]:
        """
        Return the base pose of ``T`` (map <- sensor) if every guard passes.

        :param cov: the 6x6 covariance of ``T`` (ROS order).
        :param automatic: the scan was registered without a relocalization request.
        :param lookup: the node's TF lookup of the extrinsic, for an unset
            ``base_from_sensor``.
        :returns: (what was published or why not, ``T_map_base`` or None, its covariance
            or None); a publish is counted as done.
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
        base = None
        if not key:
            base = extrinsic(cfg)
            base = lookup(cfg.base_frame, sensor_frame) if base is None else base
        if not key and base is None:
            key, why = 'no_extrinsic', (f'no TF {cfg.base_frame} <- {sensor_frame} (set '
                                        'base_from_sensor)')
        with self._lock:
            if key:
                self.counts[f'refused.{key}'] += 1
                return why, None, None
            self.counts['published'] += 1
            self.counts['auto'] += automatic
            self._last_publish = now
        sensor_base = np.linalg.inv(base)
        return (f'initial pose published in {cfg.map_frame}', T @ sensor_base,
                moved_covariance(cov, T, sensor_base))

    def statistics(self) -> dict[str, int]:
        """Return ``initial_pose.*`` counters for /diagnostics."""
        with self._lock:
            return {f'initial_pose.{k}': v for k, v in sorted(self.counts.items())}
