"""Covariance of a registration result for geometry_msgs/PoseWithCovariance (ROS-free)."""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from .. import fitted
from ..geometry import occupied_cells


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


def overlap_covariance(source: np.ndarray, target: np.ndarray, target_normals: np.ndarray,
                       tree: cKDTree, T: np.ndarray, distance: float, voxel_size: float,
                       gravity: np.ndarray | None = None,
                       pairs: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """
    Return the 6x6 covariance of ``T`` from the whole overlap it aligns, ROS order.

    Same convention as :func:`pose_covariance`. The residuals are point-to-plane,
    ``r_i = n_i . (R p_i + t - q_i)`` over every source point with a target point ``q_i``
    (normal ``n_i``) within ``distance`` under ``T``: the surfaces, not a few keypoints,
    fix the pose, and a wall or a floor constrains only its normal, so the covariance opens
    along the motions the overlap leaves weak. ``J_i = [n_i, (R p_i) x n_i]``, ``H = sum
    J_i^T J_i``, ``sigma^2 = sum r_i^2 / (N - 6)``. Three corrections make it honest:

    - neighbouring residuals share their errors (the voxel grid, normals estimated from
      the same neighbours, a depth sensor's correlated noise), so the ``N`` residuals count
      as the ``C`` cells of a coarser grid (``CELL_FACTOR`` voxels) they occupy:
      ``SCALE sigma^2 H^-1 N / C``;
    - a floor no fit goes below: ``FLOOR_POSITION`` voxels on each position axis, and on
      each rotation axis the angle that moves a point at the overlap's RMS radius (about
      its centroid) by ``FLOOR_ROTATION`` voxels: the voxel grid and the surfaces' own
      noise bound what any alignment can resolve (the four numbers are
      :mod:`cgags_ros.fitted`'s ``COVARIANCE_*``);
    - ``gravity`` (4-DoF): the yaw-only information ``B^T H B`` as in
      :func:`pose_covariance`, the floor on yaw only.

    ``pairs``: the overlap's (source index, target index) when the caller has them (the
    nearest target point of each source point within ``distance`` under ``T``); else found
    in ``tree``.

    Fewer than 6 overlapping points or a singular information: variances of 1e6.
    """
    src = np.asarray(source, dtype=np.float64)
    R, t = T[:3, :3], T[:3, 3]
    if pairs is None:
        dist, nn = tree.query(src @ R.T + t, k=1, distance_upper_bound=distance)
        close = np.isfinite(dist)
        pairs = np.flatnonzero(close), nn[close]
    n_points = len(pairs[0])
    if n_points < 6:
        return np.diag([1e6] * 6)
    p, nn = src[pairs[0]] @ R.T, pairs[1]
    moved = p + t
    normals = np.asarray(target_normals, dtype=np.float64)[nn]
    J = np.hstack([normals, np.cross(p, normals)])
    r = np.einsum('ij,ij->i', normals, moved - np.asarray(target, dtype=np.float64)[nn])
    cells = occupied_cells(moved, fitted.COVARIANCE_CELL_FACTOR * voxel_size)
    sigma2 = max(float(r @ r) / max(n_points - 6, 1), 1e-12)
    scale = fitted.COVARIANCE_SCALE * sigma2 * n_points / max(cells, 1)
    radius = np.sqrt(np.mean(np.sum((moved - moved.mean(axis=0)) ** 2, axis=1)))
    floor = np.diag([(fitted.COVARIANCE_FLOOR_POSITION * voxel_size) ** 2] * 3
                    + [(fitted.COVARIANCE_FLOOR_ROTATION * voxel_size
                        / max(radius, voxel_size)) ** 2] * 3)
    B = np.eye(6)
    if gravity is not None:
        B = np.zeros((6, 4))
        B[:3, :3] = np.eye(3)
        B[3:, 3] = np.asarray(gravity, dtype=np.float64) / np.linalg.norm(gravity)
    info = B.T @ (J.T @ J) @ B
    if np.linalg.cond(info) > 1e12:
        return B @ np.diag([1e6] * B.shape[1]) @ B.T
    return B @ (scale * np.linalg.inv(info) + B.T @ floor @ B) @ B.T


def with_confidence(cov: np.ndarray, confidence: float, voxel_size: float) -> np.ndarray:
    """
    Return the covariance of a pose's error when the pose is right with ``confidence``.

    A right pose errs as ``cov`` says; a wrong one (a slide along a wall, a turn a
    near-symmetric room allows) by far more, with the spread ``W = diag((WRONG_POSITION_VOXELS
    v)^2 I, WRONG_ROTATION^2 I)`` at voxel size ``v`` (these numbers and ``DOUBT_EXPONENT``:
    :mod:`cgags_ros.fitted`): a scene's size, and so how far off a wrong pose lands in it,
    goes with the voxel it wants, as the bound on the sigma does (in voxels). With
    ``q`` the chance of a wrong pose the mixture's second moment is ``cov + q W``: a pose the
    pipeline is sure of keeps its ellipsoid, one it calls valid with less to spare opens, so
    that the error of the wrong ones among them lies inside it rather than far outside. ``q =
    (1 - confidence)^DOUBT_EXPONENT``: the confidence is cautious at its top (estimates near 1
    are right more often than it says), so the chance of a wrong pose falls faster than ``1 -
    confidence``. ``confidence`` 0 (no estimate) opens it by the whole of ``W``.
    """
    return np.asarray(cov, dtype=np.float64) + doubt(
        confidence, fitted.WRONG_POSITION_VOXELS * voxel_size, fitted.WRONG_ROTATION,
        fitted.DOUBT_EXPONENT)


def doubt(confidence: float, position: float, rotation: float, exponent: float) -> np.ndarray:
    """
    Return ``q W`` of :func:`with_confidence` for these spreads and exponent.

    ``position`` metres a position axis, ``rotation`` radians a rotation axis: what a
    record's covariance was opened with, to take it off again, as well as what ships.
    """
    W = np.diag([position ** 2] * 3 + [rotation ** 2] * 3)
    return (1.0 - min(max(confidence, 0.0), 1.0)) ** exponent * W


def loosest_sigma(cov: np.ndarray) -> float:
    """Return the position sigma (metres) along the loosest direction of a 6x6 covariance."""
    return float(np.sqrt(max(np.linalg.eigvalsh(np.asarray(cov)[:3, :3])[-1], 0.0)))


def result_covariance(result: Any, source: np.ndarray, target: np.ndarray,
                      target_normals: np.ndarray, tree: cKDTree, distance: float,
                      gravity: np.ndarray | None = None,
                      pairs: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """
    Return the 6x6 covariance (:func:`overlap_covariance`) of a pipeline result's estimate.

    Over the overlap its final ``transform`` aligns (downsampled clouds, ``distance`` the
    refinement's; ``pairs`` that overlap when the caller measured it); variances of 1e6 when
    fewer than three correspondences support the estimate (there is none). ``gravity`` is
    the unit up axis of a 4-DoF estimate.
    """
    if len(result.inlier_source_points) < 3:
        return np.diag([1e6] * 6)
    return overlap_covariance(source, target, target_normals, tree,
                              np.asarray(result.transform, dtype=np.float64), distance,
                              float(result.voxel_size), gravity, pairs)
