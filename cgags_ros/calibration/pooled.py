"""
Candidates from every frame's correspondences at once.

The extrinsic maps each frame's child keypoints onto its parent keypoints, so the right
pose collects the correspondence inliers of all frames, while a coincidence of one scene
collects only that frame's. The core searches the pooled correspondences of the frames
for their consensus, then again among the correspondences no earlier consensus explains,
as the pipeline searches one frame's for its candidates (:mod:`cgags_ros.pipeline.candidates`).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .frames import Evidence
from ..config.pipeline import PipelineConfig
from ..errors import DegenerateCorrespondencesError
from ..pipeline.candidates import MAX_ITERATIONS, support
from ..registration import register_correspondences


def pooled_candidates(evidence: list[Evidence], cfg: PipelineConfig
                      ) -> list[tuple[np.ndarray, float]]:
    """
    Return up to ``cfg.num_candidates`` (transform parent <- child, tau in metres).

    Empty when the frames hold fewer than three correspondences in all.
    """
    usable = [e for e in evidence if e.matches is not None and len(e.matches[0])]
    if not usable:
        return []
    src = np.vstack([e.matches[0] for e in usable])
    dst = np.vstack([e.matches[1] for e in usable])
    resolution = float(np.mean([e.resolution for e in usable]))
    tau = cfg.core.inlier_threshold or None
    explained = np.zeros(len(src), dtype=bool)
    found: list[tuple[np.ndarray, float]] = []
    for attempt in range(cfg.num_candidates):
        rest = np.flatnonzero(~explained)
        if len(rest) < 3:
            break
        core_cfg = cfg.core if attempt == 0 else dataclasses.replace(
            cfg.core, max_iterations=min(cfg.core.max_iterations, MAX_ITERATIONS))
        try:
            core = register_correspondences(src[rest], dst[rest], inlier_threshold=tau,
                                            resolution=resolution, config=core_cfg,
                                            seed=cfg.seed + attempt)
        except DegenerateCorrespondencesError:
            break
        if core.num_inliers < cfg.core.min_inliers:
            break  # what is left supports no motion
        found.append((core.transform, float(core.inlier_threshold)))
        explained |= support(src, dst, core.transform, core.inlier_threshold)
        explained[rest[core.inliers]] = True
    return found
