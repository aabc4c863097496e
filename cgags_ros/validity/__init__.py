"""
Validity: the one place that decides whether an estimate is trusted, and why not.

The core (:mod:`cgags_ros.registration`), the pipeline's gates (:mod:`cgags_ros.pipeline.gates`)
and the node measure; the functions here compare those measurements with their settings and
return a :class:`~cgags_ros.refusal.Refusal` (None when the estimate passes), the first
check that fails in a fixed order. Nothing here measures: the measurements are the results'
own fields (the protocols below name the ones each decision reads), so a refusal can always
be traced to numbers the result reports.

Order, as a pair goes through the pipeline: a cloud that is a line; the core's outcome (no
estimate, too few inliers, a collinear consensus, chance level or a distinct alternative, a
tilt in 4-DoF mode: :mod:`.consensus`); then, on the refined estimate, too little shared
surface (or an unalike one), chance-level inliers, a degenerate axis, low fitness, a
free-space violation, a tilt, surfaces in the free space both sensors saw (:mod:`.shared`);
an ambiguity among the candidates overrides all but the shared surface (also said of
the core's ambiguity or chance level). A pose found in one place of a map is then also
ambiguous when the whole map's matches back it no more than chance and another pose more
(:func:`elsewhere_refusal`). The node adds stricter guards (:func:`quality_refusal`).

Ambiguity is decided here only: the stages that propose other poses (the correspondences'
candidates, the estimate's twins: :mod:`cgags_ros.pipeline.settle`) measure them, and the
functions of the ambiguity section below say what the measures mean.
"""

from __future__ import annotations

from typing import Any, Protocol, Sequence

from .consensus import Consensus, tilt_refusal
from .shared import (met_surface_refusal, said_over_ambiguity,  # noqa: F401 (the API)
                     seen_through_refusal, Shared, shared_surface_refusal, unalike)
from .. import fitted
from ..config.node import NodeConfig
from ..config.pipeline import PipelineConfig
from ..geometry import rotation_error_deg, translation_error
from ..refusal import Refusal, RefusalCode

# An estimate the correspondences did not settle (a collinear consensus, or a candidate
# within the ambiguity ratio) is trusted only below this share of the free-space bound:
# nothing but the overlap's geometry vouches for it (docs/ablation.md, unsettled estimates).
FREE_SPACE_SETTLE_FACTOR = 0.5

Code = RefusalCode


class Overlap(Protocol):
    """What the gates measured of an estimate's overlap alone (a ``PipelineResult``'s fields)."""

    observability: float
    fitness: float
    free_space_violation: float
    tilt_deg: float  # 4-DoF only (else NaN)


class Trusted(Protocol):
    """An estimate's calibrated confidence (:mod:`cgags_ros.pipeline.confidence`)."""

    confidence: float


class Estimate(Consensus, Overlap, Shared, Protocol):
    """What the gates measured of a refined estimate (a ``PipelineResult``'s fields)."""

    num_correspondences: int
    num_hypotheses: int
    chance_inliers: float
    chance_bound: float
    ambiguous: bool
    runner_up_ratio: float
    candidates: Sequence[Any]


# --- the pipeline --------------------------------------------------------------------------

def line_cloud_refusal(cross_spread: float, name: str, voxel_size: float) -> Refusal | None:
    """
    Return why a downsampled cloud is a line, or None.

    ``cross_spread``: its RMS spread across its main axis (metres). Below one voxel the
    rotation about that axis can never be determined, so the core is not even asked.
    """
    if cross_spread >= voxel_size:
        return None
    return Refusal(Code.COLLINEAR, (
        f'degenerate {name} cloud: it is (nearly) a line (spread across its axis '
        f'{cross_spread:.3g} m < voxel size {voxel_size:g} m); the rotation about it is '
        'undetermined'))


def unsettled(core: Consensus, cfg: PipelineConfig) -> bool:
    """
    Tell whether a core refusal is left to the gates: only its consensus was collinear.

    Such a consensus leaves the rotation about its line to the correspondences' noise, but
    the refinement fits the whole overlap, whose geometry may well fix that rotation: it is
    refined and judged by the gates on the overlap (observability, free space under a
    tighter bound, chance inliers, ambiguity) instead.
    """
    return (core.refusal is not None and core.refusal.code is Code.COLLINEAR
            and core.num_inliers >= cfg.core.min_inliers
            and cfg.core.motion_model != '4dof' and cfg.refine.method != 'none')


