"""cgags_ros.frontend.keypoints: bounded source keypoints for matching, on real LiDAR scans."""

import dataclasses

from cgags_ros.config import PipelineConfig
from cgags_ros.config.fields import update_from_flat
from cgags_ros.config.frontend import FrontEndConfig
from cgags_ros.frontend.features import extract_features
from cgags_ros.frontend.keypoints import match_keypoints, select_keypoints
from cgags_ros.frontend.matching import match_features
from cgags_ros.geometry import rotation_error_deg, translation_error
from cgags_ros.io.clouds import read_cloud
from cgags_ros.pipeline import clear_feature_cache, register_clouds
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

VOXEL = 0.5  # metres: ~2700 points a scan
KEYPOINTS = 1000


@pytest.fixture(scope='module')
def lidar(data_dir):
    """small_gicp source/target scans, their features and the source->target transform."""
    folder = data_dir / 'lidar/small_gicp'
    src, dst = read_cloud(folder / 'source.ply'), read_cloud(folder / 'target.ply')
    cfg = FrontEndConfig()
    return (src, dst, extract_features(src, VOXEL, cfg), extract_features(dst, VOXEL, cfg),
            np.loadtxt(folder / 'T_target_source.txt'))


def test_keypoints_are_bounded_spread_and_reproducible(lidar):
    points = lidar[2].points
    keep = select_keypoints(points, KEYPOINTS, VOXEL)
    assert 0.8 * KEYPOINTS <= len(keep) <= KEYPOINTS
    assert np.all(np.diff(keep) > 0)
    assert np.array_equal(keep, select_keypoints(points, KEYPOINTS, VOXEL))
    # Spread: every downsampled point has a keypoint within a few voxels.
    dist, _ = lidar[2].tree.query(points[keep])
    gap = np.max(np.min(np.linalg.norm(points[:, None] - points[keep][None], axis=2), axis=1))
    assert dist.max() == 0.0 and gap < 4 * VOXEL * np.sqrt(len(points) / KEYPOINTS)


def test_zero_and_large_bounds_match_every_point(lidar):
    fs, ft = lidar[2], lidar[3]
    ref = match_features(fs.descriptors, ft.descriptors, FrontEndConfig())
    for bound in (0, len(fs.points)):
        cfg = FrontEndConfig(max_keypoints=bound)
        got = match_keypoints(fs.points, fs.descriptors, ft.descriptors, VOXEL, cfg)
        for f in dataclasses.fields(ref):
            assert np.array_equal(getattr(got, f.name), getattr(ref, f.name))


def test_exact_mutual_matches_at_keypoints_are_kept(lidar):
    fs, ft = lidar[2], lidar[3]
    cfg = FrontEndConfig(max_correspondences=0, max_keypoints=KEYPOINTS)
    keep = select_keypoints(fs.points, KEYPOINTS, VOXEL)
    full = match_features(fs.descriptors, ft.descriptors, cfg)
    got = match_keypoints(fs.points, fs.descriptors, ft.descriptors, VOXEL, cfg)
    assert np.isin(got.source_index, keep).all()
    at_keypoints = np.isin(full.source_index, keep)
    expected = set(zip(full.source_index[at_keypoints], full.target_index[at_keypoints]))
    assert expected <= set(zip(got.source_index, got.target_index))


def test_registration_with_bounded_keypoints(lidar):
    src, dst, _, _, T = lidar
    R = Rotation.from_euler('zyx', [130, 40, -70], degrees=True).as_matrix()
    H = np.eye(4)
    H[:3, :3] = R
    config = update_from_flat(PipelineConfig(), {'frontend.max_keypoints': KEYPOINTS})
    clear_feature_cache()
    result = register_clouds(src @ R.T, dst, voxel_size=VOXEL, config=config)
    gt = T @ np.linalg.inv(H)
    assert result.valid, result.reason
    assert rotation_error_deg(result.transform, gt) < 2.0
    assert translation_error(result.transform, gt) < 0.3
