"""
A pose accepted against a map, refined once more with the scan's own points.

The refinement matches the scan's voxel centroids; a scan of few voxels can settle degrees
from where its surfaces fit a map (docs/maps_measured.md, the simulated LiDAR's near
misses), and its own points at half the voxel settle it
(:func:`~cgags_ros.frontend.refine.refine_finer`). A pair of clouds is not refined again:
there both clouds' centroids are alike, and on the 3DMatch pairs the stage found no more
for much of a pair's time (docs/maps_measured.md).
"""

from __future__ import annotations

import numpy as np

from .gates import measure
from .result import PipelineResult
from ..config.pipeline import PipelineConfig
from ..frontend.features import CloudFeatures
from ..frontend.matching import Correspondences
from ..frontend.refine import Alignment, refine_finer, refines_finer
from ..timing import timed
from ..validity import gate_refusal


def polished(src: np.ndarray, fs: CloudFeatures, ft: CloudFeatures, corr: Correspondences,
             result: PipelineResult, cfg: PipelineConfig, overlap: Alignment,
             left_to_gates: bool, workers: int) -> Alignment:
    """
    Refine a pose accepted against a map once more with the scan's own points ``src``.

    :func:`~cgags_ros.frontend.refine.refine_finer`, for a 6-DoF scan of few voxels. After
    the verdict, which it never makes: a refused pose is not polished, so a wrong one cannot
    fit its way past the gates. The gates' measurements are then the polished pose's, and the
    candidate that was the judged pose becomes it, unless the gates would refuse it: the pose
    stays as judged. Returns the overlap.
    """
    if cfg.core.motion_model != '6dof' or not refines_finer(len(fs.points), cfg.refine):
        return overlap
    judged = result.transform
    with timed(result.timings, 'refinement'):
        result.transform = refine_finer(src, len(fs.points), ft.points, ft.normals, ft.tree,
                                        judged, voxel_size=cfg.voxel_size, config=cfg.refine,
                                        workers=workers)
    with timed(result.timings, 'validation'):
        after = measure(fs, ft, corr, result, cfg, map_target=True)
        if gate_refusal(result, cfg, left_to_gates) is not None:
            result.transform = judged
            return measure(fs, ft, corr, result, cfg, map_target=True)
    for candidate in result.candidates:
        if np.array_equal(candidate.transform, judged):
            candidate.transform = result.transform.copy()
            candidate.fitness = float(result.fitness)
    return after
