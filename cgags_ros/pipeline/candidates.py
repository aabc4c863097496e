"""
Ranked, distinct candidate poses and the ambiguity flag.

The core returns one estimate. Further candidates are found in the pipeline, without
touching the core: the correspondences the estimate explains (within tau of its coarse
transform) are set aside and the core searches again among the rest, up to
``num_candidates - 1`` times (each search at most :data:`MAX_ITERATIONS` hypotheses), and
no further once a search finds only a chance-level consensus (the core reports it invalid:
it is the last candidate, the rest of the correspondences support no motion). A new
estimate is a candidate only when it is distinct from every earlier one: its rotation
differs by more than :data:`MIN_ROTATION_DEG` or its translation by more than
:data:`MIN_TRANSLATION_FACTOR` voxel sizes. Every candidate's support is counted
the same way, on all correspondences: those within tau of its coarse transform. The first
candidate is the final (refined) estimate; the others are the core's estimates (re-fit on
their inliers, good to about tau), not refined: ICP from a wrong pose would cost more than
the search itself.

Ambiguity: with a runner-up, best / runner-up inliers below ``ambiguity_ratio`` means two
poses are nearly equally supported by the correspondences. With ``verify_rivals`` each such
rival is then refined like the estimate and judged on the geometry as well
(:func:`verify_rivals`): one that converges onto the estimate supports it, one whose overlap
the estimate's exceeds ``ambiguity_ratio`` times, or that stacks surfaces where a sensor saw
free space, is no plausible alternative. The result is flagged ambiguous and invalid only
when a plausible, distinct rival remains.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .gates import measured_free_space
from .result import Candidate, PipelineResult
from ..config.pipeline import PipelineConfig
from ..errors import DegenerateCorrespondencesError
from ..frontend.features import CloudFeatures
from ..frontend.matching import Correspondences
from ..frontend.refine import evaluate_alignment, refine_transform
from ..geometry import apply_transform, rotation_error_deg, translation_error
from ..parallel import map_ordered
from ..registration import register_correspondences
from ..validity import free_space_limit

MAX_ITERATIONS = 1000  # hypotheses of each search for a further candidate (at most the core's)
MIN_ROTATION_DEG = 10.0  # two candidates are distinct beyond this rotation (degrees)
MIN_TRANSLATION_FACTOR = 10.0  # or beyond this translation (voxel sizes)


def support(src: np.ndarray, dst: np.ndarray, transform: np.ndarray, tau: float) -> np.ndarray:
    """Return the mask of correspondences ``src[i] -> dst[i]`` within ``tau`` of ``transform``."""
    return np.linalg.norm(apply_transform(transform, src) - dst, axis=1) <= tau


def distinct(a: np.ndarray, b: np.ndarray, cfg: PipelineConfig) -> bool:
    """Tell whether transforms ``a`` and ``b`` are distinct candidates (see the module doc)."""
    return (rotation_error_deg(a, b) > MIN_ROTATION_DEG
            or translation_error(a, b) > MIN_TRANSLATION_FACTOR * cfg.voxel_size)


def find_candidates(fs: CloudFeatures, ft: CloudFeatures, corr: Correspondences,
                    result: PipelineResult, cfg: PipelineConfig) -> None:
    """
    Fill ``result.candidates``, ``runner_up_ratio`` and ``ambiguous`` (see the module doc).

    ``result`` holds the core's estimate (``coarse_transform``) and the final
    ``transform`` and ``fitness``; it is the first candidate.
    """
    rank_candidates(result, search_rivals(fs, ft, corr, result, cfg), cfg)


def search_rivals(fs: CloudFeatures, ft: CloudFeatures, corr: Correspondences,
                  result: PipelineResult, cfg: PipelineConfig) -> list[Candidate]:
    """
    Return the best candidate (without its fitness: NaN) and the rivals found, in order.

    Reads only the core's estimate (``coarse_transform``, ``inliers``, ``inlier_threshold``,
    ``resolution``) and the final ``transform`` of ``result``, never what the gates set,
    so it may run beside them (:func:`rank_candidates` completes the list).
    """
    src, dst = fs.points[corr.source_index], ft.points[corr.target_index]
    tau = float(result.inlier_threshold)
    explained = support(src, dst, result.coarse_transform, tau)
    best = Candidate(np.asarray(result.transform, dtype=np.float64).copy(),
                     int(np.count_nonzero(explained)), float('nan'))
    explained[result.inliers] = True
    found = [best]
    core_cfg = dataclasses.replace(
        cfg.core, max_iterations=min(cfg.core.max_iterations, MAX_ITERATIONS))
    distance = cfg.refine.max_correspondence_distance_factor * cfg.voxel_size
    need = 2 if cfg.core.motion_model == '4dof' else 3
    for attempt in range(1, 2 * cfg.num_candidates):
        if len(found) >= cfg.num_candidates:
            break
        rest = np.flatnonzero(~explained)
        if len(rest) < need:
            break
        try:
            core = register_correspondences(
                src[rest], dst[rest], inlier_threshold=tau,
                resolution=result.resolution, config=core_cfg, seed=cfg.seed + attempt)
        except DegenerateCorrespondencesError:
            break
        if core.num_inliers < cfg.core.min_inliers:
            break  # what is left supports no motion
        mask = support(src, dst, core.transform, tau)
        explained |= mask
        explained[rest[core.inliers]] = True
        T = core.transform
        if not all(distinct(T, c.transform, cfg) for c in found):
            continue  # a remnant of an earlier candidate's consensus
        fitness = evaluate_alignment(fs.points, ft.tree, T, distance).fitness
        found.append(Candidate(T, int(np.count_nonzero(mask)), fitness))
        if not core.valid:
            break  # a chance-level consensus: what is left supports no motion either
    return found


def rank_candidates(result: PipelineResult, found: list[Candidate],
                    cfg: PipelineConfig) -> None:
    """Complete :func:`search_rivals`' list with ``result.fitness`` and set the ambiguity."""
    best = found[0]
    best.fitness = float(result.fitness)
    found[1:] = sorted(found[1:], key=lambda c: -c.num_inliers)
    for c in found:
        c.ratio = c.num_inliers / best.num_inliers if best.num_inliers else 0.0
    result.candidates = found
    if len(found) > 1 and found[1].num_inliers > 0:
        result.runner_up_ratio = best.num_inliers / found[1].num_inliers
        result.ambiguous = result.runner_up_ratio < cfg.gates.ambiguity_ratio