def free_space_limit(cfg: PipelineConfig, unsettled: bool = False) -> float:
    """Return the free-space bound: tighter for an estimate the correspondences did not settle."""
    limit = cfg.gates.max_free_space_violation
    return limit * FREE_SPACE_SETTLE_FACTOR if unsettled and limit < 1 else limit


def gate_refusal(e: Estimate, cfg: PipelineConfig, unsettled: bool = False) -> Refusal | None:
    """Return why the refined estimate must not be trusted, or None when every gate passes."""
    if surface := met_surface_refusal(e, cfg):
        return surface
    if cfg.gates.significance > 0 and not e.num_inliers > e.chance_bound:
        return Refusal(Code.CHANCE_LEVEL, (
            f'{e.num_inliers} inliers of {e.num_correspondences} correspondences is no better '
            f'than chance (random pairing gives {e.chance_inliers:.2g} per estimate; the best '
            f'of {max(e.num_hypotheses, 1)} hypotheses reaches {e.chance_bound:.0f}): the '
            'clouds probably do not overlap'))
    return overlap_refusal(e, cfg, unsettled) or seen_through_refusal(e)


def overlap_refusal(e: Overlap, cfg: PipelineConfig, unsettled: bool = False) -> Refusal | None:
    """
    Return why an estimate must not be trusted on its overlap alone, or None.

    The gates that need no correspondences (degenerate axis, fitness, free space, tilt), so
    that a pose refined from a prediction is judged as a global one is.
    """
    gates = cfg.gates
    distance = cfg.refine.max_correspondence_distance_factor * cfg.voxel_size
    limit = free_space_limit(cfg, unsettled)
    if gates.min_observability > 0 and not e.observability >= gates.min_observability:
        return Refusal(Code.DEGENERATE_AXIS, (
            'the overlap constrains some motion only weakly '
            f'(observability {e.observability:.2g} < {gates.min_observability:g}; e.g. '
            'plane, line, sphere or cylinder); the pose along it is arbitrary'))
    if gates.min_fitness > 0 and not e.fitness >= gates.min_fitness:
        return Refusal(Code.LOW_FITNESS, (
            f'fitness {e.fitness:.3f} < gates.min_fitness {gates.min_fitness:g}: too few '
            f'source points lie within {distance:.3g} m of the target after alignment'))
    if e.free_space_violation > limit:  # NaN: not measured
        return Refusal(Code.FREE_SPACE, (
            f'{100 * e.free_space_violation:.0f} % of the aligned '
            "points that meet the other cloud's view lie in front of its observed surface "
            f'(> {limit:g}, gates.max_free_space_violation, times '
            f'{FREE_SPACE_SETTLE_FACTOR:g} for an unsettled estimate): the pose stacks '
            'surfaces where a sensor saw free space'))
    return tilt_refusal(e.tilt_deg, cfg.core.max_tilt_deg,
                        'a 6-DoF point-to-plane step over the overlap', 'core.max_tilt_deg',
                        "core.motion_model='6dof'")


def tracking_refusal(correction_deg: float, correction_m: float, fitness: float,
                     last_fitness: float, cfg: PipelineConfig) -> Refusal | None:
    """
    Return why a pose refined from a prediction is no tracked pose, or None.

    Smooth motion moves little and changes the overlap little, a jump does neither: the
    refinement must not have moved the prediction by more than ``tracking.max_correction_*``
    (``correction_deg``, ``correction_m``), and ``fitness`` must be at least
    ``tracking.min_fitness_ratio`` times the last accepted pose's.
    """
    track = cfg.tracking
    limit = track.max_correction_factor * cfg.voxel_size
    if not (correction_deg <= track.max_correction_deg and correction_m <= limit):
        return Refusal(Code.TRACKING_LOST, (
            f'the refinement moved the predicted pose by {correction_m:.3g} m and '
            f'{correction_deg:.3g} deg (> tracking.max_correction_factor {limit:.3g} m or '
            f'tracking.max_correction_deg {track.max_correction_deg:g} deg): a jump, not a '
            'tracked motion'))
    if not fitness >= track.min_fitness_ratio * last_fitness:
        return Refusal(Code.TRACKING_LOST, (
            f'fitness {fitness:.3f} < tracking.min_fitness_ratio times the last '
            f"pose's {last_fitness:.3f}: the prediction converged where far fewer points "
            'fit (a jump or a changed scene)'))
    return None


def confidence_refusal(e: Trusted, min_confidence: float) -> Refusal | None:
    """Return why an estimate's calibrated confidence is too low to call it valid, or None."""
    if min_confidence <= 0 or e.confidence >= min_confidence:
        return None
    return Refusal(Code.LOW_CONFIDENCE, (
        f'P(right) {e.confidence:.2f} < min_confidence '
        f'{min_confidence:g}: estimates measured like this one (inliers against chance, '
        'overlap, free space, rivals) are too often wrong'))


