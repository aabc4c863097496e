"""cgags_ros.pipeline.covariance: the covariance follows the geometry and holds on real data."""

from __future__ import annotations

from cgags_ros.fitted import COVARIANCE_FLOOR_POSITION, WRONG_POSITION_VOXELS, WRONG_ROTATION
from cgags_ros.pipeline.covariance import overlap_covariance, pose_covariance, with_confidence
import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

CHI2_6_95 = 12.592  # 95 % quantile of the chi-square law with 6 degrees of freedom


def _floor_and_wall(rng: np.random.Generator, block: float, step: float = 0.05):
    """
    Return a noisy source, target and target normals: a 4 m floor, a wall along x, a block.

    Floor and wall fix y, z and every rotation; only the block (``block`` metres a side,
    on the floor against nothing) fixes x.
    """
    u = np.arange(0.0, 4.0, step)
    a, b = np.meshgrid(u, u)
    floor = np.column_stack([a.ravel(), b.ravel(), np.zeros(a.size)])
    wall = np.column_stack([a.ravel(), np.zeros(a.size), b.ravel() / 2])
    s = np.arange(0.0, block, step)
    c, d = np.meshgrid(s, s)
    side = np.column_stack([np.full(c.size, 2.0), 1.0 + c.ravel(), d.ravel()])
    points = np.vstack([floor, wall, side])
    normals = np.vstack([np.tile([0, 0, 1.0], (len(floor), 1)),
                         np.tile([0, 1.0, 0], (len(wall), 1)),
                         np.tile([1.0, 0, 0], (len(side), 1))])
    return (points + rng.normal(scale=0.02, size=points.shape),
            points + rng.normal(scale=0.02, size=points.shape), normals)


def test_pose_covariance_reflects_geometry():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(400, 3)) * [1.0, 1.0, 0.01]  # a thin slab: rotations about x/y
    noise = rng.normal(scale=0.01, size=src.shape)       # are constrained less tightly than z
    cov = pose_covariance(src, src + noise, np.eye(4))
    assert np.allclose(cov, cov.T)
    sd = np.sqrt(np.diag(cov))
    assert sd[:3] == pytest.approx([0.01 / 20] * 3, rel=0.3)  # sigma / sqrt(N)
    assert sd[3] > 1.2 * sd[5] and sd[4] > 1.2 * sd[5]
    assert pose_covariance(src[:2], src[:2], np.eye(4))[0, 0] == 1e6


def test_the_pipeline_result_carries_the_covariance_of_its_estimate():
    """register_clouds() returns the covariance the node publishes, also in summary()."""
    from cgags_ros.config import PipelineConfig
    from cgags_ros.pipeline.register import terrain_patch
    from cgags_ros.geometry import make_transform, rotation_error_deg
    from cgags_ros.pipeline import register_clouds

    target = terrain_patch(np.random.default_rng(3))
    c, s = np.cos(0.3), np.sin(0.3)
    T_gt = make_transform(np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]),
                          [0.4, -0.2, 0.1])
    source = (target - T_gt[:3, 3]) @ T_gt[:3, :3]  # T_gt maps source onto target
    result = register_clouds(source, target, config=PipelineConfig(voxel_size=0.15))
    assert result.valid, result.reason
    assert rotation_error_deg(result.transform, T_gt) < 2.0
    cov = result.covariance
    assert cov.shape == (6, 6) and np.allclose(cov, cov.T)
    assert np.all(np.linalg.eigvalsh(cov) > 0) and np.all(np.diag(cov) < 1.0)
    from cgags_ros.pipeline import cached_features

    config = PipelineConfig(voxel_size=0.15)
    fs = cached_features(source, 0.15, config.frontend, 'source')
    ft = cached_features(target, 0.15, config.frontend, 'target')
    expected = overlap_covariance(fs.points, ft.points, ft.normals, ft.tree, result.transform,
                                  1.5 * 0.15, 0.15)
    np.testing.assert_allclose(cov, with_confidence(expected, result.confidence, 0.15))
    assert np.array(result.summary()['covariance']) == pytest.approx(cov)
    # No estimate: no support, the "unknown" variances
    empty = register_clouds(source[:5], target, config=PipelineConfig(voxel_size=0.15))
    assert not empty.valid and np.all(np.diag(empty.covariance) == 1e6)


