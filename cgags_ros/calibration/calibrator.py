"""
Extrinsic calibration from several synchronized frames: take frames, solve, say when done.

:class:`Calibrator` takes frames one at a time (:meth:`Calibrator.add`); each runs the
pipeline once. :meth:`Calibrator.solve` finds the pose the frames agree on
(:mod:`.consensus`), refines it once over every agreeing frame's overlap
(:mod:`.joint`), and measures its covariance and observability (:mod:`.uncertainty`).
Refused, with the reason and never as a pose to use: no frame with a candidate, frames
that disagree (fewer than ``min_agreement`` agree), motions the frames leave unconstrained,
and a second pose the frames agree on about as well.
"""

from __future__ import annotations

import time
from typing import Iterable

import numpy as np

from . import consensus, joint, uncertainty
from .frames import Evidence, Frame, gather
from .result import CalibrationResult
from ..config.calibration import CalibrationConfig
from ..geometry import rotation_error_deg, translation_error
from ..refusal import Refusal, RefusalCode


class Calibrator:
    """
    Accumulates frames of one sensor pair and solves for the extrinsic parent <- child.

    :param config: :class:`CalibrationConfig` (defaults when None).
    :param parent_frame, child_frame: frame ids, carried into the result's outputs.
    """

    def __init__(self, config: CalibrationConfig | None = None, *, parent_frame: str = 'parent',
                 child_frame: str = 'child'):
        self.config = config or CalibrationConfig()
        self.parent_frame, self.child_frame = parent_frame, child_frame
        self.evidence: list[Evidence] = []
        self.result: CalibrationResult | None = None
        self._seconds = 0.0

    def add(self, frame: Frame) -> Evidence:
        """Run the pipeline on one frame and keep its evidence."""
        start = time.perf_counter()
        e = gather(frame, self.config.pipeline)
        self.evidence.append(e)
        self._seconds += time.perf_counter() - start
        return e

    @property
    def done(self) -> bool:
        """Whether to stop taking frames: ``max_frames`` taken or the estimate converged."""
        return (len(self.evidence) >= self.config.max_frames
                or (self.result is not None and self.result.converged))

    def solve(self) -> CalibrationResult:
        """Solve over every frame taken so far (see the module doc); remember the result."""
        start = time.perf_counter()
        result = solve(self.evidence, self.config)
        result.parent_frame, result.child_frame = self.parent_frame, self.child_frame
        result.converged = bool(result.valid and len(self.evidence) >= self.config.min_frames
                                and _last_frame_within_std(self.evidence, result,
                                                           self.config))
        self._seconds += time.perf_counter() - start
        result.seconds = self._seconds
        self.result = result
        return result


def calibrate(frames: Iterable[Frame], config: CalibrationConfig | None = None, *,
              parent_frame: str = 'parent', child_frame: str = 'child') -> CalibrationResult:
    """
    Calibrate from ``frames``, taken in order until converged or ``max_frames``.

    The estimate is solved after every frame from ``min_frames`` on; it has converged when
    the last frame moved it by less than one standard deviation on every axis.
    """
    cal = Calibrator(config, parent_frame=parent_frame, child_frame=child_frame)
    for frame in frames:
        cal.add(frame)
        if len(cal.evidence) >= cal.config.min_frames:
            cal.solve()
        if cal.done:
            break
    return cal.result if cal.result is not None else cal.solve()


def solve(evidence: list[Evidence], cfg: CalibrationConfig) -> CalibrationResult:
    """Solve for the extrinsic over ``evidence`` (see the module doc); never raises on data."""
    result = CalibrationResult()
    usable = [e for e in evidence if e.clouds is not None and e.candidates]
    if not usable:
        result.frames = [consensus.verdict(i, e, np.eye(4), cfg) for i, e in enumerate(evidence)]
        for f in result.frames:
            f.agrees, f.reason = False, f.reason or 'no candidate pose'
        result.refusal = Refusal(RefusalCode.NO_ESTIMATE, 'no frame gave a candidate pose: '
                                 + '; '.join(f'{f.name}: {f.single_frame_reason}'
                                             for f in result.frames))
        scans = [e.clouds for e in evidence if e.clouds is not None]
        if scans:  # say what the scenes themselves leave free, if anything
            result.observability, result.unobservable = _scene_observability(scans, cfg)
            free = _observability_refusal(result, cfg)
            if free:
                result.refusal = Refusal(free.code, f'{free.message} (judged on the parent '
                                         f'scans: {result.reason})')
        return result
    found = consensus.hypotheses(usable, cfg)
    T = found[0].transform
    result.frames = [consensus.verdict(i, e, T, cfg) for i, e in enumerate(evidence)]
    if not all(f.agrees for f in result.frames):
        T = consensus.largest_agreeing(usable, T, cfg)
        result.frames = [consensus.verdict(i, e, T, cfg) for i, e in enumerate(evidence)]
    agreeing = [e for e, f in zip(evidence, result.frames) if f.agrees]
    clouds = [e.clouds for e in (agreeing or usable)]
    d = consensus.distance(cfg)
    if agreeing and len(agreeing) < len(evidence):  # the others never enter the estimate
        T = joint.refine(clouds, T, [d], joint.ITERATIONS)
    result.transform = T
    _uncertainty(result, clouds, agreeing, cfg)
    result.refusal = (_observability_refusal(result, cfg) or _agreement_refusal(result, cfg)
                      or _contender_refusal(found, usable, cfg))
    return result