def uncertainty_refusal(sigma: float, cfg: PipelineConfig) -> Refusal | None:
    """
    Return why a pose is too uncertain to act on, or None.

    ``sigma``: the position sigma (metres) along the covariance's loosest direction. Above
    ``gates.max_position_sigma`` voxel sizes the covariance itself says the pose may be
    metres off along some direction: no robot can use it, however well the rest fits.
    """
    bound = cfg.gates.max_position_sigma * cfg.voxel_size
    if bound <= 0 or sigma <= bound:
        return None
    return Refusal(Code.UNCERTAIN, (
        f'too uncertain to use: the position sigma along the loosest direction is '
        f'{sigma:.3g} m (> gates.max_position_sigma {cfg.gates.max_position_sigma:g} voxels, '
        f'{bound:.3g} m): the overlap leaves the pose loose there, or the confidence leaves '
        'room for a wrong pose; the covariance says which'))


# --- ambiguity: a distinct pose about as good ----------------------------------------------

class Twin(Protocol):
    """What a twin measured where it settled (a :class:`~cgags_ros.pipeline.settle.Settled`)."""

    fitness: float
    free_space: float  # the free-space violation (NaN: not measured)


class Settlement(Protocol):
    """What settling an ambiguous estimate's candidates measured (:mod:`~.pipeline.candidates`)."""

    overlap: float  # the chosen pose's
    free_space: float  # the chosen pose's violation
    others: Sequence[float]  # the other plausible candidates' overlaps
    alone: bool  # no distinct candidate is left: every one settled onto the chosen pose


def outnumbered(runner_up_ratio: float, cfg: PipelineConfig) -> bool:
    """Tell whether the correspondences support a distinct candidate nearly as well (inf: none)."""
    return runner_up_ratio < cfg.gates.ambiguity_ratio


def passes_free_space(violation: float, cfg: PipelineConfig) -> bool:
    """Tell whether a pose passes the free-space gate (NaN: the gate does not apply)."""
    return not violation > cfg.gates.max_free_space_violation


def still_ambiguous(s: Settlement, cfg: PipelineConfig) -> bool:
    """
    Tell whether the candidates, settled on the geometry, leave the estimate ambiguous.

    Settled only when no other plausible candidate's overlap is above the chosen one's /
    ``ambiguity_ratio`` and the chosen one clearly passes the free-space test (the tighter
    bound of an unsettled estimate); when every candidate settled onto it, nothing distinct
    is left to be confused with.
    """
    return not s.alone and (any(o * cfg.gates.ambiguity_ratio > s.overlap for o in s.others)
                            or s.free_space > free_space_limit(cfg, unsettled=True))


def settled_apart(rotation_deg: float, translation_m: float, voxel_size: float,
                  min_rotation_deg: float, apart: float = fitted.TWIN_APART) -> bool:
    """Tell whether a twin settled this far from the estimate is another pose, not it."""
    return rotation_deg > min_rotation_deg or translation_m > apart * voxel_size


def fits_as_well(fitness: float, estimate_fitness: float,
                 ratio: float = fitted.TWIN_OVERLAP_RATIO) -> bool:
    """Tell whether a twin's fitness is at least ``1 / ratio`` of the estimate's."""
    return fitness * ratio >= estimate_fitness


def clear_of_free_space(violation: float, limit: float = fitted.TWIN_MAX_VIOLATION) -> bool:
    """Tell whether a twin stacks few enough surfaces in free space (NaN: not measured)."""
    return not violation > limit


def plausible_twin(apart_deg: float, apart_m: float, twin: Twin, estimate_fitness: float,
                   voxel_size: float, min_rotation_deg: float) -> bool:
    """
    Tell whether a twin settled ``apart_deg`` / ``apart_m`` from the estimate makes it ambiguous.

    It settled away from the estimate, fits about as well and does not stack surfaces where a
    sensor saw free space: the tests in that order, each measure read (and so taken) only when
    the test before passed.
    """
    return (settled_apart(apart_deg, apart_m, voxel_size, min_rotation_deg)
            and fits_as_well(twin.fitness, estimate_fitness)
            and clear_of_free_space(twin.free_space))


