"""
One point-to-plane problem over every frame: the joint refinement and its information.

Frame k holds the child cloud (child frame) and the parent cloud (parent frame), both
voxel-downsampled, with their surface normals. The unknown is one transform parent <-
child, ``T = (R, t)`` with ``p_parent = R p_child + t``, shared by all frames. Residuals
are ``n . (R p + t - q)`` for every child point p whose nearest parent point q (normal n)
lies within the correspondence distance, and the same for every parent point against its
nearest child point's surface (:class:`Pairs`), pooled over the frames.

Perturbation convention (the covariance's too, see :mod:`.uncertainty`): ``t' = t + dt``
(metres, parent frame) and ``R' = exp([dphi]x) R`` (radians, about the parent frame's axes
through the child origin), ordered ``(dt_x, dt_y, dt_z, dphi_x, dphi_y, dphi_z)``. The
Jacobian of a residual is then ``[n, a x n]``, with ``a`` its point relative to the child
origin in parent axes.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from ..geometry import apply_transform

ITERATIONS = 30  # Gauss-Newton iterations of each joint refinement stage


@dataclasses.dataclass
class FrameClouds:
    """
    The downsampled clouds of one frame, as the joint problem reads them.

    :ivar child: (M, 3) child points, child frame, metres.
    :ivar parent: (N, 3) parent points, parent frame, metres.
    :ivar parent_normals: (N, 3) unit normals of ``parent``; NaN rows where no surface
        defines one (:func:`surface_normals`).
    :ivar parent_tree: k-d tree over ``parent``.
    :ivar child_tree: k-d tree over ``child``.
    :ivar child_normals: (M, 3) unit normals of ``child`` (child frame), NaN as above.
    :ivar child_queries, parent_queries: indices of the points that seek a partner in the
        other cloud (None: all); their partners are sought among all points.
    """

    child: np.ndarray
    parent: np.ndarray
    parent_normals: np.ndarray
    parent_tree: cKDTree
    child_tree: cKDTree
    child_normals: np.ndarray
    child_queries: np.ndarray | None = None
    parent_queries: np.ndarray | None = None


@dataclasses.dataclass
class Pairs:
    """
    The point-to-plane pairs of one frame under a transform, both ways.

    Child points against the parent's surfaces (parent normals) and parent points against
    the child's (child normals, rotated into the parent frame): whichever cloud is denser
    defines the surfaces better, and the two together do not depend on which it is.

    :ivar arms: (K, 3) each pair's point relative to the child origin, parent axes
        (``R p`` for a child point p, ``q - t`` for a parent point q), metres.
    :ivar normals: (K, 3) the surface normals, parent frame.
    :ivar residuals: (K,) signed point-to-plane distances, metres.
    :ivar fitness: share of the frame's child points within the distance of a parent point.
    """

    arms: np.ndarray
    normals: np.ndarray
    residuals: np.ndarray
    fitness: float


def pairs(frame: FrameClouds, T: np.ndarray, distance: float) -> Pairs:
    """Return the point-to-plane pairs of ``frame`` under ``T`` within ``distance`` metres."""
    R, t = T[:3, :3], T[:3, 3]
    child = frame.child if frame.child_queries is None else frame.child[frame.child_queries]
    parent = (frame.parent if frame.parent_queries is None
              else frame.parent[frame.parent_queries])
    rotated = child @ R.T
    dist, nn = frame.parent_tree.query(rotated + t, k=1, distance_upper_bound=distance)
    close = np.isfinite(dist)
    fitness = float(close.mean()) if len(close) else 0.0
    close[close] = np.isfinite(frame.parent_normals[nn[close], 0])
    arms = rotated[close]
    n = frame.parent_normals[nn[close]]
    r = np.einsum('ij,ij->i', n, arms + t - frame.parent[nn[close]])
    # parent points against the child's surfaces, found in the child frame
    back = (parent - t) @ R
    dist, nn = frame.child_tree.query(back, k=1, distance_upper_bound=distance)
    near = np.isfinite(dist)
    near[near] = np.isfinite(frame.child_normals[nn[near], 0])
    m = frame.child_normals[nn[near]] @ R.T
    q_arms = parent[near] - t
    r_back = np.einsum('ij,ij->i', m, frame.child[nn[near]] @ R.T - q_arms)
    return Pairs(np.vstack([arms, q_arms]), np.vstack([n, m]), np.concatenate([r, r_back]),
                 fitness)


def jacobian(p: Pairs) -> np.ndarray:
    """Return the (K, 6) Jacobian ``[n, arm x n]`` of the residuals (module convention)."""
    return np.hstack([p.normals, np.cross(p.arms, p.normals)])


def surface_normals(points: np.ndarray, tree: cKDTree, radius: float,
                    neighbours: int = 10) -> np.ndarray:
    """
    Return (N, 3) unit normals of ``points`` where a surface defines them, NaN elsewhere.

    A normal is the least-variance direction of the point's ``neighbours`` nearest points
    within ``radius`` metres. Where they lie along a line (a single far scan ring, an edge:
    the second-largest variance below a twentieth of the largest) the plane through them
    is arbitrary and its normal would constrain motions the scene does not; such points,
    and those with fewer than three neighbours, get NaN and take no part in the joint
    problem.
    """
    dist, nn = tree.query(points, k=neighbours, distance_upper_bound=radius)
    ok = np.isfinite(dist)
    nn = np.where(ok, nn, 0)
    weights = ok.astype(np.float64)
    count = weights.sum(axis=1)
    neigh = points[nn]
    mean = (neigh * weights[..., None]).sum(axis=1) / np.maximum(count, 1)[:, None]
    centred = (neigh - mean[:, None, :]) * weights[..., None]
    cov = np.einsum('nki,nkj->nij', centred, centred) / np.maximum(count, 1)[:, None, None]
    eig, vec = np.linalg.eigh(cov)
    normals = vec[:, :, 0].copy()
    defined = (count >= 3) & (eig[:, 1] >= 0.05 * eig[:, 2]) & (eig[:, 2] > 0)
    normals[~defined] = np.nan
    return normals


def thinned(frame: FrameClouds, max_points: int) -> FrameClouds:
    """Return ``frame`` with at most ``max_points`` query points per cloud (an even stride)."""
    def pick(n: int) -> np.ndarray | None:
        return None if n <= max_points else np.linspace(0, n - 1, max_points).astype(int)

    return dataclasses.replace(frame, child_queries=pick(len(frame.child)),
                               parent_queries=pick(len(frame.parent)))


def perturb(T: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """Apply ``delta = (dt, dphi)`` to ``T`` in the module's convention."""
    out = np.asarray(T, dtype=np.float64).copy()
    out[:3, :3] = Rotation.from_rotvec(delta[3:]).as_matrix() @ out[:3, :3]
    out[:3, 3] += delta[:3]
    return out


