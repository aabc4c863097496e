"""
Relocalization in a prior map: the node's map, candidates, initial pose and on-demand mode.

:class:`Localization` holds what the node adds for a map: the map of ``map_file`` (loaded
in the registration process, features cached on disk), ``~/candidates``
(geometry_msgs/PoseArray: the ranked candidate poses of the scan's frame, best first, in the
map frame), the guarded ``initialpose`` (:mod:`.initial_pose`) and, in ``mode: on_demand``,
the ``~/relocalize`` service (:mod:`.relocalize`). The node calls it from its worker
thread: :meth:`load_map` first, :meth:`ready` before taking a pair, :meth:`stale` and
:meth:`finish` around each registration, :meth:`settle` after it.
"""

from __future__ import annotations

import math
import os
import threading
from typing import Any

from geometry_msgs.msg import PoseArray
import numpy as np
from std_msgs.msg import Header

from .conversions import transform_to_pose
from .initial_pose import InitialPose, quality_refusal
from .relocalize import Relocalizer
from .worker import IsolatedRegistration, MapRef, prepare_map
from ..config.node import NodeConfig
from ..config.pipeline import PipelineConfig
from ..errors import CgagsError
from ..geometry import matrix_to_quaternion
from ..pipeline.pairing import Pair


class Localization:
    """The map, candidates, initial pose and ~/relocalize of one node (see the module doc)."""

    def __init__(self, node: Any, cfg: NodeConfig):
        self._node = node
        self.on_demand = cfg.mode == 'on_demand'
        self.map_ref = (MapRef(os.path.expanduser(cfg.map_file),
                               os.path.expanduser(cfg.map_cache_dir)) if cfg.map_file else None)
        self.map_info: dict[str, Any] = {}
        self.map_error = ''
        self._lock = threading.Lock()
        self._candidates: list[Any] = []
        self._last_summary = ''
        self._answered = True
        self._candidates_pub = node.create_publisher(PoseArray, '~/candidates', 10)
        self.initial_pose = InitialPose(node)
        self.relocalizer = Relocalizer(node, cfg.relocalize_timeout) if self.on_demand else None

    # ------------------------------------------------------------------ map

    def load_map(self, register: Any, config: PipelineConfig, cfg: NodeConfig) -> bool:
        """Load ``map_file`` where the pipeline runs; return True when it is ready."""
        log = self._node.get_logger()
        log.info(f'loading map {self.map_ref.path} (cache {self.map_ref.cache_dir or "off"})')
        try:
            if isinstance(register, IsolatedRegistration):
                info = register.prepare_map(self.map_ref, config, cfg.map_load_timeout)
            else:
                info = prepare_map(self.map_ref, config)
        except CgagsError as exc:
            self.map_error = f'map_file cannot be used: {exc}'
            log.error(self.map_error + '; no scan is registered until the node is restarted '
                      'with a usable map')
            return False
        self.map_info = info
        note = (f", {info['nonfinite_points']} non-finite points dropped"
                if info['nonfinite_points'] else '')
        log.info(f"map ready: {info['raw_points']} points -> {info['points']} after "
                 f"{info['voxel_size']:g} m voxels, cache {info['cache']} "
                 f"({info['load_s']:.2f} s){note}")
        return True

    # ------------------------------------------------------------------ on-demand gating

    def ready(self) -> bool:
        """Tell whether the worker may take a pair now (always, unless on_demand and idle)."""
        if self.relocalizer is None:
            return True
        self.relocalizer.expire()
        if self.relocalizer.waiting() is None:
            self.relocalizer.wait(0.2)
            return False
        return True

    def stale(self, pair: Pair, cfg: NodeConfig) -> str:
        """Return why an on-demand pair's scan is too old for the pending call, or ''."""
        called = self.relocalizer.waiting() if self.relocalizer is not None else None
        if called is None:
            return ''
        age = called - pair.source.payload.receipt_ns * 1e-9
        if age <= cfg.max_scan_age:
            return ''
        return (f'on_demand: the latest scan was received {age:.2f} s before the '
                f'~/relocalize call (> max_scan_age {cfg.max_scan_age:g} s); waiting for the '
                'next one')

    # ------------------------------------------------------------------ results

    def finish(self, pair: Pair, result: Any, T: np.ndarray, cov: np.ndarray | None,
               cfg: NodeConfig, frame_id: str) -> None:
        """Publish the candidates, offer the initial pose, answer a pending call."""
        source = pair.source.payload
        header = Header(stamp=source.header.stamp, frame_id=frame_id)
        candidates = list(result.candidates)
        msg = PoseArray(header=header)
        msg.poses = [transform_to_pose(c.transform) for c in candidates
                     if np.isfinite(c.transform).all()]
        self._node._send(self._candidates_pub, msg)
        calls = self.relocalizer is not None and self.relocalizer.waiting() is not None
        published, why = False, 'publish_initial_pose is off'
        key, refusal = quality_refusal(result, cfg)
        if cfg.publish_initial_pose and (calls or not self.on_demand):
            cov = np.zeros((6, 6)) if cov is None else cov
            published, why = self.initial_pose.offer(result, T, cov, source.header.stamp,
                                                     source.header.frame_id, cfg,
                                                     automatic=not self.on_demand)
        line = summary_line(result, T, key, refusal, published, why)
        with self._lock:
            self._candidates, self._last_summary = candidates, line
        if calls:
            self.relocalizer.answer(not key, line, key or 'ok')

    def settle(self, cause: str, message: str) -> None:
        """Answer calls still pending after a pair that failed before :meth:`finish`."""
        if self.relocalizer is not None and cause and self.relocalizer.waiting() is not None:
            if cause != 'on_demand_stale_scan':
                self.relocalizer.answer(False, f'not localized ({cause}): {message}', cause)

    def statistics(self, mode: str) -> dict[str, Any]:
        """Return the map, candidate, initial-pose and relocalize keys of /diagnostics."""
        with self._lock:
            candidates, line = list(self._candidates), self._last_summary
        stats: dict[str, Any] = {'mode': mode}
        if self.map_ref is not None:
            stats['map.file'] = self.map_ref.path
            stats.update({f'map.{k}': v for k, v in self.map_info.items() if k != 'path'})
            if self.map_error:
                stats['map.error'] = self.map_error
        stats['candidates.count'] = len(candidates)
        for i, c in enumerate(candidates):
            stats[f'candidates.{i}.inliers'] = c.num_inliers
            stats[f'candidates.{i}.fitness'] = round(c.fitness, 4)
            stats[f'candidates.{i}.ratio'] = round(c.ratio, 4)
        if line:
            stats['last_summary'] = line
        stats.update(self.initial_pose.statistics())
        if self.relocalizer is not None:
            stats.update(self.relocalizer.statistics())
        return stats

    def update_map_info(self, result: Any) -> None:
        """Take the map summary a registration reports (the map may have been reloaded)."""
        info = result.stats.get('map')
        if info:
            self.map_info = info

    def close(self) -> None:
        """Stop the relocalize service."""
        if self.relocalizer is not None:
            self.relocalizer.close()


def summary_line(result: Any, T: np.ndarray, key: str, refusal: str, published: bool,
                 why: str) -> str:
    """Return the one-line answer of ``~/relocalize``: pose, inliers, ratio, or why not."""
    ratio = float(result.runner_up_ratio)
    scores = (f'{result.num_inliers} inliers, best/runner-up {ratio:.2f}, fitness '
              f'{float(result.fitness):.3f}')
    if key:
        return f'not localized ({key}): {refusal}; {scores}'
    x, y, z = (float(v) for v in T[:3, 3])
    q = matrix_to_quaternion(T[:3, :3])
    yaw = math.degrees(math.atan2(2 * (q[3] * q[2] + q[0] * q[1]),
                                  1 - 2 * (q[1] ** 2 + q[2] ** 2)))
    pose = f'x {x:.3f} y {y:.3f} z {z:.3f} m, yaw {yaw:.1f} deg'
    return (f'localized: {pose}; {scores}; '
            + ('initial pose published' if published else f'initial pose not published: {why}'))
