"""
Structured rivals: the poses a near-symmetric or weakly constrained scene would also accept.

The candidate search (:mod:`.candidates`) finds rivals the correspondences support. A room
that looks alike turned half-way round, or a wall along which the overlap can slide, may
give its wrong pose few distinct correspondences but as good a fit on the surfaces. So
before an estimate is called valid, the poses such a scene would confuse it with are tried
directly: the estimate turned 180 degrees about each principal axis of the overlap (through
its centroid), and slid both ways along the translation the overlap constrains least
(``SLIDE`` voxels). Each start that already fits reasonably (at least ``PROMISING`` times
the estimate's fitness) is refined like the estimate (``ITERATIONS`` a stage: a rival only
has to show where it settles) and judged like it. A rival is plausible when it settles
away from the estimate (more than ``candidate_min_rotation_deg`` or ``APART`` voxels), does
not stack surfaces where a sensor saw free space (violation at most ``MAX_VIOLATION``) and
fits at least ``1 / OVERLAP_RATIO`` as well as the estimate (fitness, the share of source
points on the target: a large target's share would say nothing): the result is then
ambiguous, with the rival as runner-up. The settings were chosen leave-one-scene-out on
real RGB-D pairs (docs/ablation.md); a map target is not checked.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial.transform import Rotation

from .candidates import support
from .gates import measured_free_space
from .result import Candidate, PipelineResult
from ..config.pipeline import PipelineConfig
from ..frontend.features import CloudFeatures
from ..frontend.matching import Correspondences
from ..frontend.refine import evaluate_alignment, refine_transform
from ..geometry import rotation_error_deg, translation_error

SLIDE = 10.0
PROMISING = 0.25
ITERATIONS = 5
APART = 6.0
MAX_VIOLATION = 0.1
OVERLAP_RATIO = 1.5


def rival_starts(fs: CloudFeatures, ft: CloudFeatures, T: np.ndarray,
                 distance: float, voxel_size: float) -> list[np.ndarray]:
    """Return the starting poses of the structured rivals of ``T`` (see the module doc)."""
    align = evaluate_alignment(fs.points, ft.tree, T, distance)
    if len(align.source_index) < 6:
        return []
    rotated = fs.points[align.source_index] @ T[:3, :3].T
    moved = rotated + T[:3, 3]
    centroid = moved.mean(axis=0)
    _, axes = np.linalg.eigh(np.cov(moved.T))
    starts = []
    for axis in axes.T:
        M = np.eye(4)
        M[:3, :3] = Rotation.from_rotvec(np.pi * axis).as_matrix()
        M[:3, 3] = centroid - M[:3, :3] @ centroid
        starts.append(M @ T)
    normals = ft.normals[align.target_index]
    _, directions = np.linalg.eigh(normals.T @ normals)  # least constrained translation first
    for sign in (1.0, -1.0):
        M = np.eye(4)
        M[:3, 3] = sign * SLIDE * voxel_size * directions[:, 0]
        starts.append(M @ T)
    return starts


def structured_rival(fs: CloudFeatures, ft: CloudFeatures, corr: Correspondences,
                     result: PipelineResult, cfg: PipelineConfig,
                     map_target: bool = False, workers: int = 1) -> Candidate | None:
    """
    Return the first plausible structured rival of ``result``'s estimate, or None.

    ``result`` has passed the gates (its ``fitness`` is set). 6-DoF pairs of sensor-frame
    clouds only: a 4-DoF estimate cannot turn about a horizontal axis (its yaw flips are
    what the correspondences' own rivals test); without the free-space test (clouds not in
    their sensor frames, or the gate off) a slide along a wall fits as well as the estimate
    whether or not it is right; and a map (``map_target``) was not measured.
    """
    if (cfg.core.motion_model == '4dof' or cfg.refine.method == 'none' or map_target
            or cfg.frontend.normal_orientation != 'origin'
            or cfg.gates.max_free_space_violation >= 1):
        return None
    v = cfg.voxel_size
    distance = cfg.refine.max_correspondence_distance_factor * v
    T = np.asarray(result.transform, dtype=np.float64)
    refine = dataclasses.replace(cfg.refine, max_iterations=ITERATIONS)
    for start in rival_starts(fs, ft, T, distance, v):
        if evaluate_alignment(fs.points, ft.tree, start, distance).fitness \
                < PROMISING * result.fitness:
            continue
        R = refine_transform(fs.points, ft.points, start, voxel_size=v, config=refine,
                             target_normals=ft.normals,
                             coarse_distance=result.inlier_threshold, workers=workers)
        if (rotation_error_deg(R, T) <= cfg.candidate_min_rotation_deg
                and translation_error(R, T) <= APART * v):
            continue  # settled back onto the estimate: it is constrained there
        fitness = evaluate_alignment(fs.points, ft.tree, R, distance).fitness
        if fitness * OVERLAP_RATIO < result.fitness:
            continue
        if measured_free_space(fs, ft, R, cfg, map_target) > MAX_VIOLATION:
            continue
        inliers = support(fs.points[corr.source_index], ft.points[corr.target_index], R,
                          float(result.inlier_threshold))
        return Candidate(R, int(np.count_nonzero(inliers)), fitness)
    return None


def mark_ambiguous(result: PipelineResult, rival: Candidate) -> None:
    """Make ``rival`` the runner-up of ``result`` and flag the result ambiguous."""
    best = result.candidates[0]
    rival.ratio = rival.num_inliers / best.num_inliers if best.num_inliers else 0.0
    result.candidates.insert(1, rival)
    result.ambiguous = True
    if rival.num_inliers > 0:
        result.runner_up_ratio = best.num_inliers / rival.num_inliers
