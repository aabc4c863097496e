"""
Structured rivals: the poses a near-symmetric or weakly constrained scene would also accept.

The candidate search (:mod:`.candidates`) finds rivals the correspondences support. A room
that looks alike turned round, or a wall along which the overlap can slide, may give its
wrong pose few distinct correspondences but as good a fit on the surfaces. So before an
estimate is called valid, the poses such a scene would confuse it with are tried directly:
the estimate turned 180 degrees about each principal axis of the overlap (through its
centroid); slid both ways along the translation the overlap constrains least (``SLIDE``
voxels); turned a quarter of the way both ways about each principal axis of the overlap's
normals (a room's walls and floor face along those axes, and a near-square room turns
about its vertical one); and the other distinct poses the correspondences support (the
candidates within the ambiguity ratio were refined already; the others were not). Each
start that already fits reasonably (at least ``PROMISING`` times the estimate's fitness,
on every ``STRIDE``-th source point: a share needs no more to be told apart; most that
start worse never settle anywhere plausible) is refined in the estimate's stages
(``ITERATIONS`` a stage of point-to-plane against the target's k-d tree, built once with
its features: a rival only has to show where it settles) and judged like the estimate. A
rival is plausible when it settles away from the estimate (more than
``candidates.MIN_ROTATION_DEG`` or ``APART`` voxels), does not stack surfaces where a sensor
saw free space (violation at most ``MAX_VIOLATION``) and fits at least ``1 /
OVERLAP_RATIO`` as well as the estimate (fitness, the share of source points on the
target: a large target's share would say nothing): the result is then ambiguous, with the
rival as runner-up. Each test of that verdict is a function of its own (:func:`worth_refining`,
:func:`settled_apart`, :func:`fits_as_well`, :func:`clear_of_free_space`), so that a study
judging recorded rivals judges them as the pipeline does. The settings were chosen
leave-one-scene-out on real RGB-D pairs (docs/ablation.md); a map target is not checked.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from .candidates import MIN_ROTATION_DEG, support
from .gates import measured_free_space
from .map import PreparedMap
from .result import Candidate, PipelineResult
from ..config.pipeline import PipelineConfig
from ..frontend.features import CloudFeatures
from ..frontend.matching import Correspondences
from ..frontend.refine import evaluate_alignment, staged_point_to_plane
from ..geometry import rotation_error_deg, translation_error
from ..parallel import map_ordered

SLIDE = 10.0
SYMMETRY_FIT = 0.5  # a turn is a symmetry of a map when it puts half of the map on itself
SYMMETRY_START = 1 / 3  # ...and it is refined only when it starts with a third there
SYMMETRY_POINTS = 2000  # about this many of the map's points judge a turn
ITERATIONS = 5
STRIDE = 2
# The verdict's limits (:func:`worth_refining`, :func:`settled_apart`, :func:`fits_as_well`,
# :func:`clear_of_free_space`), chosen on real RGB-D pairs (docs/ablation.md);
# ``python -m bench.studies.fit`` regenerates them from the study's records.
PROMISING = 0.45
APART = 4.0
MAX_VIOLATION = 0.1
OVERLAP_RATIO = 1.25


def worth_refining(start_fitness: float, fitness: float, promising: float = PROMISING) -> bool:
    """Tell whether a rival is refined: its start fits ``promising`` times the estimate's."""
    return start_fitness >= promising * fitness


def settled_apart(rotation_deg: float, translation_m: float, voxel_size: float,
                  min_rotation_deg: float, apart: float = APART) -> bool:
    """Tell whether a rival settled this far from the estimate is another pose, not it."""
    return rotation_deg > min_rotation_deg or translation_m > apart * voxel_size


def fits_as_well(fitness: float, estimate_fitness: float, ratio: float = OVERLAP_RATIO) -> bool:
    """Tell whether a rival's fitness is at least ``1 / ratio`` of the estimate's."""
    return fitness * ratio >= estimate_fitness


def clear_of_free_space(violation: float, limit: float = MAX_VIOLATION) -> bool:
    """Tell whether a rival stacks few enough surfaces in free space (NaN: not measured)."""
    return not violation > limit


def rival_starts(fs: CloudFeatures, ft: CloudFeatures, T: np.ndarray, distance: float,
                 voxel_size: float, candidates: Sequence[np.ndarray] = ()
                 ) -> list[tuple[str, np.ndarray]]:
    """
    Return the structured rivals' starting poses of ``T``, each with its name.

    In this order: ``flip0..2``, ``slide1``/``slide-1``, ``turn0..2`` with ``+``/``-``, and
    ``candidate1..`` (``candidates``: the other distinct poses the correspondences support).
    See the module doc.
    """
    align = evaluate_alignment(fs.points, ft.tree, T, distance)
    if len(align.source_index) < 6:
        return []
    rotated = fs.points[align.source_index] @ T[:3, :3].T
    moved = rotated + T[:3, 3]
    centroid = moved.mean(axis=0)
    _, axes = np.linalg.eigh(np.cov(moved.T))
    starts = [(f'flip{i}', _turned(T, axis, np.pi, centroid)) for i, axis in enumerate(axes.T)]
    normals = ft.normals[align.target_index]
    _, directions = np.linalg.eigh(normals.T @ normals)  # least constrained translation first
    for sign in (1, -1):
        M = np.eye(4)
        M[:3, 3] = sign * SLIDE * voxel_size * directions[:, 0]
        starts.append((f'slide{sign}', M @ T))
    # A room's walls and floor face along a few directions, and the eigenvectors of the
    # normals' scatter are those directions: a four-fold symmetric room turns about one.
    for i, axis in enumerate(directions.T):
        for sign, label in ((1, '+'), (-1, '-')):
            starts.append((f'turn{i}{label}', _turned(T, axis, sign * np.pi / 2, centroid)))
    starts.extend((f'candidate{k}', np.asarray(C, dtype=np.float64))
                  for k, C in enumerate(candidates, start=1))
    return starts


