"""
Confidence: the probability that a pipeline result's estimate is right, from its measurements.

A logistic model over what the gates and the candidate search measured (inliers against
their chance level, the runner-up's support, overlap, fitness, observability, free-space
violation, residuals), fit on real RGB-D pairs with each scene's probabilities predicted by
a model fit on the others (docs/confidence.md). "Right" is the benchmark's: within 15
degrees and 30 cm of the truth. ``valid`` requires ``confidence >= min_confidence`` on top of
the gates: the operating point trades right estimates kept against wrong ones passed.
"""

from __future__ import annotations

import math
from typing import Any

from .gates import chance_bound

# Inputs of the model, each a number every estimate has (see :func:`features`).
FEATURES = ('log_inliers', 'log_margin', 'log_runner_up', 'overlap', 'fitness',
            'log_observability', 'free_space', 'rmse_voxels', 'log_correspondences',
            'inlier_share', 'rival_fitness')

# Weights of the logistic model (on the raw features) and its intercept, fit on every
# pair of the shared 3DMatch scenes by ``bench/loso_trust_study.py``.
WEIGHTS = {'log_inliers': 0.07082, 'log_margin': 2.054, 'log_runner_up': -0.3696,
           'overlap': 0.2475, 'fitness': -0.6355, 'log_observability': 2.198,
           'free_space': -12.83, 'rmse_voxels': -18.26, 'log_correspondences': -1.052,
           'inlier_share': -1.499, 'rival_fitness': -1.224}
INTERCEPT = 27.74

RUNNER_UP_CAP = 20.0  # a runner-up this far behind is as good as none


def features(result: Any, significance: float, members: int = 3) -> dict[str, float] | None:
    """
    Return the model's inputs for ``result`` (a :class:`~.result.PipelineResult`).

    None when there is no estimate to judge (no candidate: the core found nothing). The
    chance bound is the gates' (:func:`~.gates.chance_bound`): the inliers the best of the
    hypotheses reaches by chance at ``significance``; ``members`` define a hypothesis.
    """
    if not result.candidates or not result.fitness > 0:
        return None
    inliers = max(int(result.num_inliers), 1)
    bound = chance_bound(result.chance_inliers, result.num_hypotheses, significance,
                         members) \
        if math.isfinite(result.chance_inliers) else members
    voxel = float(result.voxel_size)
    rmse = result.inlier_rmse if math.isfinite(result.inlier_rmse) else 1.5 * voxel
    violation = result.free_space_violation
    rivals = [c.fitness for c in result.candidates[1:] if math.isfinite(c.fitness)]
    return {
        'log_inliers': math.log(inliers),
        'log_margin': math.log(inliers / max(bound, 1)),
        'log_runner_up': math.log(min(result.runner_up_ratio, RUNNER_UP_CAP)),
        'overlap': float(result.overlap),
        'fitness': float(result.fitness),
        'log_observability': math.log(max(float(result.observability), 0.0) + 1e-3)
        if math.isfinite(result.observability) else math.log(1e-3),
        'free_space': float(violation) if math.isfinite(violation) else 0.0,
        'rmse_voxels': rmse / voxel,
        'log_correspondences': math.log(max(int(result.num_correspondences), 1)),
        'inlier_share': inliers / max(int(result.num_correspondences), 1),
        'rival_fitness': max(rivals) / max(result.fitness, 1e-3) if rivals else 0.0,
    }


def probability(values: dict[str, float] | None) -> float:
    """Return the model's P(right) for :func:`features`' values (0 without an estimate)."""
    if values is None:
        return 0.0
    z = INTERCEPT + sum(WEIGHTS[name] * values[name] for name in FEATURES)
    return 1.0 / (1.0 + math.exp(-z)) if z > -700 else 0.0
