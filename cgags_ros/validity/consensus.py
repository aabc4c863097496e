"""
The core's verdict on its consensus: whether the global search found a pose it can trust.

The core (:mod:`cgags_ros.registration`) asks, once its search has stopped: no estimate
(no compatibility edge, no minimal subset to fit), too few inliers, a collinear consensus,
chance level or a distinct alternative, a tilt in 4-DoF mode. Part of
:mod:`cgags_ros.validity`, the one place that decides.
"""

from __future__ import annotations

from typing import Protocol

from ..config.core import CoreConfig
from ..refusal import Refusal, RefusalCode

Code = RefusalCode


class Consensus(Protocol):
    """What the core measured of its final consensus (a ``RegistrationResult``'s fields)."""

    num_inliers: int
    inlier_threshold: float  # tau, metres
    inlier_spread: float  # metres, across the line that would leave a rotation free
    chance_level: int
    runner_up: int
    tilt_deg: float  # 4-DoF only (else NaN)
    refusal: Refusal | None
    reason: str


def no_graph_refusal(delta: float) -> Refusal:
    """Return the refusal of a compatibility graph without an edge (no estimate)."""
    return Refusal(Code.NO_ESTIMATE, (
        f'no two correspondences are length-consistent within delta={delta:.4g} m: '
        'they are all outliers, or the thresholds are too small for the noise'))


def no_model_refusal(collinear_subsets: int, yaw_only: bool) -> Refusal:
    """
    Return the refusal of a search that found no minimal subset to fit (no estimate).

    ``collinear_subsets``: compatible subsets the search drew and set aside as degenerate
    (nearly collinear triangles; 4-DoF: nearly vertical edges).
    """
    if collinear_subsets:
        return Refusal(Code.COLLINEAR, (
            'every compatible edge of correspondences is nearly vertical (shorter across the '
            'gravity axis than tau): the yaw is undetermined'
            if yaw_only else
            'every compatible triangle of correspondences is nearly collinear: the scene (or '
            'its matched keypoints) is a line, and the rotation about it is undetermined'))
    return Refusal(Code.NO_ESTIMATE, (
        'no usable compatible edge of correspondences was found (too few inliers or '
        'thresholds too small)' if yaw_only else
        'no compatible triangle of correspondences was found: the compatibility graph has '
        'edges but no 3-cliques (too few inliers or thresholds too small)'))


def consensus_refusal(c: Consensus, cfg: CoreConfig) -> Refusal | None:
    """
    Return why the core's final consensus is not trusted, or None.

    Enough inliers, not on a line (4-DoF: not on one vertical line), standing out from
    chance and from every distinct alternative (step 7's test), and in 4-DoF mode levelled
    clouds. A tilt also splits a yaw-only consensus into competing parts: both are then said,
    under the tilt's code, the tilt being what the user can act on.
    """
    refusal = _consensus_shape(c, cfg) or _stands_out(c, cfg)
    tilted = tilt_refusal(c.tilt_deg, cfg.max_tilt_deg, 'the best 6-DoF fit of the inliers',
                          'max_tilt_deg', "motion_model='6dof'")
    if refusal and tilted:
        return Refusal(Code.TILT, f'{refusal.message}; {tilted.message}')
    return refusal or tilted


def _consensus_shape(c: Consensus, cfg: CoreConfig) -> Refusal | None:
    if c.num_inliers < cfg.min_inliers:
        return Refusal(Code.FEW_INLIERS, (
            f'only {c.num_inliers} inliers (< min_inliers={cfg.min_inliers}): no rigid motion '
            'is supported by enough correspondences'))
    if not c.inlier_spread < c.inlier_threshold:
        return None
    if cfg.motion_model == '4dof':  # a line determines the yaw unless it is vertical
        return Refusal(Code.COLLINEAR, 'the inliers lie (nearly) on one vertical line: the '
                       'yaw about it is undetermined')
    return Refusal(Code.COLLINEAR, 'the inliers are nearly collinear: the rotation about '
                   'their line is undetermined')


def _stands_out(c: Consensus, cfg: CoreConfig) -> Refusal | None:
    """Step 7's significance test on the final consensus (as the search stops on it)."""
    if c.num_inliers < c.chance_level:
        code = Code.CHANCE_LEVEL
    elif c.num_inliers < cfg.distinct_ratio * c.runner_up:
        code = Code.AMBIGUOUS
    else:
        return None
    return Refusal(code, (
        f'the best consensus ({c.num_inliers} inliers) does not stand out: chance level '
        f'{c.chance_level}, best distinct alternative {c.runner_up} (x{cfg.distinct_ratio} '
        'required); no rigid motion is clearly supported'))


def tilt_refusal(tilt_deg: float, max_tilt_deg: float, measured_by: str, setting: str,
                 six_dof: str) -> Refusal | None:
    """Return why a yaw-only estimate is not trusted on a measured tilt (NaN passes)."""
    if not tilt_deg > max_tilt_deg:  # NaN: 6-DoF mode, or not measurable
        return None
    return Refusal(Code.TILT, (
        f'the clouds are not levelled: {measured_by} tilts the gravity axis by '
        f'{tilt_deg:.2f} deg (> {setting}={max_tilt_deg:g}); the yaw-only estimate is not '
        f'trusted: level the clouds or use {six_dof}'))
