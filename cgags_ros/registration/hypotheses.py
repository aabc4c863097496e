"""Hypotheses: score contributions and the final least-squares re-fit (fits: compiled)."""

from __future__ import annotations

import numpy as np

from .rigid import kabsch, residuals


def score_values(res: np.ndarray, tau: float, mode: str) -> np.ndarray:
    """
    Return the score contribution of each residual under the score ``mode``.

    'inlier_count' gives 1 for inliers (r <= tau) and 0 otherwise; 'truncated' (MSAC)
    gives the truncated quadratic max(0, 1 - r^2 / tau^2).
    """
    if mode == 'inlier_count':
        return (res <= tau).astype(np.float64)
    return np.maximum(0.0, 1.0 - (res / tau) ** 2)


def refit(src: np.ndarray, dst: np.ndarray, T: np.ndarray, tau: float,
          iterations: int, fit=kabsch, min_points: int = 3
          ) -> tuple[np.ndarray, np.ndarray, int]:
    """
    Weighted least-squares re-fit on the inliers, repeated while the inlier set changes.

    Inliers are weighted by Tukey's biweight (1 - r^2/tau^2)^2 of their current residual,
    so a chance outlier just inside tau cannot pull the estimate (with few inliers one
    such point would otherwise tilt the rotation by degrees). A re-fit is kept only if it
    does not lower the truncated score sum max(0, 1 - r^2/tau^2) (whatever the search's
    score: an inlier count would prefer a tilted fit that grazes one more outlier over an
    accurate fit of the true inliers), so it never makes the estimate worse. ``fit``
    ``(src, dst, weights) -> 4x4`` is the weighted least-squares solver of the motion model
    (6-DoF Kabsch, or :func:`~.yaw.fit_yaw` for 4-DoF), which needs ``min_points``.
    Returns (T, inlier indices, re-fits done).
    """
    res = residuals(T, src, dst)
    best_score = score_values(res, tau, 'truncated').sum()
    inliers = np.flatnonzero(res <= tau)
    done = 0
    for _ in range(iterations):
        if len(inliers) < min_points:
            break
        weights = (1.0 - (res[inliers] / tau) ** 2) ** 2 + 1e-12
        T_new = fit(src[inliers], dst[inliers], weights)
        res_new = residuals(T_new, src, dst)
        score_new = score_values(res_new, tau, 'truncated').sum()
        new_inliers = np.flatnonzero(res_new <= tau)
        if score_new < best_score:
            break
        done += 1
        changed = not np.array_equal(new_inliers, inliers)
        T, inliers, best_score, res = T_new, new_inliers, score_new, res_new
        if not changed:
            break
    return T, inliers, done
