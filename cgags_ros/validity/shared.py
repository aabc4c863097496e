"""
Whether two clouds share a surface under an estimate: the ``no_shared_surface`` decision.

Part of :mod:`cgags_ros.validity`, the one place that decides. Clouds of two different
places still meet under some pose; what they share then is small, looks unalike, or puts
each place's walls where the other's sensor saw free space (docs/no_overlap.md).
"""

from __future__ import annotations

from typing import Protocol

from ..config.pipeline import PipelineConfig
from ..refusal import Refusal, RefusalCode

Code = RefusalCode

# The surfaces a pose may put in free space as both sensors see them (the share of
# :func:`cgags_ros.pipeline.free_space.free_space_surface`), chosen as the no-shared-surface
# bounds were, on right poses of low overlap (docs/no_overlap.md).
MAX_FREE_SPACE_SURFACE = 0.04
# It is judged on thin overlaps only: a pose under which the clouds share at least this share
# of both their surfaces shows one place however the free space reads (clouds not in their
# sensors' frames, object scans, read free space from a viewpoint no sensor had), and no
# estimate between different places overlaps as much (docs/no_overlap.md).
THIN_OVERLAP = 0.7


class Shared(Protocol):
    """What the gates measured of the surface an estimate makes the clouds share (or NaN)."""

    shared_area: float  # square metres
    descriptor_ratio: float  # its pairs' descriptor distance over a random pairing's
    free_space_surface: float  # share put in free space as surfaces both sensors see
    overlap: float  # the smaller side's share of points with a neighbour in the other
    observability: float
    voxel_size: float


def unalike(descriptor_ratio: float, observability: float, cfg: PipelineConfig) -> bool:
    """
    Tell whether an overlap's descriptors differ as different surfaces' do (NaN: no).

    ``descriptor_ratio`` above ``gates.max_descriptor_ratio``, unless the overlap is
    degenerate (``observability`` below ``gates.min_observability``): there every descriptor
    looks alike, or none does.
    """
    gates = cfg.gates
    return (0 < gates.max_descriptor_ratio < descriptor_ratio
            and observability >= gates.min_observability)


def shared_surface_refusal(e: Shared, cfg: PipelineConfig) -> Refusal | None:
    """
    Return why the clouds share no surface under the estimate, or None (NaN passes).

    Clouds of different places still meet under some pose (a floor on a floor, a corner):
    what they share is too small or unalike (:func:`met_surface_refusal`), or a thin overlap
    stands surfaces where both sensors saw free space (:func:`seen_through_refusal`). The
    gates judge the two apart, the second after the free-space gate
    (:func:`cgags_ros.validity.gate_refusal`).
    """
    return met_surface_refusal(e, cfg) or seen_through_refusal(e)


def met_surface_refusal(e: Shared, cfg: PipelineConfig) -> Refusal | None:
    """
    Return why the surface the clouds meet over is no shared one, or None (NaN passes).

    Too small a shared surface, or one whose descriptors differ as random pairs do (unless
    the overlap is degenerate: there all descriptors look alike, or none do).
    """
    gates, v2 = cfg.gates, e.voxel_size ** 2
    if gates.min_shared_area > 0 and (cells := e.shared_area / v2) < gates.min_shared_area:
        return _no_shared_surface(
            f'the best pose makes the clouds share {e.shared_area:.3g} m^2 ({cells:.0f} '
            f'voxels; < gates.min_shared_area {gates.min_shared_area:g} voxels, '
            f'{gates.min_shared_area * v2:.3g} m^2): too little to tell one place')
    if unalike(e.descriptor_ratio, e.observability, cfg):
        return _no_shared_surface(
            f'the {e.shared_area:.3g} m^2 the best pose makes the clouds share look '
            f'unalike (descriptor ratio {e.descriptor_ratio:.2f} > gates.max_descriptor'
            f'_ratio {gates.max_descriptor_ratio:g}): different surfaces that only meet')
    return None


def seen_through_refusal(e: Shared) -> Refusal | None:
    """
    Return why a thin overlap stands where both sensors saw free space, or None (NaN passes).

    Judged after the free-space gate: clouds not in their sensor frames read free space
    too, and ``free_space`` names their fix.
    """
    if not seen_through(e.free_space_surface, e.overlap):
        return None
    return _no_shared_surface(
        f'the best pose puts {100 * e.free_space_surface:.0f} % of the points each '
        'sensor saw of the other cloud where it saw free space, as whole surfaces '
        f'(> {100 * MAX_FREE_SPACE_SURFACE:g} %, both sensors): two places that only '
        'meet along a floor or a corner')


def _no_shared_surface(shown: str) -> Refusal:
    return Refusal(Code.NO_SHARED_SURFACE, f'no shared surface: {shown}; no pose found shows '
                   'one place: different places (a wrong map, a scan outside it)?')


def said_over_ambiguity(refusal: Refusal | None, ambiguity: Refusal | None) -> Refusal | None:
    """Return ``ambiguity`` over the gates' ``refusal``, unless that says no shared surface."""
    shared = refusal is not None and refusal.code is Code.NO_SHARED_SURFACE
    return refusal if shared else ambiguity or refusal


def seen_through(free_space_surface: float, overlap: float) -> bool:
    """
    Tell whether a thin overlap puts surfaces where both sensors saw free space (NaN: no).

    Above :data:`MAX_FREE_SPACE_SURFACE` with ``overlap`` below :data:`THIN_OVERLAP`: two
    rooms laid on a shared-looking floor or corner put each room's walls in the space the
    other's sensor saw through; a right pose leaves at most one view's occlusion edges.
    """
    return free_space_surface > MAX_FREE_SPACE_SURFACE and overlap < THIN_OVERLAP