def ambiguity_refusal(e: Estimate, cfg: PipelineConfig) -> Refusal | None:
    """Return why the estimate is ambiguous among its candidates, or None when it is not."""
    if not e.ambiguous:
        return None
    best, runner = e.candidates[0], e.candidates[1]
    moved = translation_error(best.transform, runner.transform)
    turned = rotation_error_deg(best.transform, runner.transform)
    geometry = (' and, refined, overlaps about as well' if cfg.gates.settle_candidates
                and cfg.refine.method != 'none' else '')
    return Refusal(Code.AMBIGUOUS, (
        f'a distinct pose ({turned:.0f} deg, {moved:.2f} m away) has '
        f'{runner.num_inliers} inliers against {best.num_inliers} of the best (within '
        f'gates.ambiguity_ratio {cfg.gates.ambiguity_ratio:g}){geometry}; the scene looks '
        'alike in both poses'))


def elsewhere_refusal(support: int, bound: float, elsewhere: int, turned_deg: float,
                      moved_m: float, cfg: PipelineConfig) -> Refusal | None:
    """
    Return why a pose found in one place of a map is ambiguous with another, or None.

    A place's registration sees no other place. The scan's keypoints matched against the
    whole map support its pose with ``support`` matches, no more than chance gives when at
    most ``bound`` (:func:`~cgags_ros.pipeline.gates.chance_bound` of one pose at
    ``gates.significance``), and a distinct pose, ``turned_deg`` and ``moved_m`` from it,
    with ``elsewhere``: a pose the whole map backs no more than chance while it backs
    another more is a look-alike surface fitted in the wrong place, which passes every gate
    of its own (docs/maps.md, the judgement).
    """
    if support > bound or elsewhere <= support:
        return None
    return Refusal(Code.AMBIGUOUS, (
        f"the whole map's matches put the scan elsewhere: its pose has {support} of them, "
        f'no more than chance gives ({bound:g} at gates.significance '
        f'{cfg.gates.significance:g}), a distinct pose ({turned_deg:.0f} deg, {moved_m:.2f} m '
        f'away) {elsewhere}; the places look alike'))


# --- the relocalizer over a few scans -----------------------------------------------------

def unexplained_refusal(misses: Sequence[int]) -> Refusal:
    """Return the refusal of a best hypothesis that does not explain the scans ``misses``."""
    return Refusal(Code.UNEXPLAINED, (
        f'no pose explains every scan (the best misses scan(s) '
        f'{", ".join(map(str, misses))}): the odometry contradicts the scans, or the '
        'place is not in the map'))


def sequence_ambiguity_refusal(scans: int, turned_deg: float, moved_m: float) -> Refusal:
    """Return the refusal of a distinct pose that explains every scan about as well."""
    return Refusal(Code.AMBIGUOUS, (
        f'a distinct pose ({turned_deg:.0f} deg, {moved_m:.2f} m away) explains every '
        f'one of {scans} scans about as well'))


def more_scans_refusal(scans: int, min_scans: int) -> Refusal | None:
    """Return why ``scans`` scans cannot confirm yet (fewer than ``min_scans``), or None."""
    if scans >= min_scans:
        return None
    return Refusal(Code.MORE_SCANS, f'{scans} of the {min_scans} scans a confirmation needs')


# --- the node ------------------------------------------------------------------------------

def quality_refusal(e: Estimate, cfg: NodeConfig) -> Refusal | None:
    """
    Return why ``e`` is no confident pose for an initial pose, or None.

    Valid and unambiguous, then the node's stricter guards: at least
    ``relocalization.min_inliers`` inliers, a best/runner-up candidate ratio of at least
    ``relocalization.min_ratio`` and a fitness of at least ``relocalization.min_fitness``.
    """
    if e.ambiguous:
        return Refusal(Code.AMBIGUOUS, e.reason)
    if e.refusal is not None:
        return e.refusal
    if e.num_inliers < cfg.relocalization.min_inliers:
        return Refusal(Code.FEW_INLIERS, (
            f'{e.num_inliers} inliers < relocalization.min_inliers '
            f'{cfg.relocalization.min_inliers}'))
    ratio = float(e.runner_up_ratio)
    if ratio < cfg.relocalization.min_ratio:
        return Refusal(Code.LOW_RATIO, (
            f'best/runner-up ratio {ratio:.2f} < relocalization.min_ratio '
            f'{cfg.relocalization.min_ratio:g}'))
    fitness = float(e.fitness)
    if fitness < cfg.relocalization.min_fitness:
        return Refusal(Code.LOW_FITNESS, (
            f'fitness {fitness:.3f} < relocalization.min_fitness '
            f'{cfg.relocalization.min_fitness:g}'))
    return None
