"""
Configuration of the validity gates: the settings :mod:`cgags_ros.validity` decides with.

Read after the core and the refinement: the overlap (fitness), the chance level, the
observability, the free-space gate, the ambiguity between candidates and the estimate's
twins, and the calibrated confidence. The core's own refusals (``core.min_inliers``,
``core.distinct_ratio``, ``core.max_tilt_deg``) stay in :mod:`.core`, since its search stops
on them too.
"""

from __future__ import annotations

import dataclasses

from .fields import option
from .. import fitted


@dataclasses.dataclass
class GatesConfig:
    """When a refined estimate is valid, and when it is ambiguous."""

    ambiguity_ratio: float = option(
        1.5, 'The estimate is ambiguous (reported invalid, flagged ambiguous) when the best '
        "candidate's inlier count is below this times the runner-up's: two poses are then "
        'nearly equally supported (a symmetric room, a corridor).', low=1.0, high=100.0)
    min_confidence: float = option(
        fitted.MIN_CONFIDENCE,
        'The estimate is valid only when its confidence (the calibrated probability that '
        "it is right, from the gates' measurements) is at least this, on top of every gate. "
        '6-DoF pairs only: against a map or in 4-DoF mode the confidence is reported but '
        'decides nothing. 0 leaves the decision to the gates.', low=0.0, high=1.0)
    max_position_sigma: float = option(
        fitted.MAX_POSITION_SIGMA,
        "Valid means usable: the estimate is invalid when its covariance's position "
        "sigma along its loosest direction (the overlap's, opened by the doubt the "
        "confidence leaves; against a map, the overlap's alone) is above this many voxel "
        'sizes; the covariance is still reported. 6-DoF pairs of scans, and the '
        "relocalizer's confirmed poses. 0 disables.", low=0.0, high=1e6)
    settle_candidates: bool = option(
        True, 'Refine the candidates that make an estimate ambiguous; one that converges onto '
        "it, whose overlap the estimate's exceeds ambiguity_ratio times, or that fails the "
        'free-space gate is not plausible; only a plausible candidate makes it ambiguous.',
        advanced=True)
    check_twins: bool = option(
        True, 'Before calling an estimate valid, try its twins: the poses a near-symmetric or '
        'weakly constrained scene would also accept (the estimate turned 180 degrees about '
        "the overlap's principal axes, slid along its least constrained direction), each "
        'refined briefly and judged; a plausible one makes the result ambiguous. 6-DoF '
        'pairs of sensor-frame clouds only (the free-space gate must apply).',
        advanced=True)
    min_fitness: float = option(
        0.0, 'After refinement, a fitness (share of source points with a target point within '
        'the refinement distance) below this marks the result invalid. 0 disables.',
        low=0.0, high=1.0)
    significance: float = option(
        0.01, 'Chance-inlier gate: the estimate is invalid unless its inlier count is above '
        'what the best of the generated hypotheses would reach with probability '
        '`significance` if every correspondence were an outlier (Poisson model). A pose in '
        "one place of a prepared map is ambiguous when the whole map's matches back it no "
        'more than chance and another pose more (docs/maps.md). 0 disables both.',
        low=0.0, high=1.0)
    min_shared_area: float = option(
        480.0, 'Shared-surface gate: the estimate is invalid when the surface the clouds share '
        "under it (the smaller side's downsampled points within the refinement distance of "
        'the other cloud) is below this many square voxel sizes: clouds of different places '
        'meet over a floor or a wall corner, not over a room. 0 disables.',
        low=0.0, high=1e9)
    max_descriptor_ratio: float = option(
        0.85, 'Shared-surface gate: the estimate is invalid when the descriptors (FPFH) of the '
        'point pairs of its overlap differ, in median, by more than this times those of the '
        'same points paired at random: near 1, different surfaces only meet under it. '
        '0 disables.', low=0.0, high=10.0)
    min_observability: float = option(
        0.02, 'Degeneracy gate: smallest / largest eigenvalue of the point-to-plane '
        'information matrix over the overlapping points (rotation scaled by the overlap '
        'radius). Planes, lines, spheres and cylinders leave some motion unconstrained and '
        'give ~0; the estimate is then invalid. 0 disables.', low=0.0, high=1.0)
    max_free_space_violation: float = option(
        0.3, "Free-space gate (sensor-frame clouds: frontend.normal_orientation 'origin'): "
        "the share of aligned points in front of the other cloud's observed surface (by "
        'over two voxels), among those in front or on it, the larger '
        'direction; above this the pose puts surfaces where a sensor saw free space and is '
        'invalid. 1 disables.', low=0.0, high=1.0)
