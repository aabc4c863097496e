"""
The check of a map query's truth: where its surfaces settle on the map, started from it.

A map of ``bench.maps`` is fused from other scans' logged poses (the 3DMatch fragments'
benchmark poses). Where the map disagrees with a query's logged pose, a localizer that
aligns the query with the map is counted wrong against the logged pose although it is
right against the map it was given (``bench.truth_settle`` checks the benchmark's pairs
the same way). Point-to-plane ICP of the query onto the map, both on a fine grid
(:data:`VOXEL`), started from the logged pose and narrowed in :data:`DISTANCES`, settles it
where the map's surfaces put it. A pose is then right when it is within the limits of the
logged pose or of the settled one (:func:`bench.maps.outcome`); the settings are fixed,
not fitted to any estimate.
"""

from __future__ import annotations

from collections.abc import Hashable

import numpy as np
import open3d as o3d

VOXEL = 0.02  # metres: the map and the queries are settled on this grid
DISTANCES = (0.1, 0.05, 0.03)  # metres: the ICP's correspondence distances, one stage each
ITERATIONS = 200  # each stage's, at most


def settled(points: np.ndarray, normals: np.ndarray,
            queries: list[tuple[Hashable, np.ndarray, np.ndarray | None]]
            ) -> dict[Hashable, np.ndarray]:
    """
    Return each query's settled truth (4x4, map frame) by its label (any hashable).

    ``points``, ``normals``: the map's (N, 3); ``queries``: (label, scan in its sensor frame,
    logged truth sensor -> map); a query without a truth (from outside the map) has none.
    """
    asked = [(label, scan, truth) for label, scan, truth in queries if truth is not None]
    if not asked:
        return {}
    target = _cloud(points)
    target.normals = o3d.utility.Vector3dVector(np.asarray(normals, dtype=np.float64))
    target = target.voxel_down_sample(VOXEL)
    target.normalize_normals()
    icp = o3d.pipelines.registration
    criteria = icp.ICPConvergenceCriteria(relative_fitness=1e-7, relative_rmse=1e-7,
                                          max_iteration=ITERATIONS)
    out = {}
    for label, scan, truth in asked:
        source = _cloud(scan).voxel_down_sample(VOXEL)
        T = np.asarray(truth, dtype=np.float64)
        for distance in DISTANCES:
            T = np.asarray(icp.registration_icp(
                source, target, distance, T, icp.TransformationEstimationPointToPlane(),
                criteria).transformation).copy()
        out[label] = T
    return out


def with_settled(built: dict) -> dict:
    """
    Return a map of ``bench.maps`` with its queries' settled truths (``'settled'``).

    A map's sequences get theirs too (``'settled_sequences'``: a list of each sequence's
    scans' settled truths, in the sequences' order).
    """
    runs = built.get('sequences', [])
    steps = [(('sequence', i, k), scan, truth) for i, (_, scans, truths) in enumerate(runs)
             for k, (scan, truth) in enumerate(zip(scans, truths))]
    # One call: the map's fine grid is built once for the queries and the sequences.
    found = settled(built['points'], built['normals'], built['queries'] + steps)
    return {**built, 'settled': {label: T for label, T in found.items()
                                 if not isinstance(label, tuple)},
            'settled_sequences': [[found['sequence', i, k] for k in range(len(scans))]
                                  for i, (_, scans, _) in enumerate(runs)]}


def _cloud(points: np.ndarray) -> o3d.geometry.PointCloud:
    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(
        np.ascontiguousarray(points, dtype=np.float64)))
