"""
Configuration of the registration core (``cgags_ros.registration``).

"paper" marks the paper's parameter table (docs/method.md). "INFERRED" marks a
reconstruction choice the paper does not state. The choices the ablation settled
(docs/ablation.md) are no options: the code does only what the measurements chose (soft
compatibility, edge and vertex tournaments, pre-screening, guided sampling from the best
inliers at stage-one confidence, max_up as kernel refreshes, the iterative re-fit; 6-DoF
scored by inlier count, 4-DoF by the truncated quadratic with vertical compatibility).
"""

from __future__ import annotations

import dataclasses
import math

from .fields import option
from ..errors import InvalidConfigError


@dataclasses.dataclass
class CoreConfig:
    """Options of the registration core; the defaults are the paper's where it has one."""

    # --- motion model (docs/method.md, "4-DoF mode") -------------------------------------
    motion_model: str = option(
        '6dof', "Unknowns of the transform: '6dof' (any rotation and translation) or '4dof' "
        '(yaw about the gravity axis and translation, for clouds already levelled, e.g. by '
        'an IMU: roll and pitch of the result are exactly zero).', choices=('6dof', '4dof'),
        ros=True)
    gravity: tuple[float, float, float] = option(
        (0.0, 0.0, 1.0), "[x, y, z]: the gravity (up) axis in both clouds' frames, used with "
        "motion_model='4dof'. It may have any nonzero length (it is normalised) and either "
        'sign; a zero axis is refused.', ros=True)
    max_tilt_deg: float = option(
        3.0, "With motion_model='4dof': largest tilt (degrees) between the clouds' gravity "
        'axes that is accepted. The tilt is measured by a 6-DoF re-fit of the 4-DoF inliers '
        '(and, in the pipeline, a 6-DoF point-to-plane step on the overlap); a larger tilt '
        'means the clouds are not levelled and the result is reported valid=False, never '
        'forced flat.', low=0.0, high=90.0)

    # --- thresholds (paper: tau = 6 pr; delta = 10 pr is COMPATIBILITY_FACTOR) ------------
    inlier_threshold: float = option(
        0.0, 'Inlier threshold tau in metres; 0 derives it from the point resolution pr (mean '
        'nearest-neighbour distance of the downsampled clouds) as inlier_threshold_factor * '
        'pr.', low=0.0)
    inlier_threshold_factor: float = option(
        6.0, 'Inlier threshold tau in units of the point resolution pr (paper: 6).', low=1e-6)

    # --- minimal compatible subsets (INFERRED) -------------------------------------------
    edge_tournament: int = option(
        16, 'INFERRED. Graph edge sampling draws this many uniform edges (by soft weight '
        '1 - (d_ij/delta)^2) and keeps the one with the most common neighbours '
        '|N(i) ∩ N(j)|; 1 is uniform sampling.',
        low=1, high=4096, advanced=True)
    vertex_tournament: int = option(
        8, 'INFERRED. Graph vertex sampling keeps, of this many uniform k in N(i) ∩ N(j), '
        'the one with the largest |N(i) ∩ N(j) ∩ N(k)|.',
        low=1, high=4096, advanced=True)

    # --- preference-based accelerated guided sampling -------------------------------------
    guided_sampling: bool = option(
        True, 'Use preference-based accelerated guided sampling after stage one.',
        advanced=True)

    # --- stopping ----------------------------------------------------------------------------
    max_iterations: int = option(
        100000, 'Hard cap on generated hypotheses (paper: 1e5).', low=1, high=10**8)
    time_budget: float = option(
        0.0, 'Seconds after which sampling stops and the best model so far is used (the '
        "result then says stopped_by='time_budget'). 0: no limit, only max_iterations.",
        low=0.0, ros=True)
    p1: float = option(0.99, 'Confidence P1 of the compatible-sampling stage (paper: 0.99).',
                       low=0.0, high=0.999999)
    futility_stop: bool = option(
        False, '4-DoF only. End the search without a valid model once a motion with the '
        'smallest significant consensus would have been drawn with confidence P1. Set it on '
        'a live system that rejects a non-significant answer anyway and needs it fast (no '
        'match ends in milliseconds, not at max_iterations); it misses more barely '
        'significant true motions (docs/bench_core_4dof.md).')

    # --- validity ------------------------------------------------------------------------------
    distinct_ratio: float = option(
        1.3, 'A result is significant (search may stop, result may be valid) only if its '
        'inlier count is at least this times that of the best distinct alternative '
        'hypothesis (sharing under half its inliers), and above the chance level.', low=1.0)
    min_inliers: int = option(
        6, 'An estimate with fewer inliers is reported valid=False.', low=3)

    def check(self) -> None:
        """Check constraints between fields (called by ``fields.validate``)."""
        norm = math.sqrt(sum(c * c for c in self.gravity))
        if not norm > 1e-9:
            raise InvalidConfigError(
                f'core.gravity = {list(self.gravity)} has zero length: give the up direction '
                "of the clouds' frames, e.g. [0, 0, 1]")

    @property
    def gravity_axis(self) -> tuple[float, float, float]:
        """Return the unit gravity (up) axis: ``gravity`` normalised."""
        g = self.gravity
        norm = math.sqrt(sum(c * c for c in g))
        return (g[0] / norm, g[1] / norm, g[2] / norm)
