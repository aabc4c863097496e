"""Covariance of a registration result for geometry_msgs/PoseWithCovariance (ROS-free)."""

from __future__ import annotations

from typing import Any

import numpy as np


def pose_covariance(src: np.ndarray, dst: np.ndarray, T: np.ndarray,
                    gravity: np.ndarray | None = None) -> np.ndarray:
    """
    Return the 6x6 covariance of a rigid pose estimated from matched points, ROS order.

    Row-major, ordered (x, y, z, rotation about X, Y, Z) as geometry_msgs/
    PoseWithCovariance wants: a perturbation ``t' = t + dt`` (metres, target frame) and
    ``R' = exp([dphi]x) R`` (radians, about the target frame's axes through the source
    origin).

    Gauss-Newton on the point-to-point residuals ``r_i = R src_i + t - dst_i``: the
    Jacobian of r_i is ``J_i = [I, -[R src_i]x]``, the information is ``sum J_i^T J_i``
    and ``cov = sigma^2 (J^T J)^-1`` with the residual variance ``sigma^2 = sum |r_i|^2 /
    (3K - 6)``. It reflects geometry (a planar scene leaves some directions weak) and fit
    quality; it ignores wrong correspondences and correlation between points, so treat it
    as optimistic. Fewer than 3 pairs or a singular information: variances of 1e6.

    With ``gravity`` (the unit up axis of a 4-DoF estimate) the rotation is a yaw about it,
    ``dphi = g dyaw``: the information of (dt, dyaw) is ``B^T info B`` with
    ``B = [[I, 0], [0, g]]``, ``sigma^2`` has 3K - 4 degrees of freedom, and the result is
    ``B cov4 B^T``, so roll and pitch have zero variance.
    """
    src = np.asarray(src, dtype=np.float64).reshape(-1, 3)
    dst = np.asarray(dst, dtype=np.float64).reshape(-1, 3)
    k = min(len(src), len(dst))
    if k < 3:
        return np.diag([1e6] * 6)
    R, t = T[:3, :3], T[:3, 3]
    rotated = src[:k] @ R.T
    residuals = rotated + t - dst[:k]
    unknowns = 6 if gravity is None else 4
    sigma2 = max(float(np.sum(residuals**2)) / max(3 * k - unknowns, 1), 1e-12)
    # J_i^T J_i summed in closed form: [[K I, -S^T], [-S, sum(|p|^2 I - p p^T)]],
    # with S = sum [p]x (p = R src_i); -[p]x^T = [p]x, so the off-diagonal block is [sum p]x.
    p_sum = rotated.sum(axis=0)
    skew = np.array([[0, -p_sum[2], p_sum[1]], [p_sum[2], 0, -p_sum[0]],
                     [-p_sum[1], p_sum[0], 0]])
    info = np.zeros((6, 6))
    info[:3, :3] = k * np.eye(3)
    info[:3, 3:] = skew
    info[3:, :3] = skew.T
    info[3:, 3:] = np.sum(rotated**2) * np.eye(3) - rotated.T @ rotated
    if gravity is not None:
        B = np.zeros((6, 4))
        B[:3, :3] = np.eye(3)
        B[3:, 3] = np.asarray(gravity, dtype=np.float64) / np.linalg.norm(gravity)
        info4 = B.T @ info @ B
        if np.linalg.cond(info4) > 1e12:
            return B @ np.diag([1e6] * 4) @ B.T
        return sigma2 * B @ np.linalg.inv(info4) @ B.T
    if np.linalg.cond(info) > 1e12:
        return np.diag([1e6] * 6)
    return sigma2 * np.linalg.inv(info)


def moved_covariance(cov: np.ndarray, T_map_sensor: np.ndarray,
                     T_sensor_frame: np.ndarray) -> np.ndarray:
    """
    Return the covariance of ``T_map_sensor @ T_sensor_frame`` from that of ``T_map_sensor``.

    Same perturbation model as :func:`pose_covariance` (``t' = t + dt``, ``R' = exp([dphi]x)
    R`` in the map frame): a frame rigidly attached to the sensor at lever arm ``l`` (its
    origin in the sensor frame) moves by ``dt + dphi x (R l)``, so ``J = [[I, -[R l]x],
    [0, I]]`` and the result is ``J cov J^T``; the rotation part is unchanged.
    """
    arm = np.asarray(T_map_sensor, dtype=np.float64)[:3, :3] @ np.asarray(T_sensor_frame)[:3, 3]
    J = np.eye(6)
    J[:3, 3:] = -np.array([[0.0, -arm[2], arm[1]], [arm[2], 0.0, -arm[0]],
                           [-arm[1], arm[0], 0.0]])
    return J @ np.asarray(cov, dtype=np.float64) @ J.T


def map_to_odom(T_map_base: np.ndarray, T_odom_base: np.ndarray) -> np.ndarray:
    """Return ``T_map_odom`` (Nav2's map -> odom) from the base pose in both frames."""
    return np.asarray(T_map_base) @ np.linalg.inv(T_odom_base)


def result_covariance(result: Any, gravity: np.ndarray | None = None) -> np.ndarray:
    """
    Return the 6x6 covariance (:func:`pose_covariance`) of a pipeline result's estimate.

    From its inlier correspondences (``inlier_source_points``, ``inlier_target_points``)
    under its final ``transform``; ``gravity`` is the unit up axis of a 4-DoF estimate.
    """
    return pose_covariance(result.inlier_source_points, result.inlier_target_points,
                           np.asarray(result.transform, dtype=np.float64), gravity)
