"""Hypotheses: fitting minimal subsets, scoring them, and the final least-squares re-fit."""

from __future__ import annotations

import numpy as np

from .compatibility import CompatibilityGraph
from .rigid import kabsch, kabsch_batch, residuals


def fit_triples(src: np.ndarray, dst: np.ndarray, i: np.ndarray, j: np.ndarray,
                k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closed-form rigid transform of each triple: R (B, 3, 3), t (B, 3)."""
    idx = np.stack([i, j, k], axis=1)
    return kabsch_batch(src[idx], dst[idx])


def score_values(res: np.ndarray, tau: float, mode: str) -> np.ndarray:
    """
    Return the score contribution of each residual under the score ``mode``.

    'inlier_count' gives 1 for inliers (r <= tau) and 0 otherwise; 'truncated' (MSAC)
    gives the truncated quadratic max(0, 1 - r^2 / tau^2).
    """
    if mode == 'inlier_count':
        return (res <= tau).astype(np.float64)
    return np.maximum(0.0, 1.0 - (res / tau) ** 2)


def score_in_common_neighbourhood(graph: CompatibilityGraph, src: np.ndarray, dst: np.ndarray,
                                  R: np.ndarray, t: np.ndarray, triples: np.ndarray,
                                  tau: float, mode: str) -> np.ndarray:
    """
    Score each hypothesis on {i, j, k} ∪ (N(i) ∩ N(j) ∩ N(k)) only.

    Every inlier of a correct hypothesis is compatible with its three (inlier) sample
    members, so for good hypotheses this equals the full score up to noise, at a fraction
    of the cost; wrong hypotheses can only score lower. Used to pre-screen a batch before
    the exact (all-N) scoring of its best members.
    """
    i, j, k = triples.T
    cand = np.unpackbits(graph.common(i, j, k), axis=1, count=graph.n, bitorder='little')
    rows = np.arange(len(triples))
    for member in (i, j, k):
        cand[rows, member] = 1
    b, m = np.nonzero(cand)
    moved = np.einsum('bij,bj->bi', R[b], src[m]) + t[b]
    res = np.linalg.norm(moved - dst[m], axis=1)
    return np.bincount(b, weights=score_values(res, tau, mode), minlength=len(triples))


def residual_matrix(src: np.ndarray, dst: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Residuals of all N correspondences under E hypotheses: (E, N) float32."""
    moved = np.matmul(src.astype(np.float32)[None], R.transpose(0, 2, 1).astype(np.float32))
    moved += (t.astype(np.float32)[:, None, :] - dst.astype(np.float32)[None])
    return np.sqrt(np.einsum('eni,eni->en', moved, moved))


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


__all__ = ['fit_triples', 'score_values', 'score_in_common_neighbourhood', 'residual_matrix',
           'refit']