def verify_rivals(fs: CloudFeatures, ft: CloudFeatures, result: PipelineResult,
                  cfg: PipelineConfig, map_target: bool = False,
                  workers: int = 1) -> Candidate | None:
    """
    Judge the rivals that make ``result`` ambiguous on the geometry (see the module doc).

    Runs after :func:`rank_candidates` and the gates (it reads ``result.overlap`` and
    ``result.free_space_violation``). Each rival within ``ambiguity_ratio`` of the best's
    inliers is refined from its core pose; one that converges onto the estimate is dropped
    (it is the same pose), the others keep their refined transform and fitness. A pose is
    plausible when it passes the free-space gate (where that applies); its geometric
    support is its overlap (the smaller share of both clouds' points within the refinement
    distance). The estimate stays unless it is implausible or a plausible rival's overlap
    exceeds its own ``ambiguity_ratio`` times: the plausible rival with the largest overlap
    is then returned, for the caller to make it the estimate. ``ambiguous`` stays True only
    when another plausible pose's overlap is above the chosen one's / ``ambiguity_ratio``,
    or when the chosen one's free-space violation is above the tighter bound of an
    unsettled estimate (``gates.free_space_settle_factor``).
    """
    if not (cfg.gates.verify_rivals and result.ambiguous) or cfg.refine.method == 'none':
        return None
    v, ratio = cfg.voxel_size, cfg.gates.ambiguity_ratio
    distance = cfg.refine.max_correspondence_distance_factor * v
    gravity = cfg.core.gravity_axis if cfg.core.motion_model == '4dof' else None
    limit = cfg.gates.max_free_space_violation
    best = result.candidates[0]
    # (candidate, overlap) of every plausible pose within the inlier ratio, best first.
    plausible = [] if result.free_space_violation > limit else [(best, result.overlap)]
    violation = {id(best): result.free_space_violation}
    kept = [best]
    contenders = [c for c in result.candidates[1:] if c.num_inliers * ratio > best.num_inliers]
    # Each contender refines on its own: side by side (their ICP runs outside the GIL); a
    # lone one keeps the threads for its refinement's neighbour queries (4-DoF).
    inner = max(1, workers // max(1, len(contenders)))

    def refined(c: Candidate) -> tuple[np.ndarray, float, float, float] | None:
        """Return the rival refined: its transform, fitness both ways and free-space violation."""
        T = refine_transform(fs.points, ft.points, c.transform, voxel_size=v,
                             config=cfg.refine, target_normals=ft.normals,
                             coarse_distance=result.inlier_threshold, gravity=gravity,
                             workers=inner)
        if not distinct(T, best.transform, cfg):
            return None  # converged onto the estimate: it supports it
        ahead = evaluate_alignment(fs.points, ft.tree, T, distance).fitness
        back = evaluate_alignment(ft.points, fs.tree, np.linalg.inv(T), distance).fitness
        return T, ahead, back, measured_free_space(fs, ft, T, cfg, map_target)

    settled = dict(zip(map(id, contenders), map_ordered(refined, contenders, workers)))
    for c in result.candidates[1:]:
        if id(c) not in settled:
            kept.append(c)  # clearly less supported: no rival, left as found
            continue
        if settled[id(c)] is None:
            continue
        c.transform, c.fitness, back, violation[id(c)] = settled[id(c)]
        kept.append(c)
        if not violation[id(c)] > limit:  # NaN: the gate does not apply
            plausible.append((c, min(c.fitness, back)))
    chosen, support = best, result.overlap
    if plausible:
        top, top_support = max(plausible, key=lambda p: p[1])
        if plausible[0][0] is not best or top_support >= ratio * result.overlap:
            chosen, support = top, top_support
    result.candidates = [chosen] + [c for c in kept if c is not chosen]
    # Settled by the geometry only when the chosen pose clearly passes the free-space test;
    # when every rival converged onto it, nothing distinct is left to be confused with.
    result.ambiguous = len(result.candidates) > 1 and (
        any(c is not chosen and o * ratio > support for c, o in plausible)
        or violation[id(chosen)] > free_space_limit(cfg, unsettled=True))
    rivals = [c.num_inliers for c in result.candidates[1:] if c.num_inliers > 0]
    result.runner_up_ratio = (chosen.num_inliers / max(rivals) if rivals
                              else float('inf'))
    return chosen if chosen is not best else None
