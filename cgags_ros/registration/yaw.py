"""
The 4-DoF motion model (yaw about gravity + translation): steps 3 and 8 of Algorithm 1.

Adapts the paper's hypothesis step (closed-form fit of a minimal subset, step 3)
and the final least-squares re-fit (step 8) to clouds that are already levelled: the
rotation is a yaw about the gravity axis g, so a hypothesis has four unknowns and a
compatible edge (two correspondences) determines it. Everything here works in the
*gravity frame*, whose z axis is g (:class:`GravityFrame`); there the rotation is
``R_z(yaw)`` exactly, so the result maps g onto itself (roll and pitch exactly zero).

``GravityFrame`` (in :mod:`cgags_ros.geometry`, shared with the refinement) is re-exported.
"""

from __future__ import annotations

import numpy as np

from .hypotheses import refit
from .rigid import kabsch, residuals
from ..geometry import GravityFrame, make_transform


def yaw_rotations(yaw: np.ndarray) -> np.ndarray:
    """Rotations about z by ``yaw`` (B,) radians: (B, 3, 3), last row exactly (0, 0, 1)."""
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.zeros((len(yaw), 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1] = c, -s, s, c
    R[:, 2, 2] = 1.0
    return R


def fit_yaw_batch(P: np.ndarray, Q: np.ndarray,
                  W: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """
    Weighted least-squares yaw + translation with ``Q ≈ R_z(yaw) P + t`` per item.

    The closed form: with weighted centroids removed, yaw = atan2(sum w (a x b)_z,
    sum w a_xy . b_xy) and t = c_q - R c_p. Two correspondences suffice (K >= 2).

    :param P, Q: (B, K, 3) corresponding points in the gravity frame.
    :param W: optional (B, K) non-negative weights.
    :returns: R (B, 3, 3) yaw rotations, t (B, 3).
    """
    if W is None:
        W = np.ones(P.shape[:2])
    W = W / W.sum(axis=1, keepdims=True)
    cp = np.einsum('bk,bki->bi', W, P)
    cq = np.einsum('bk,bki->bi', W, Q)
    a, b = P - cp[:, None], Q - cq[:, None]
    cos = np.einsum('bk,bk->b', W, a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1])
    sin = np.einsum('bk,bk->b', W, a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0])
    R = yaw_rotations(np.arctan2(sin, cos))
    return R, cq - np.einsum('bij,bj->bi', R, cp)


def fit_edges(src: np.ndarray, dst: np.ndarray, i: np.ndarray,
              j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closed-form yaw + translation of each compatible edge (i, j): R (B, 3, 3), t (B, 3)."""
    idx = np.stack([i, j], axis=1)
    return fit_yaw_batch(src[idx], dst[idx])


def fit_yaw(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """4x4 (weighted) least-squares yaw + translation mapping ``src`` (K, 3) onto ``dst``."""
    R, t = fit_yaw_batch(src[None], dst[None], None if weights is None else weights[None])
    return make_transform(R[0], t[0])


def vertical_offsets(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """
    Return u_i = z(q_i) - z(p_i): the vertical translation correspondence i implies.

    Yaw and translation preserve vertical offsets, so |dz_p - dz_q| = |u_i - u_j| for an
    edge (i, j): the vertical compatibility test is 1-D.
    """
    return dst[:, 2] - src[:, 2]


def horizontal_lengths(points: np.ndarray, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """Return the lengths of (p_j - p_i) across the gravity axis (gravity frame)."""
    d = points[j, :2] - points[i, :2]
    return np.sqrt(np.einsum('...k,...k->...', d, d))


def tilt_deg(T: np.ndarray) -> float:
    """Return the angle (degrees) by which the rotation of ``T`` moves the z axis."""
    return float(np.degrees(np.arccos(np.clip(T[2, 2], -1.0, 1.0))))


def measure_tilt(src: np.ndarray, dst: np.ndarray, inliers: np.ndarray, tau: float,
                 iterations: int) -> float:
    """
    Return the tilt (degrees) of the best 6-DoF fit started from the 4-DoF inliers.

    A 6-DoF least-squares fit of the inliers, then the iterative 6-DoF re-fit
    (:func:`~.hypotheses.refit`) over all correspondences; its rotation's deviation from
    a pure yaw is the tilt between the clouds' gravity axes. NaN when the inliers cannot
    determine a rotation (fewer than 3, or collinear).
    """
    if len(inliers) < 3:
        return float('nan')
    pts = src[inliers] - src[inliers].mean(axis=0)
    if np.linalg.svd(pts, compute_uv=False)[1] / np.sqrt(len(pts)) < tau:
        return float('nan')
    T6 = kabsch(src[inliers], dst[inliers])
    if residuals(T6, src[inliers], dst[inliers]).max() <= 2 * tau:
        T6, _, _ = refit(src, dst, T6, tau, iterations)
    return tilt_deg(T6)


__all__ = ['GravityFrame', 'fit_edges', 'fit_yaw', 'fit_yaw_batch', 'horizontal_lengths',
           'measure_tilt', 'tilt_deg', 'vertical_offsets', 'yaw_rotations']
