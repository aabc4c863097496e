"""
The map of ``map.file`` as the node's one latched target: loaded where the pipeline runs.

ROS-free. The features are computed (or read from the on-disk cache) in the registration
process, so the node's process never holds them; the node pairs every scan with a target
that is the map's reference (:class:`~.interface.MapCloud`), never its points.
"""

from __future__ import annotations

import os
import time
from typing import Any, Callable

from .interface import MapCloud, StartFailed
from ..config.node import NodeConfig
from ..config.pipeline import PipelineConfig
from ..errors import CgagsError
from ..pipeline.result import PipelineResult
from ..runtime.jobs import MapReady, MapRef, PrepareMap, Runner


class MapTarget:
    """The map file, its load summary (``map.*`` of /diagnostics) or why it is unusable."""

    def __init__(self, cfg: NodeConfig):
        self.ref = MapRef(os.path.expanduser(cfg.map.file), os.path.expanduser(cfg.map.cache_dir))
        self.info: dict[str, Any] = {}
        self.error = ''

    def load(self, runner: Runner, config: PipelineConfig, cfg: NodeConfig,
             log: Callable[[str, str], None]) -> MapCloud:
        """
        Load the map where the pipeline runs (features computed or from the cache).

        ``runner`` runs the job: in a registration process of its own the load may take
        ``map.load_timeout``; in this process it cannot be bounded.

        :returns: the map as the target of every scan.
        :raises StartFailed: the map is missing, unreadable or empty, or its load failed
            (past the time limit, or the process died); ``error`` says why.
        """
        ref = self.ref
        log('info', f'loading map {ref.path} (cache {ref.cache_dir or "off"})')
        try:
            answer = runner.run(PrepareMap(ref, config), cfg.map.load_timeout)
            assert isinstance(answer, MapReady)
            info = answer.info
        except CgagsError as exc:
            self.error = f'map.file cannot be used: {exc}'
            raise StartFailed(self.error) from exc
        self.info = info
        note = (f", {info['nonfinite_points']} non-finite points dropped"
                if info['nonfinite_points'] else '')
        log('info', f"map ready: {info['raw_points']} points -> {info['points']} after "
            f"{info['voxel_size']:g} m voxels, cache {info['cache']} ({info['load_s']:.2f} s), "
            f"normals signed by {info.get('normals') or 'the cached setting'}{note}")
        if info.get('normals') == 'origin':
            log('warning', "the map file carries no normals, so the map's face its frame origin, "
                "unlike a scan's (its sensor): fine for one scan kept in its sensor frame, "
                'not for a map fused from many views; write the map with normals facing its '
                'sensors, or set frontend.normal_orientation to centroid (docs/relocalization.md)')
        return MapCloud(ref, cfg.map.frame, time.monotonic_ns())

    def update(self, result: PipelineResult) -> None:
        """Take the map summary a registration reports (the map may have been reloaded)."""
        if result.map_info:
            self.info = result.map_info

    def statistics(self) -> dict[str, Any]:
        """Return the ``map.*`` keys of /diagnostics."""
        stats: dict[str, Any] = {'map.file': self.ref.path}
        stats.update({f'map.{k}': v for k, v in self.info.items() if k != 'path'})
        if self.error:
            stats['map.error'] = self.error
        return stats