def difference(T: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Return ``delta`` (module convention) with ``perturb(reference, delta) == T``."""
    rot = Rotation.from_matrix(T[:3, :3] @ reference[:3, :3].T).as_rotvec()
    return np.concatenate([T[:3, 3] - reference[:3, 3], rot])


def refine(frames: list[FrameClouds], initial: np.ndarray, distances: list[float],
           iterations: int = ITERATIONS) -> np.ndarray:
    """
    Gauss-Newton on the pooled point-to-plane residuals of ``frames``, from ``initial``.

    Runs once per distance of ``distances`` (metres, coarse to fine); each stage stops
    when a step moves the child points by less than a thousandth of its distance.
    """
    T = np.asarray(initial, dtype=np.float64).copy()
    radius = max(_radius(frames), 1e-9)
    for distance in distances:
        for _ in range(iterations):
            H, g, count = np.zeros((6, 6)), np.zeros(6), 0
            for frame in frames:
                p = pairs(frame, T, distance)
                J = jacobian(p)
                H += J.T @ J
                g += J.T @ p.residuals
                count += len(p.residuals)
            if count < 6:
                break
            H += 1e-9 * np.trace(H) / 6 * np.eye(6)
            delta = np.linalg.solve(H, -g)
            T = perturb(T, delta)
            if np.linalg.norm(delta[:3]) + radius * np.linalg.norm(delta[3:]) < 1e-3 * distance:
                break
    return T


def information(frames: list[FrameClouds], T: np.ndarray,
                distance: float) -> tuple[np.ndarray, float, int]:
    """
    Return ``(H, sum of squared residuals, K)`` of the pooled pairs under ``T``.

    ``H = sum J^T J`` is the 6x6 information of unit-variance residuals (module
    convention); K is the number of pairs.
    """
    H, ssr, count = np.zeros((6, 6)), 0.0, 0
    for frame in frames:
        p = pairs(frame, T, distance)
        J = jacobian(p)
        H += J.T @ J
        ssr += float(p.residuals @ p.residuals)
        count += len(p.residuals)
    return H, ssr, count


def overlap(frame: FrameClouds, T: np.ndarray, distance: float) -> tuple[float, float]:
    """
    Return (child share, parent share) of points within ``distance`` of the other cloud.

    The child share is the fitness (of the child's points, those near a parent point under
    ``T``); the parent share is that of the parent points near a moved child point.
    """
    moved = apply_transform(T, frame.child)
    ahead = np.isfinite(frame.parent_tree.query(moved, k=1, distance_upper_bound=distance)[0])
    back_points = apply_transform(np.linalg.inv(T), frame.parent)
    back = np.isfinite(frame.child_tree.query(back_points, k=1,
                                              distance_upper_bound=distance)[0])
    return float(ahead.mean()), float(back.mean())


def _radius(frames: list[FrameClouds]) -> float:
    """RMS distance of the child points from the child origin, metres."""
    sq = [np.sum(f.child ** 2, axis=1) for f in frames if len(f.child)]
    return float(np.sqrt(np.mean(np.concatenate(sq)))) if sq else 0.0