def test_the_covariance_opens_by_the_chance_that_the_pose_is_wrong():
    """A sure pose keeps its covariance; a doubtful one opens towards a wrong pose's spread."""
    cov, voxel = np.diag([1e-4] * 3 + [1e-5] * 3), 0.05
    np.testing.assert_array_equal(with_confidence(cov, 1.0, voxel), cov)
    W = np.diag([(WRONG_POSITION_VOXELS * voxel) ** 2] * 3 + [WRONG_ROTATION ** 2] * 3)
    assert WRONG_POSITION_VOXELS > 0 and WRONG_ROTATION > 0
    np.testing.assert_allclose(with_confidence(cov, 0.0, voxel), cov + W)
    doubt = [np.trace(with_confidence(cov, p, voxel) - cov) for p in (0.5, 0.9, 0.99, 0.999)]
    assert doubt == sorted(doubt, reverse=True) and doubt[-1] < 1e-3 * doubt[0]
    # Wrong by a metre and 90 degrees: far outside a sure pose's ellipsoid, inside that of
    # a pose which is as likely wrong as right.
    e = np.array([1.0, 0, 0, 0, 0, np.pi / 2])
    assert e @ np.linalg.solve(with_confidence(cov, 1.0, voxel), e) > 1e3
    assert e @ np.linalg.solve(with_confidence(cov, 0.5, voxel), e) < CHI2_6_95
    # The position's doubt goes with the voxel: a tenth of it, a tenth of the spread.
    fine = with_confidence(cov, 0.0, voxel / 10) - cov
    np.testing.assert_allclose(np.sqrt(np.diag(fine)[:3]), WRONG_POSITION_VOXELS * voxel / 10)
    np.testing.assert_allclose(np.diag(fine)[3:], WRONG_ROTATION ** 2)


def test_4dof_covariance_has_no_roll_or_pitch_and_matches_the_yaw_only_fit():
    rng = np.random.default_rng(2)
    src = rng.normal(size=(300, 3)) * [2.0, 1.0, 0.3]
    noise = rng.normal(scale=0.01, size=src.shape)
    cov6 = pose_covariance(src, src + noise, np.eye(4))
    cov4 = pose_covariance(src, src + noise, np.eye(4), gravity=np.array([0.0, 0.0, 2.0]))
    assert np.allclose(cov4, cov4.T)
    assert np.all(cov4[3:5] == 0) and np.all(cov4[:, 3:5] == 0)  # roll, pitch fixed
    assert cov4[5, 5] > 0 and np.all(np.diag(cov4)[:3] > 0)
    # Fixing roll and pitch can only tighten the others (Schur complement), up to the
    # residual variance's degrees of freedom (3K - 4 instead of 3K - 6).
    scale = (3 * 300 - 6) / (3 * 300 - 4)
    keep = [0, 1, 2, 5]
    assert np.all(np.diag(cov4)[keep] <= np.diag(cov6)[keep] * (1 + 1e-9) / scale)
    # A tilted up axis: the yaw variance lies along it.
    g = np.array([0.0, 1.0, 1.0]) / np.sqrt(2)
    tilted = pose_covariance(src, src + noise, np.eye(4), gravity=g)
    rot = tilted[3:, 3:]
    assert np.allclose(rot, rot[1, 1] * 2 * np.outer(g, g))


