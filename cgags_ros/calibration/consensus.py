"""
The pose the frames agree on: hypotheses from every frame, judged on every frame.

Each frame's ranked candidates (the pipeline's, on that frame alone) are hypotheses. A
wrong candidate is a coincidence of one scene (a symmetric street, a repeated facade);
the extrinsic is the same in every frame. So each distinct hypothesis is refined jointly
over all frames (:func:`.joint.refine`) and scored by its joint overlap: the sum over the
frames of the smaller of the child-side and parent-side shares of points within the
refinement distance. The best scoring one is the estimate.

A frame agrees with a pose when (1) refining the pose on that frame alone moves the
frame's overlapping child points, along the parent's normals, by at most
``AGREEMENT_SHIFT`` voxel sizes RMS (motion along directions the frame does not
constrain is free), and (2) none of the frame's own candidates, refined on it, overlaps
``AMBIGUITY_RATIO`` times better. A contender is a distinct pose scoring above
1/``AMBIGUITY_RATIO`` of the best that every frame agrees with too: the set is then
ambiguous.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from . import joint
from .frames import Evidence
from .joint import FrameClouds
from .pooled import pooled_candidates
from .result import FrameReport
from ..config.calibration import CalibrationConfig
from ..geometry import rotation_error_deg, translation_error
from ..pipeline.candidates import distinct


SCREEN_POINTS = 1500  # child points per frame while hypotheses are compared
AGREEMENT_SHIFT = 0.15  # a frame agrees when the pose moves on it by at most this (voxels RMS)
AMBIGUITY_RATIO = 1.5  # a pose scoring within this factor of the best contends (module doc)


@dataclasses.dataclass
class Hypothesis:
    """
    A pose refined jointly over the frames, with its overlap on each.

    :ivar transform: 4x4 parent <- child, metres.
    :ivar origins: (frame index, candidate rank) of the candidates that led here (frame
        index -1: the pooled search, :mod:`.pooled`).
    :ivar overlaps: per frame, min(child share, parent share) within the distance.
    :ivar fitness: per frame, the child share.
    """

    transform: np.ndarray
    origins: list[tuple[int, int]]
    overlaps: list[float]
    fitness: list[float]

    @property
    def score(self) -> float:
        return float(sum(self.overlaps))


def distance(cfg: CalibrationConfig) -> float:
    """Return the correspondence distance of the refinement, metres (as the pipeline's)."""
    return cfg.pipeline.refine.max_correspondence_distance_factor * cfg.pipeline.voxel_size


def hypotheses(evidence: list[Evidence], cfg: CalibrationConfig) -> list[Hypothesis]:
    """Return the distinct jointly refined hypotheses of ``evidence``, best score first."""
    clouds = [e.clouds for e in evidence]
    # Telling hypotheses apart needs far fewer points than the final estimate.
    light = [joint.thinned(c, SCREEN_POINTS) for c in clouds]
    d = distance(cfg)
    seeds: list[tuple[np.ndarray, list[tuple[int, int]], float]] = []
    for i, e in enumerate(evidence):
        tau = float(e.result.inlier_threshold)
        for rank, T in enumerate(e.candidates):
            same = next((s for s in seeds if not distinct(T, s[0], cfg.pipeline)), None)
            if same is None:
                seeds.append((T, [(i, rank)], tau))
            else:
                same[1].append((i, rank))
    for rank, (T, tau) in enumerate(pooled_candidates(evidence, cfg.pipeline)):
        same = next((s for s in seeds if not distinct(T, s[0], cfg.pipeline)), None)
        if same is None:
            seeds.append((T, [(-1, rank)], tau))
        else:
            same[1].append((-1, rank))
    found: list[Hypothesis] = []
    for T0, origins, tau in seeds:
        stages = [tau, d] if tau > d else [d]
        T = joint.refine(light, T0, stages, joint.ITERATIONS)
        same = next((h for h in found if not distinct(T, h.transform, cfg.pipeline)), None)
        if same is not None:
            same.origins += origins
            continue
        shares = [joint.overlap(c, T, d) for c in clouds]
        found.append(Hypothesis(T, origins, [min(a, b) for a, b in shares],
                                [a for a, _ in shares]))
    found.sort(key=lambda h: -h.score)
    if found:  # the winner on every point
        best = found[0]
        best.transform = joint.refine(clouds, best.transform, [d], joint.ITERATIONS)
    return found


def shift(clouds: FrameClouds, T: np.ndarray, d: float,
          iterations: int) -> tuple[float, np.ndarray]:
    """
    Return (RMS normal shift in metres, the single-frame refinement) of ``T`` on one frame.

    The shift is that of the frame's paired points (:class:`.joint.Pairs`), moved with the
    child, between ``T`` and ``T`` refined on this frame alone, along their normals.
    """
    T_k = joint.refine([clouds], T, [d], iterations)
    p = joint.pairs(clouds, T, d)
    if len(p.residuals) == 0:
        return float('inf'), T_k
    delta = (p.arms @ (T_k[:3, :3] @ T[:3, :3].T).T + T_k[:3, 3]) - (p.arms + T[:3, 3])
    along = np.einsum('ij,ij->i', p.normals, delta)
    return float(np.sqrt(np.mean(along ** 2))), T_k


def verdict(index: int, e: Evidence, T: np.ndarray, cfg: CalibrationConfig) -> FrameReport:
    """Return frame ``index``'s report on the joint pose ``T`` (agreement, see module doc)."""
    report = FrameReport(name=e.frame.name or f'frame {index}',
                         time_offset_s=e.frame.time_offset_s,
                         single_frame_valid=bool(e.result.valid),
                         single_frame_reason=e.result.reason)
    report.candidate_rank = next((r for r, c in enumerate(e.candidates)
                                  if not distinct(c, T, cfg.pipeline)), -1)
    if e.clouds is None:
        report.reason = f'unusable: {e.result.reason}'
        return report
    d, v = distance(cfg), cfg.pipeline.voxel_size
    report.shift_m, report.transform = shift(e.clouds, T, d, joint.ITERATIONS)
    ahead, back = joint.overlap(e.clouds, report.transform, d)
    report.fitness, report.overlap = ahead, min(ahead, back)
    limit = AGREEMENT_SHIFT * v
    if not report.shift_m <= limit:
        report.reason = (
            f'refined on this frame alone, the joint pose moves by '
            f'{rotation_error_deg(report.transform, T):.2f} deg / '
            f'{translation_error(report.transform, T):.3f} m (its surfaces by '
            f'{report.shift_m:.3f} m RMS > {limit:.3f} m): the frame fits another pose')
        return report
    own = _best_own(e, cfg)
    if own is not None and distinct(own[0], report.transform, cfg.pipeline) \
            and own[1] > AMBIGUITY_RATIO * report.overlap:
        report.reason = (
            f'its own pose ({rotation_error_deg(own[0], T):.1f} deg / '
            f'{translation_error(own[0], T):.2f} m from the joint one) overlaps '
            f'{own[1]:.3f} against {report.overlap:.3f} (more than '
            f'{AMBIGUITY_RATIO:g} times better)')
        report.transform = own[0]
        return report
    report.agrees = True
    return report


def _best_own(e: Evidence, cfg: CalibrationConfig) -> tuple[np.ndarray, float] | None:
    """Return the frame's own best-overlapping candidate, refined on it, and its overlap."""
    d = distance(cfg)
    tau = float(e.result.inlier_threshold)
    best = None
    for T0 in e.candidates:
        T = joint.refine([e.clouds], T0, [tau, d] if tau > d else [d], joint.ITERATIONS)
        ahead, back = joint.overlap(e.clouds, T, d)
        if best is None or min(ahead, back) > best[1]:
            best = (T, min(ahead, back))
    return best


def contender(found: list[Hypothesis], evidence: list[Evidence],
              cfg: CalibrationConfig) -> Hypothesis | None:
    """Return a distinct hypothesis the frames agree on about as well as the best, or None."""
    best, d = found[0], distance(cfg)
    limit = AGREEMENT_SHIFT * cfg.pipeline.voxel_size
    for h in found[1:]:
        if h.score * AMBIGUITY_RATIO <= best.score:
            break  # sorted: the rest score lower still
        if all(e.clouds is not None and shift(e.clouds, h.transform, d, joint.ITERATIONS)[0]
               <= limit for e in evidence):
            return h
    return None


def largest_agreeing(evidence: list[Evidence], T: np.ndarray,
                     cfg: CalibrationConfig) -> np.ndarray:
    """
    Return the pose of the largest set of frames that agree, refined over that set only.

    ``T`` was refined over every frame, so one frame that fits another pose pulls it off
    the others'. Each frame's own refinement of ``T`` is a candidate; the one the most
    frames agree with (by the shift test) wins, and only those frames refine it: frames
    that disagree are left out, never averaged in.
    """
    d, limit = distance(cfg), AGREEMENT_SHIFT * cfg.pipeline.voxel_size
    anchors = [shift(e.clouds, T, d, joint.ITERATIONS)[1] for e in evidence]
    best: tuple[int, list[FrameClouds], np.ndarray] | None = None
    for anchor in anchors:
        members = [e.clouds for e in evidence
                   if shift(e.clouds, anchor, d, joint.ITERATIONS)[0] <= limit]
        if best is None or len(members) > best[0]:
            best = (len(members), members, anchor)
    if not best[1]:
        return T
    return joint.refine(best[1], best[2], [d], joint.ITERATIONS)