def _uncertainty(result: CalibrationResult, clouds: list, agreeing: list[Evidence],
                 cfg: CalibrationConfig) -> None:
    """Set the covariance, standard deviations and observability of ``result.transform``."""
    T, d = result.transform, consensus.distance(cfg)
    H, ssr, count = joint.information(clouds, T, d)
    result.num_pairs = count
    result.rms_m = float(np.sqrt(ssr / count)) if count else float('nan')
    arms = np.concatenate([joint.pairs(c, T, d).arms for c in clouds])
    centre = arms.mean(axis=0) if len(arms) else np.zeros(3)
    radius = float(np.sqrt(np.mean(np.sum((arms - centre) ** 2, axis=1)))) \
        if len(arms) else 0.0
    result.observability, result.unobservable = uncertainty.unobservable(
        H, centre, radius, uncertainty.MIN_OBSERVABILITY)
    deviations, covariances = [], []
    for e, f in zip(agreeing, [f for f in result.frames if f.agrees]):
        deviations.append(joint.difference(f.transform, T))
        covariances.append(uncertainty.covariance(*joint.information([e.clouds], T, d)))
    result.birge_ratio = uncertainty.birge_ratio(deviations, covariances)
    result.covariance = result.birge_ratio * uncertainty.covariance(H, ssr, count)
    result.std = uncertainty.std_devs(result.covariance)


def _scene_observability(scans: list, cfg: CalibrationConfig) -> tuple[float, list[str]]:
    """
    Return :func:`.uncertainty.unobservable` of the parent scans' own surfaces.

    With no pose there is no overlap to judge; the overlap is part of the parent's scene,
    so a motion the parent scans leave free is free in any overlap.
    """
    points = np.concatenate([c.parent for c in scans])
    normals = np.concatenate([c.parent_normals for c in scans])
    keep = np.isfinite(normals[:, 0])
    points, normals = points[keep], normals[keep]
    if len(points) < 6:
        return 0.0, ['every translation', 'every rotation']
    centre = points.mean(axis=0)
    J = np.hstack([normals, np.cross(points, normals)])  # about the parent origin
    radius = float(np.sqrt(np.mean(np.sum((points - centre) ** 2, axis=1))))
    return uncertainty.unobservable(J.T @ J, centre, radius, uncertainty.MIN_OBSERVABILITY)


def _observability_refusal(result: CalibrationResult,
                           cfg: CalibrationConfig) -> Refusal | None:
    if not result.unobservable:
        return None
    return Refusal(RefusalCode.DEGENERATE_AXIS, (
        f"not observable: {'; '.join(result.unobservable)} (parent frame): the scenes do "
        f'not constrain it (observability {result.observability:.2g} < '
        f'{uncertainty.MIN_OBSERVABILITY:g}; a plane leaves the translations in it and the '
        'rotation about its normal free, a corridor the translation along it); add frames '
        'of a richer scene'))


def _agreement_refusal(result: CalibrationResult, cfg: CalibrationConfig) -> Refusal | None:
    n, total = result.num_agreeing, len(result.frames)
    if n and n >= cfg.min_agreement * total:
        if n >= cfg.min_agreeing_frames:
            return None
        alone = [f for f in result.frames if f.agrees]
        if n == 1 and alone[0].single_frame_valid and alone[0].candidate_rank == 0:
            return None  # one frame, and the pipeline's own gates accept that very pose
        return Refusal(RefusalCode.FRAMES_DISAGREE, (
            f'too little agreement: {n} frame(s) agree (min_agreeing_frames '
            f'{cfg.min_agreeing_frames}) and the pipeline alone did not accept the pose '
            f'({alone[0].single_frame_reason or "another pose"}); take more frames'))
    return Refusal(RefusalCode.FRAMES_DISAGREE, (
        f'{n} of {total} frames agree on the pose (min_agreement '
        f'{cfg.min_agreement:g}); '
        + '; '.join(f'{f.name}: {f.reason}' for f in result.frames if not f.agrees)))


def _contender_refusal(found: list, usable: list[Evidence],
                       cfg: CalibrationConfig) -> Refusal | None:
    other = consensus.contender(found, usable, cfg)
    if other is None:
        return None
    best = found[0]
    return Refusal(RefusalCode.AMBIGUOUS, (
        f'every frame also agrees with a pose '
        f'{rotation_error_deg(other.transform, best.transform):.1f} deg / '
        f'{translation_error(other.transform, best.transform):.2f} m away (joint overlap '
        f'{other.score:.3f} against {best.score:.3f}, within '
        f'{consensus.AMBIGUITY_RATIO:g} times); the scenes look alike in both poses'))


def _last_frame_within_std(evidence: list[Evidence], result: CalibrationResult,
                           cfg: CalibrationConfig) -> bool:
    """
    Whether the estimate without the last frame is within one standard deviation of it.

    The estimate without it is the joint refinement, from ``result.transform``, over the
    other agreeing frames (the search for the pose is not repeated).
    """
    agreeing = [e.clouds for e, f in zip(evidence[:-1], result.frames[:-1]) if f.agrees]
    if not agreeing or not result.frames[-1].agrees:
        return False
    before = joint.refine(agreeing, result.transform, [consensus.distance(cfg)],
                          joint.ITERATIONS)
    delta = np.abs(joint.difference(result.transform, before))
    return bool(np.all(delta <= np.sqrt(np.diag(result.covariance))))
