"""cgags_ros.pipeline.covariance: the pose covariance follows the inlier geometry."""

from __future__ import annotations

from cgags_ros.pipeline.covariance import pose_covariance
import numpy as np
import pytest


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
    expected = pose_covariance(result.inlier_source_points, result.inlier_target_points,
                               result.transform)
    np.testing.assert_allclose(cov, expected)
    assert np.array(result.summary()['covariance']) == pytest.approx(cov)
    # No estimate: no support, the "unknown" variances
    empty = register_clouds(source[:5], target, config=PipelineConfig(voxel_size=0.15))
    assert not empty.valid and np.all(np.diag(empty.covariance) == 1e6)


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
