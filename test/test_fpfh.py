"""
FPFH and its neighbour search against Open3D's FPFH and a k-d tree's neighbours.

frontend/fpfh.py, frontend/neighbours.py and their compiled functions
(frontend/compiled/fpfh.py, neighbours.py).
"""

import math

from cgags_ros.config.frontend import FrontEndConfig
from cgags_ros.frontend import compiled, fpfh, neighbours
from cgags_ros.frontend.compiled import fpfh as compiled_fpfh
from cgags_ros.frontend.compiled import neighbours as compiled_neighbours
from cgags_ros.frontend.features import downsample, estimate_normals, extract_features
from cgags_ros.frontend.fpfh import fpfh_with_spacing
from cgags_ros.frontend.neighbours import NeighbourGrid
from cgags_ros.geometry import point_resolution
from cgags_ros.io.clouds import read_cloud
from cgags_ros.open3d_import import open3d as o3d
import numpy as np
import pytest
from scipy.spatial import cKDTree


@pytest.fixture(scope='module', params=[('objects/stanford_bunny_scans/bun000.ply', 0.003),
                                        ('lidar/small_gicp/source.ply', 0.4)])
def cloud(request, data_dir):
    """Downsampled points and oriented normals of a real scan, and its voxel size."""
    path, voxel = request.param
    points = downsample(read_cloud(data_dir / path), voxel, 10)
    return points, estimate_normals(points, voxel, FrontEndConfig()), voxel


def _fpfh(points, normals, voxel, cfg, workers=1, max_nn=fpfh.FPFH_MAX_NN):
    """Return the front end's FPFH descriptors, without the spacing."""
    return fpfh_with_spacing(points, normals, voxel, cfg, workers, max_nn)[0]


def _neighbours_by_row(points, radius, max_nn, workers=1):
    """Each point's neighbour rows, their count and its nearest-other distance, in row order."""
    grid = NeighbourGrid.build(points, radius)
    nearest = np.empty(len(points))
    lists = grid.neighbours(0, len(points), max_nn, nearest, workers)
    rows, counts = np.empty_like(lists.nbr), np.empty_like(lists.count)
    rows[grid.order], counts[grid.order] = lists.nbr, lists.count  # cell order to row order
    return rows, counts, nearest


def _open3d_fpfh(points, normals, voxel, cfg, max_nn=fpfh.FPFH_MAX_NN):
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pcd.normals = o3d.utility.Vector3dVector(normals)
    param = o3d.geometry.KDTreeSearchParamHybrid(radius=cfg.fpfh_radius_factor * voxel,
                                                 max_nn=max_nn)
    return np.asarray(o3d.pipelines.registration.compute_fpfh_feature(pcd, param).data).T


@pytest.mark.parametrize('max_nn', [fpfh.FPFH_MAX_NN, 20])
def test_fpfh_equals_open3d(cloud, max_nn):
    points, normals, voxel = cloud
    cfg = FrontEndConfig()
    ours = _fpfh(points, normals, voxel, cfg, workers=2, max_nn=max_nn)
    ref = _open3d_fpfh(points, normals, voxel, cfg, max_nn)
    # Rows whose max_nn-th neighbour ties with the next may pick another neighbour than
    # Open3D (ties go to the lower row here): a handful at most on real scans.
    close = np.abs(ours - ref).max(axis=1) < 1e-9
    assert close.mean() > 0.99
    assert np.array_equal(ours, _fpfh(points, normals, voxel, cfg, workers=1, max_nn=max_nn))


def test_radius_neighbours_are_the_nearest_within_the_radius(cloud):
    points, _, voxel = cloud
    radius, max_nn = 5 * voxel, 30
    tree = cKDTree(points)
    nbr, count, nearest = _neighbours_by_row(points, radius, max_nn, workers=2)
    dist, idx = tree.query(points, k=max_nn + 1, distance_upper_bound=radius)
    # the nearest other point: the same distances as the k-d tree's, to the bit
    np.testing.assert_array_equal(nearest, np.where(np.isfinite(dist[:, 1]), dist[:, 1], np.inf))
    for i in range(0, len(points), 7):
        within = np.isfinite(dist[i, :max_nn])
        assert count[i] == within.sum()
        got = nbr[i, :count[i]]
        np.testing.assert_allclose(np.sort(np.sum((points[got] - points[i]) ** 2, axis=1)),
                                   dist[i, :max_nn][within] ** 2, rtol=1e-12, atol=1e-15)
        if not np.isfinite(dist[i, max_nn]) or dist[i, max_nn] > dist[i, max_nn - 1]:
            assert set(got) == set(idx[i, :max_nn][within])  # no tie at the cut: the same set


def test_neighbours_without_the_column_table_are_the_same(cloud, monkeypatch):
    """A grid too wide for the column table finds its cells among all keys: same answers."""
    points, _, voxel = cloud
    with_table = _neighbours_by_row(points, 5 * voxel, 30)
    assert len(NeighbourGrid.build(points, 5 * voxel).column_start) > 1
    monkeypatch.setattr(neighbours, '_MAX_COLUMNS', 0)
    points_wide = np.vstack([points, points[:1] + 1e4 * voxel])  # a far point: 8 M > 8 n
    assert len(NeighbourGrid.build(points_wide, 5 * voxel).column_start) == 0
    without = _neighbours_by_row(points_wide, 5 * voxel, 30)
    n = len(points)
    assert np.array_equal(with_table[1], without[1][:n])
    assert np.array_equal(with_table[2], without[2][:n])
    for i in range(n):
        assert np.array_equal(with_table[0][i, :with_table[1][i]], without[0][i, :without[1][i]])


