"""
The guards of the ``initialpose`` for Nav2/AMCL: the robot base's pose, only when all pass.

ROS-free. Quality guards (:func:`cgags_ros.validity.quality_refusal`, decided once per
pair by the engine): a valid, unambiguous estimate with at least
``relocalization.min_inliers`` inliers, a best/runner-up candidate ratio of at least
``relocalization.min_ratio`` and a fitness of at least ``relocalization.min_fitness``. Then
``relocalization.cooldown`` seconds since the last publish and, for scans registered without
a relocalization request, at most ``relocalization.max_auto`` publishes. Every publish and
every refusal is counted, refusals by code (``initial_pose.refused.<code>``).

The pose is the base's: ``T_map_base = T_map_sensor inv(T_base_sensor)`` with the
extrinsic from ``relocalization.base_from_sensor``, or else from the node's TF lookup
(``relocalization.base_frame`` <- the scan's frame). Its covariance is the sensor pose's
moved along the lever arm (:func:`~cgags_ros.pipeline.covariance.moved_covariance`).
"""

from __future__ import annotations

import collections
import time
from typing import Callable

import numpy as np

from ..config.node import NodeConfig
from ..geometry import make_transform, quaternion_to_matrix
from ..pipeline.covariance import moved_covariance
from ..refusal import Refusal, RefusalCode

# (base frame, sensor frame) -> T_base_sensor (4x4, metres), or None when unknown
ExtrinsicLookup = Callable[[str, str], 'np.ndarray | None']


def extrinsic(cfg: NodeConfig) -> np.ndarray | None:
    """Return ``T_base_sensor`` of ``relocalization.base_from_sensor`` (4x4, metres) or None."""
    values = cfg.relocalization.sensor_pose
    if values is None:
        return None
    return make_transform(quaternion_to_matrix(values[3:]), values[:3])


class InitialPoseGuard:
    """
    Decides whether an estimate becomes an initial pose; counts publishes and refusals.

    The engine thread alone offers estimates; :meth:`statistics` may be read from any thread: the
    counts are replaced whole, never changed in place, so no lock is needed.
    """

    def __init__(self) -> None:
        self.counts: collections.Counter[str] = collections.Counter()
        self._last_publish: float | None = None

    def offer(self, refusal: Refusal | None, T: np.ndarray, cov: np.ndarray, sensor_frame: str,
              cfg: NodeConfig, automatic: bool, lookup: ExtrinsicLookup
              ) -> tuple[str, np.ndarray | None, np.ndarray | None]:
        """
        Return the base pose of ``T`` (map <- sensor) if every guard passes.

        :param refusal: the quality guards' verdict on the estimate (None: it passed).
        :param cov: the 6x6 covariance of ``T`` (ROS order).
        :param automatic: the scan was registered without a relocalization request.
        :param lookup: the node's TF lookup of the extrinsic, for an unset
            ``relocalization.base_from_sensor``.
        :returns: (what was published or why not: the refusal as ``code: message``,
            ``T_map_base`` or None, its covariance or None); a publish is counted as done.
        """
        now = time.monotonic()
        if not refusal and self._last_publish is not None \
                and now - self._last_publish < cfg.relocalization.cooldown:
            refusal = Refusal(RefusalCode.COOLDOWN, (
                f'{now - self._last_publish:.1f} s since the last publish < '
                f'relocalization.cooldown {cfg.relocalization.cooldown:g} s'))
        if not refusal and automatic and self.counts['auto'] >= cfg.relocalization.max_auto:
            refusal = Refusal(RefusalCode.MAX_AUTO, (
                f'{self.counts["auto"]} automatic publishes = relocalization.max_auto '
                f'{cfg.relocalization.max_auto}'))
        base = None
        if not refusal:
            base = extrinsic(cfg)
            base = lookup(cfg.relocalization.base_frame, sensor_frame) if base is None else base
        if not refusal and base is None:
            refusal = Refusal(RefusalCode.NO_EXTRINSIC, (
                f'no TF {cfg.relocalization.base_frame} <- {sensor_frame} (set '
                'relocalization.base_from_sensor)'))
        counts = self.counts.copy()
        if refusal:
            counts[f'refused.{refusal.code.value}'] += 1
            self.counts = counts
            return str(refusal), None, None
        counts['published'] += 1
        counts['auto'] += automatic
        self.counts, self._last_publish = counts, now
        sensor_base = np.linalg.inv(base)
        return (f'initial pose published in {cfg.map.frame}', T @ sensor_base,
                moved_covariance(cov, T, sensor_base))

    def may_publish_auto(self, cfg: NodeConfig) -> bool:
        """Tell whether an automatic publish (no relocalization request) is still allowed."""
        return self.counts['auto'] < cfg.relocalization.max_auto

    def statistics(self) -> dict[str, int]:
        """Return ``initial_pose.*`` counters for /diagnostics."""
        return {f'initial_pose.{k}': v for k, v in sorted(self.counts.items())}
