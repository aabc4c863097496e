"""
Confidence: the probability that a pipeline result's estimate is right, from its measurements.

A logistic model over three measurements that each mean one thing and move P(right) one
way: the core's inliers over the chance bound of the same correspondences (more margin, more
trust), the loosest position sigma of the overlap's covariance in voxels (a looser overlap,
less) and the free-space violation (surfaces where a sensor saw free space, less). Fit on
real RGB-D pairs, then rescaled to how sure it may be on a scene it was not fit on (each
training scene predicted by a model fit on the others), and checked on harder scenes than
those it was chosen on (docs/confidence.md). "Right" is the benchmark's: within 15 degrees
and 30 cm of the truth. ``valid`` requires ``confidence >= min_confidence`` on top of the
gates, and the covariance opens by the doubt it leaves (:func:`~.covariance.with_confidence`).
"""

from __future__ import annotations

import math
from typing import Any

from .covariance import loosest_sigma
from .gates import chance_bound
from .. import fitted

# Inputs of the model, each a number every estimate has (see :func:`features`), with the
# sign its weight must have.
SIGNS = {'log_margin': 1.0, 'log_sigma': -1.0, 'free_space': -1.0}
FEATURES = tuple(SIGNS)

SIGMA_FLOOR = 1e-3  # voxels: log of a sigma that no overlap reaches


def refused_at_most(code: str) -> float:
    """
    Return the most the confidence of an estimate the gates refused as ``code`` may say.

    The share of right estimates among such refusals (:data:`cgags_ros.fitted.REFUSED_RIGHT`):
    the model rates the pose on what the overlap shows, never the refusal (it never saw
    clouds of different places, and rates a floor on a floor as a room on itself).
    """
    return fitted.REFUSED_RIGHT.get(code, fitted.REFUSED_RIGHT_OTHER)


def capped(confidence: float, code: str) -> float:
    """Return ``confidence`` for an estimate refused as ``code``: ``refused_at_most`` at most."""
    return min(confidence, refused_at_most(code))


def features(result: Any, significance: float, members: int = 3) -> dict[str, float] | None:
    """
    Return the model's inputs for ``result`` (a :class:`~.result.PipelineResult`).

    None when there is no estimate to judge (no candidate: the core found nothing). The
    chance bound is the gates' (:func:`~.gates.chance_bound`): the inliers the best of the
    hypotheses reaches by chance at ``significance``; ``members`` define a hypothesis.
    ``result.covariance`` is the overlap's, before the doubt opens it.
    """
    if not result.candidates or not result.fitness > 0:
        return None
    inliers = max(int(result.num_inliers), 1)
    bound = chance_bound(result.chance_inliers, result.num_hypotheses, significance,
                         members) \
        if math.isfinite(result.chance_inliers) else members
    violation = result.free_space_violation
    sigma = loosest_sigma(result.covariance) / float(result.voxel_size)
    return {
        'log_margin': math.log(inliers / max(bound, 1)),
        'log_sigma': math.log(max(sigma, SIGMA_FLOOR)),
        'free_space': float(violation) if math.isfinite(violation) else 0.0,
    }


def probability(values: dict[str, float] | None) -> float:
    """Return the model's P(right) for :func:`features`' values (0 without an estimate)."""
    if values is None:
        return 0.0
    z = fitted.CONFIDENCE_INTERCEPT + sum(fitted.CONFIDENCE_WEIGHTS[name] * values[name]
                                          for name in FEATURES)
    return 1.0 / (1.0 + math.exp(-z)) if z > -700 else 0.0