def test_select_keeps_the_smallest_with_ties_to_the_lower_row():
    rng = np.random.default_rng(5)
    for n, m in [(50, 10), (200, 100), (7, 6), (30, 1)]:
        d = rng.integers(0, 12, n).astype(float)  # many ties
        j = rng.permutation(n).astype(np.int32)  # rows, as the neighbour lists hold them
        want = sorted(zip(d, j))[:m]
        dd, jj = d.copy(), j.copy()
        compiled_neighbours._select(dd, jj, n, m)
        assert sorted(zip(dd[:m], jj[:m])) == want


def test_fpfh_in_blocks_equals_one_pass(cloud, monkeypatch):
    """A cloud too large to keep every neighbour list is done in blocks: same values."""
    points, normals, voxel = cloud
    cfg = FrontEndConfig()
    whole = _fpfh(points, normals, voxel, cfg, workers=2)
    monkeypatch.setattr(fpfh, '_NEIGHBOUR_BYTES', 4 * fpfh.FPFH_MAX_NN * 700)  # 700 rows a block
    assert len(points) > 1400
    np.testing.assert_array_equal(_fpfh(points, normals, voxel, cfg, workers=2), whole)


def test_a_stray_point_far_away_falls_back_to_open3d(cloud):
    """A grid too large to index (a point 1e9 voxels away): Open3D's FPFH, same values."""
    points, normals, voxel = cloud
    far = np.vstack([points, points[:1] + 1e9 * voxel])
    far_normals = np.vstack([normals, normals[:1]])
    cfg = FrontEndConfig()
    assert NeighbourGrid.build(far, cfg.fpfh_radius_factor * voxel) is None
    ours, spacing = fpfh_with_spacing(far, far_normals, voxel, cfg)
    assert np.abs(ours - _open3d_fpfh(far, far_normals, voxel, cfg)).max() < 1e-9
    assert spacing is None  # no neighbour search ran
    assert NeighbourGrid.build(far, voxel) is None  # too far for a grid of any FPFH radius


def test_resolution_from_the_fpfh_search_equals_the_k_d_tree(cloud):
    """The features' point resolution is point_resolution's number, isolated points too."""
    points, _, voxel = cloud
    stray = np.vstack([points, points.max(axis=0) + 50 * voxel])  # none within the radius
    for pts in (points, stray):
        features = extract_features(pts, voxel, FrontEndConfig(), workers=2)
        assert features.resolution == point_resolution(features.points)


def test_angle_bins_equal_atan2_bins():
    """The polynomial angle bins equal Open3D's atan2 bins, edges and special values too."""
    rng = np.random.default_rng(5)
    y, x = rng.normal(size=(2, 200000)) * rng.choice([1e-9, 1.0, 1e6], (2, 200000))
    edges = -np.pi + 2 * np.pi * np.arange(12) / 11  # every bin edge, and just beside it
    angles = np.concatenate([edges, np.nextafter(edges, 10), np.nextafter(edges, -10),
                             edges + 1e-9, edges - 1e-9])
    y = np.concatenate([y, np.sin(angles), [0.0, -0.0, 0.0, -0.0, 1.0, np.nan, 0.0]])
    x = np.concatenate([x, np.cos(angles), [0.0, 0.0, -0.0, -0.0, np.nan, 1.0, -1.0]])
    # The C library's atan2, as Open3D calls it: numpy's own arctan2 differs in the last bit on
    # some builds (numpy 1.26's SIMD loops), which moves values that sit on a bin edge.
    atan2 = np.array([math.atan2(a, b) for a, b in zip(y, x)])
    expected = np.clip(np.floor(11.0 * (atan2 + np.pi) / (2.0 * np.pi)), 0, 10)
    expected[np.isnan(expected)] = 0  # NaN: the compiled floor-and-clamp gives bin 0
    got = [compiled_fpfh._angle_bin(a, b) for a, b in zip(y, x)]
    assert np.array_equal(got, expected)


def test_spfh_equals_its_pair_by_pair_reference(cloud):
    """
    The branch-free SPFH pass equals Open3D's pair features computed one pair at a time.

    A flat patch with identical normals is added: its pairs tie (both normals orthogonal
    to the line) and take the exact path; a duplicated point gives degenerate pairs.
    """
    points, normals, voxel = cloud
    rng = np.random.default_rng(2)
    patch = np.c_[rng.uniform(0, 6 * voxel, (60, 2)), np.zeros(60)]
    flat = points.min(axis=0) - 20 * voxel + patch
    pts = np.vstack([points[:800], flat, points[:1]])
    nrm = np.vstack([normals[:800], np.tile([0.0, 0.0, 1.0], (60, 1)), normals[:1]])
    nbr, count, _ = _neighbours_by_row(pts, FrontEndConfig().fpfh_radius_factor * voxel, 100)
    order = np.arange(len(pts))
    got = np.zeros((len(pts), 33))
    compiled.spfh_pass(pts, nrm, compiled.NeighbourLists(order, 0, nbr, count), 0, len(pts), got)
    want = np.zeros((len(pts), 33))
    for i in range(len(pts)):
        c = count[i]
        for j in nbr[i, :c]:
            if j != i:
                b0, b1, b2 = compiled_fpfh._pair_bins(pts, nrm, i, j)
                for b in (b0, 11 + b1, 22 + b2):
                    want[i, b] += 100.0 / (c - 1)
    np.testing.assert_array_equal(got, want)
    assert want[800:860].any()