def _turned(T: np.ndarray, axis: np.ndarray, angle: float, centre: np.ndarray) -> np.ndarray:
    """Return ``T`` followed by a turn of ``angle`` radians about ``axis`` through ``centre``."""
    M = np.eye(4)
    M[:3, :3] = Rotation.from_rotvec(angle * axis).as_matrix()
    M[:3, 3] = centre - M[:3, :3] @ centre
    return M @ T


def settle(fs: CloudFeatures, ft: CloudFeatures, start: np.ndarray, coarse_distance: float,
           cfg: PipelineConfig) -> np.ndarray:
    """
    Return where a rival starting at ``start`` settles (4x4 source -> target, metres).

    The estimate's stages (the core's inlier threshold ``coarse_distance`` first when it is
    the larger, then the final correspondence distance), ``ITERATIONS`` each, point-to-plane
    on the target's normals whatever the estimate's refinement method, from every
    ``STRIDE``-th source point: a rival only has to show where it goes, not how precisely
    (its fitness is then judged on every point), and the target's k-d tree serves every
    rival.
    """
    final = cfg.refine.max_correspondence_distance_factor * cfg.voxel_size
    return staged_point_to_plane(fs.points[::STRIDE], ft.points, ft.normals, ft.tree, start,
                                 coarse_distance, final, ITERATIONS)


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

    def judge(start: np.ndarray) -> Candidate | None:
        """Return the rival settled from ``start`` when it is plausible (see the module doc)."""
        if not worth_refining(
                evaluate_alignment(fs.points[::STRIDE], ft.tree, start, distance).fitness,
                result.fitness):
            return None
        R = settle(fs, ft, start, float(result.inlier_threshold), cfg)
        if not settled_apart(rotation_error_deg(R, T), translation_error(R, T), v,
                             MIN_ROTATION_DEG):
            return None  # settled back onto the estimate: it is constrained there
        fitness = evaluate_alignment(fs.points, ft.tree, R, distance).fitness
        if not fits_as_well(fitness, result.fitness):
            return None
        if not clear_of_free_space(measured_free_space(fs, ft, R, cfg, map_target)):
            return None
        inliers = support(fs.points[corr.source_index], ft.points[corr.target_index], R,
                          float(result.inlier_threshold))
        return Candidate(R, int(np.count_nonzero(inliers)), fitness)

    # The starts are independent: judged side by side, the first plausible one in their
    # order is the rival, as if they were judged one after the other.
    others = [c.transform for c in result.candidates[1:]]
    starts = [start for _, start in rival_starts(fs, ft, T, distance, v, others)]
    rivals = map_ordered(judge, starts, workers)
    return next((rival for rival in rivals if rival is not None), None)


def mark_ambiguous(result: PipelineResult, rival: Candidate) -> None:
    """Make ``rival`` the runner-up of ``result`` and flag the result ambiguous."""
    best = result.candidates[0]
    rival.ratio = rival.num_inliers / best.num_inliers if best.num_inliers else 0.0
    result.candidates.insert(1, rival)
    result.ambiguous = True
    if rival.num_inliers > 0:
        result.runner_up_ratio = best.num_inliers / rival.num_inliers


def map_symmetries(prepared: PreparedMap, cfg: PipelineConfig) -> list[np.ndarray]:
    """
    Return the turns of a map that put it onto itself (4x4 each, map frame), found once.

    A room, a hall or a box-like store whose floor plan is near-square looks alike turned a
    quarter or half of the way about its vertical: every pose in it has such twins, whatever
    the scans show of the room. The map is turned by 90, -90 and 180 degrees about each
    principal axis of its normals' scatter, through its centroid (a symmetric room's centre);
    a turn that puts at least ``SYMMETRY_START`` of about ``SYMMETRY_POINTS`` evenly spread
    map points back on the map is refined map onto map (point-to-plane), and one that then
    puts at least ``SYMMETRY_FIT`` of them there is a symmetry. Kept on ``prepared``.
    """
    if prepared.symmetries is not None:
        return prepared.symmetries
    ft = prepared.features
    final = cfg.refine.max_correspondence_distance_factor * cfg.voxel_size
    points = ft.points[::max(1, len(ft.points) // SYMMETRY_POINTS)]
    found = []
    if len(points) >= 6:
        centre = ft.points.mean(axis=0)
        _, axes = np.linalg.eigh(ft.normals.T @ ft.normals)
        for axis in axes.T:
            for angle in (np.pi / 2, -np.pi / 2, np.pi):
                start = _turned(np.eye(4), axis, angle, centre)
                if evaluate_alignment(points, ft.tree, start, final).fitness < SYMMETRY_START:
                    continue
                S = staged_point_to_plane(points, ft.points, ft.normals, ft.tree, start,
                                          SLIDE * cfg.voxel_size, final, 2 * ITERATIONS)
                if evaluate_alignment(points, ft.tree, S, final).fitness >= SYMMETRY_FIT:
                    found.append(S)
    prepared.symmetries = found
    return found
