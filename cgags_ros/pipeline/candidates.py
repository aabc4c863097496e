"""
Ranked, distinct candidate poses: the other poses the correspondences support.

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

Whether they make the estimate ambiguous is :mod:`cgags_ros.validity`'s to say: a
runner-up within ``ambiguity_ratio`` of the best's inliers does
(:func:`~cgags_ros.validity.outnumbered`). With ``gates.settle_candidates`` each candidate
within that ratio is then settled (:func:`settle_candidates`: refined as the estimate is,
:mod:`.settle`) and measured on the geometry: one that converges onto the estimate supports
it, the others keep their refined pose and fitness; what they measured (a
:class:`Settlement`) is judged by :func:`~cgags_ros.validity.still_ambiguous`.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .result import Candidate, PipelineResult
from .settle import CANDIDATE, Pair, settle, Settled, support
from ..config.pipeline import PipelineConfig
from ..errors import DegenerateCorrespondencesError
from ..frontend.features import CloudFeatures
from ..frontend.matching import Correspondences
from ..frontend.refine import evaluate_alignment
from ..geometry import rotation_error_deg, translation_error
from ..parallel import map_ordered
from ..registration import register_correspondences
from ..validity import passes_free_space

MAX_ITERATIONS = 1000  # hypotheses of each search for a further candidate (at most the core's)
MIN_ROTATION_DEG = 10.0  # two candidates are distinct beyond this rotation (degrees)
MIN_TRANSLATION_FACTOR = 10.0  # or beyond this translation (voxel sizes)


def distinct(a: np.ndarray, b: np.ndarray, cfg: PipelineConfig) -> bool:
    """Tell whether transforms ``a`` and ``b`` are distinct candidates (see the module doc)."""
    return (rotation_error_deg(a, b) > MIN_ROTATION_DEG
            or translation_error(a, b) > MIN_TRANSLATION_FACTOR * cfg.voxel_size)


def search_candidates(fs: CloudFeatures, ft: CloudFeatures, corr: Correspondences,
                      result: PipelineResult, cfg: PipelineConfig) -> list[Candidate]:
    """
    Return the best candidate (without its fitness: NaN) and the others found, in order.

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


def rank_candidates(result: PipelineResult, found: list[Candidate]) -> None:
    """Complete :func:`search_candidates`' list with ``result.fitness`` and the runner-up ratio."""
    best = found[0]
    best.fitness = float(result.fitness)
    found[1:] = sorted(found[1:], key=lambda c: -c.num_inliers)
    for c in found:
        c.ratio = c.num_inliers / best.num_inliers if best.num_inliers else 0.0
    result.candidates = found
    if len(found) > 1 and found[1].num_inliers > 0:
        result.runner_up_ratio = best.num_inliers / found[1].num_inliers


@dataclasses.dataclass
class Settlement:
    """
    What settling an ambiguous estimate's candidates measured (:func:`settle_candidates`).

    :ivar chosen: the estimate's pose now: the best, or a candidate the geometry prefers.
    :ivar replaces: ``chosen`` is a candidate: it replaces the estimate.
    :ivar overlap: the chosen pose's overlap (the smaller of its fitness both ways).
    :ivar free_space: the chosen pose's free-space violation (NaN: not measured).
    :ivar others: the other plausible candidates' overlaps.
    :ivar alone: no distinct candidate is left (every one settled onto the chosen pose).
    """

    chosen: Candidate
    replaces: bool
    overlap: float
    free_space: float
    others: list[float]
    alone: bool


def settle_candidates(fs: CloudFeatures, ft: CloudFeatures, result: PipelineResult,
                      cfg: PipelineConfig, map_target: bool = False,
                      workers: int = 1) -> Settlement | None:
    """
    Settle the candidates that make ``result`` ambiguous and measure them (module doc).

    Runs after :func:`rank_candidates` and the gates (it reads ``result.overlap`` and
    ``result.free_space_violation``), when the estimate is ambiguous on its inliers. Each
    candidate within ``ambiguity_ratio`` of the best's inliers is settled from its core pose
    (:data:`~.settle.CANDIDATE`); one that converges onto the estimate is dropped (it is the
    same pose), the others keep their refined transform and fitness. A pose is plausible
    when it passes the free-space gate (where that applies); its geometric support is its
    overlap. The estimate stays unless it is implausible or a plausible candidate's overlap
    exceeds its own ``ambiguity_ratio`` times: the plausible one with the largest overlap is
    then chosen, first in ``result.candidates``, for the caller to make it the estimate.
    None when nothing is settled (not ambiguous, ``gates.settle_candidates`` off, or no
    refinement).
    """
    if not (cfg.gates.settle_candidates and result.ambiguous) or cfg.refine.method == 'none':
        return None
    ratio = cfg.gates.ambiguity_ratio
    best = result.candidates[0]
    # (candidate, overlap) of every plausible pose within the inlier ratio, best first.
    plausible = ([(best, result.overlap)] if passes_free_space(result.free_space_violation, cfg)
                 else [])
    violation = {id(best): result.free_space_violation}
    kept = [best]
    close = [c for c in result.candidates[1:] if c.num_inliers * ratio > best.num_inliers]
    # Each close candidate settles on its own: side by side (their ICP runs outside the GIL);
    # a lone one keeps the threads for its refinement's neighbour queries (4-DoF).
    inner = max(1, workers // max(1, len(close)))
    pair = Pair(fs, ft, cfg, map_target)

    def settled(c: Candidate) -> Settled | None:
        """Return the candidate settled and measured, or None when it joins the estimate."""
        s = settle(pair, c.transform, result.inlier_threshold, CANDIDATE, inner)
        if not distinct(s.transform, best.transform, cfg):
            return None  # converged onto the estimate: it supports it
        return s.measured('fitness', 'back', 'free_space')

    settled_by = dict(zip(map(id, close), map_ordered(settled, close, workers)))
    for c in result.candidates[1:]:
        if id(c) not in settled_by:
            kept.append(c)  # clearly less supported: not settled, left as found
            continue
        if (s := settled_by[id(c)]) is None:
            continue
        c.transform, c.fitness, violation[id(c)] = s.transform, s.fitness, s.free_space
        kept.append(c)
        if passes_free_space(s.free_space, cfg):
            plausible.append((c, s.overlap))
    chosen, overlap = best, result.overlap
    if plausible:
        top, top_overlap = max(plausible, key=lambda p: p[1])
        if plausible[0][0] is not best or top_overlap >= ratio * result.overlap:
            chosen, overlap = top, top_overlap
    result.candidates = [chosen] + [c for c in kept if c is not chosen]
    others = [c.num_inliers for c in result.candidates[1:] if c.num_inliers > 0]
    result.runner_up_ratio = (chosen.num_inliers / max(others) if others
                              else float('inf'))
    return Settlement(chosen, chosen is not best, overlap, violation[id(chosen)],
                      [o for c, o in plausible if c is not chosen], len(result.candidates) == 1)