def test_moved_covariance_matches_sampled_base_poses():
    from cgags_ros.geometry import make_transform
    from cgags_ros.pipeline.covariance import moved_covariance
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(5)
    T = make_transform(Rotation.from_euler('xyz', [5, -10, 40], degrees=True).as_matrix(),
                       [1.0, 2.0, 0.5])
    sensor_base = make_transform(Rotation.from_euler('z', 30, degrees=True).as_matrix(),
                                 [-0.4, 0.1, -1.2])  # base 1.2 m below the sensor
    A = rng.normal(size=(6, 6)) * 1e-2
    cov = A @ A.T
    moved = moved_covariance(cov, T, sensor_base)
    # Monte Carlo with the same perturbation model: t' = t + dt, R' = exp([dphi]x) R.
    d = rng.multivariate_normal(np.zeros(6), cov, size=20000)
    base = T @ sensor_base
    samples = []
    for dt, dphi in zip(d[:, :3], d[:, 3:]):
        Tp = make_transform(Rotation.from_rotvec(dphi).as_matrix() @ T[:3, :3], T[:3, 3] + dt)
        Bp = Tp @ sensor_base
        rot = Rotation.from_matrix(Bp[:3, :3] @ base[:3, :3].T).as_rotvec()
        samples.append(np.concatenate([Bp[:3, 3] - base[:3, 3], rot]))
    np.testing.assert_allclose(np.cov(np.array(samples).T), moved, atol=2e-5)
    assert not np.allclose(moved[:3, :3], cov[:3, :3])  # the lever arm matters


def test_map_to_odom_composes_back_to_the_base_pose():
    from cgags_ros.geometry import make_transform
    from cgags_ros.pipeline.covariance import map_to_odom
    from scipy.spatial.transform import Rotation

    T_map_base = make_transform(Rotation.from_euler('z', 70, degrees=True).as_matrix(),
                                [5.0, -3.0, 0.0])
    T_odom_base = make_transform(Rotation.from_euler('z', -20, degrees=True).as_matrix(),
                                 [1.0, 0.5, 0.0])
    np.testing.assert_allclose(map_to_odom(T_map_base, T_odom_base) @ T_odom_base, T_map_base,
                               atol=1e-12)


def test_overlap_covariance_opens_along_the_motion_the_overlap_leaves_weak():
    """Shrinking the only structure that fixes x loosens x, not the other motions."""
    sd = {}
    for block in (0.1, 1.0):
        src, dst, normals = _floor_and_wall(np.random.default_rng(4), block)
        cov = overlap_covariance(src, dst, normals, cKDTree(dst), np.eye(4), 0.075, 0.05)
        assert np.allclose(cov, cov.T) and np.all(np.linalg.eigvalsh(cov) > 0)
        sd[block] = np.sqrt(np.diag(cov))
        # The floor: no position sigma below it, whatever the fit.
        assert np.all(sd[block][:3] >= COVARIANCE_FLOOR_POSITION * 0.05 * (1 - 1e-9))
    assert sd[0.1][0] > 1.5 * sd[1.0][0]
    np.testing.assert_allclose(sd[0.1][1:], sd[1.0][1:], rtol=0.2)
    # With nothing at all to fix x the information is singular: the pose is unknown.
    src, dst, normals = _floor_and_wall(np.random.default_rng(4), 0.0)
    unknown = overlap_covariance(src, dst, normals, cKDTree(dst), np.eye(4), 0.075, 0.05)
    assert np.all(np.diag(unknown) == 1e6)


def test_a_right_3dmatch_pose_lies_inside_its_95_percent_ellipsoid(redkitchen_pair):
    """NEES of a right, valid 3DMatch estimate against the benchmark's truth, and sharpness."""
    from cgags_ros.pipeline import register_clouds

    src, tgt, gt = redkitchen_pair(0, 2)
    result = register_clouds(src, tgt, voxel_size=0.05)
    assert result.valid, result.reason
    T = result.transform
    error = np.concatenate([gt[:3, 3] - T[:3, 3],
                            Rotation.from_matrix(gt[:3, :3] @ T[:3, :3].T).as_rotvec()])
    nees = error @ np.linalg.solve(result.covariance, error)
    assert nees <= CHI2_6_95
    # Sharp, not inflated: the position sigma within two voxels, and the old point-to-point
    # covariance over the keypoints would have put the truth far outside its ellipsoid.
    assert np.sqrt(np.trace(result.covariance[:3, :3])) <= 2 * 0.05
    old = pose_covariance(result.inlier_source_points, result.inlier_target_points, T)
    assert error @ np.linalg.solve(old, error) > 2 * CHI2_6_95
