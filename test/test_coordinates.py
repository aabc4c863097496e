"""
Clouds anywhere: every entry point gives at 10^5-10^7 m from the origin what it gives near it.

The bundled LiDAR pair (test/fixtures/small_gicp, real scans), its source turned 70 degrees,
is moved as georeferenced clouds are (UTM, MGRS, ECEF magnitudes): both clouds together, or
the target alone (a map in UTM, a scan in its sensor frame). Each entry point's answer, taken
back to the origin, must match the answer at the origin within 1 cm and 0.01 degrees.
"""

from __future__ import annotations

from pathlib import Path
import warnings

from cgags_ros.calibration.frames import Frame, gather
from cgags_ros.config import pipeline_config_from
from cgags_ros.coordinates import (coarse_coordinates, CoarseCoordinatesWarning, local_origin,
                                   SENSOR_REACH, to_local, translation)
from cgags_ros.errors import InvalidInputError
from cgags_ros.geometry import apply_transform, make_transform, rotation_error_deg
from cgags_ros.geometry import translation_error
from cgags_ros.io.clouds import read_cloud, write_cloud
from cgags_ros.pipeline import register_clouds
from cgags_ros.pipeline.map import load_map
from cgags_ros.registration import register_correspondences
from cgags_ros.relocalization.relocalizer import Relocalizer
from cgags_ros.tracking import Tracker
import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

FIXTURE = Path(__file__).resolve().parent / 'fixtures' / 'small_gicp'
MAGNITUDES = (1e5, 1e6, 1e7)
VOXEL = 0.3
SAME = (0.01, 0.01)  # m, deg: the same answer


def offset(magnitude: float, seed: int = 0) -> np.ndarray:
    """Return a georeferencing offset of ``magnitude`` metres in a seeded direction."""
    d = np.random.default_rng(seed).normal(size=3)
    return magnitude * d / np.linalg.norm(d)


def same(T, T_ref):
    return (translation_error(T, T_ref) < SAME[0]
            and rotation_error_deg(T, T_ref) < SAME[1])


@pytest.fixture(scope='module')
def pair():
    """Return (source turned, target, truth source -> target, the result at the origin)."""
    source = np.load(FIXTURE / 'source.npy').astype(np.float64)
    target = np.load(FIXTURE / 'target.npy').astype(np.float64)
    truth = np.loadtxt(FIXTURE / 'T_target_source.txt')
    turn = make_transform(Rotation.from_euler('zyx', [70, 5, -3], degrees=True).as_matrix(),
                          [2.0, -1.0, 0.3])
    turned = apply_transform(turn, source)
    truth = truth @ np.linalg.inv(turn)
    result = register_clouds(turned, target, voxel_size=VOXEL)
    assert result.valid and translation_error(result.transform, truth) < 0.1, result.reason
    return turned, target, truth, result


@pytest.fixture(scope='module')
def on_map_at_origin(pair, tmp_path_factory):
    """
    Return the pair's source registered onto its target as a map file at the origin.

    Against a map an accepted scan of few voxels is refined once more with its own points
    (pipeline/polish.py), a pair of clouds is not: the map's answer is the one to match.
    """
    source, target, truth, at_origin = pair
    path = tmp_path_factory.mktemp('origin') / 'map.ply'
    write_cloud(path, target)
    cfg = pipeline_config_from({'voxel_size': VOXEL})
    result = register_clouds(source, load_map(path, cfg), config=cfg)
    assert result.valid, result.reason
    # Within the refinement's reach of the pair's answer, and right as the pair's is.
    assert rotation_error_deg(result.transform, at_origin.transform) < 1.0
    assert translation_error(result.transform, at_origin.transform) < 0.1
    assert translation_error(result.transform, truth) < 0.1
    return result


@pytest.mark.parametrize('magnitude', MAGNITUDES)
def test_both_clouds_moved_together_register_as_at_the_origin(pair, magnitude):
    source, target, _, at_origin = pair
    d = offset(magnitude)
    result = register_clouds(source + d, target + d, voxel_size=VOXEL)
    assert result.valid, result.reason
    assert same(to_local(result.transform, d, d), at_origin.transform)
    # What the result says of points is said in the caller's frames.
    for points, cloud in ((result.inlier_source_points, source),
                          (result.inlier_target_points, target)):
        assert len(points) > 10
        assert cKDTree(cloud).query(points - d)[0].max() < VOXEL
    for c in result.candidates:
        assert np.isfinite(c.transform).all()
        assert abs(np.linalg.det(c.transform[:3, :3]) - 1) < 1e-9


@pytest.mark.parametrize('magnitude', MAGNITUDES)
def test_scans_in_utm_with_their_sensors_positions_keep_the_free_space_view(pair, magnitude):
    source, target, _, at_origin = pair
    d = offset(magnitude, seed=7)
    result = register_clouds(source + d, target + d, voxel_size=VOXEL, source_sensor=d,
                             target_sensor=d)
    assert result.valid, result.reason
    assert same(to_local(result.transform, d, d), at_origin.transform)
    assert abs(result.free_space_violation - at_origin.free_space_violation) < 1e-6
    unknown = register_clouds(source + d, target + d, voxel_size=VOXEL)
    assert np.isnan(unknown.free_space_violation)  # no sensor, no view to judge from


def test_a_sensor_position_must_be_three_finite_numbers(pair):
    source, target, _, _ = pair
    for bad in ([1.0, 2.0], [np.nan, 0.0, 0.0]):
        with pytest.raises(InvalidInputError, match='sensor position'):
            register_clouds(source, target, voxel_size=VOXEL, source_sensor=bad)


@pytest.mark.parametrize('magnitude', MAGNITUDES)
def test_a_scan_onto_a_georeferenced_target(pair, magnitude):
    source, target, _, at_origin = pair
    d = offset(magnitude, seed=1)
    result = register_clouds(source, target + d, voxel_size=VOXEL)
    assert result.valid, result.reason
    assert same(result.transform, translation(d) @ at_origin.transform)
    # The source's origin did not move: its covariance (about that origin) is the same, but
    # for the confidence it opens with (the target's normals face its centre, not its origin).
    assert np.allclose(result.covariance, at_origin.covariance, rtol=0.1, atol=1e-6)


@pytest.mark.parametrize('magnitude', MAGNITUDES)
def test_register_correspondences_at_any_offset(magnitude):
    rng = np.random.default_rng(3)
    src = rng.uniform(-20, 20, (400, 3))
    T = make_transform(Rotation.from_euler('z', 130, degrees=True).as_matrix(), [4, -7, 1])
    dst = apply_transform(T, src) + rng.normal(0, 0.02, src.shape)
    wrong = rng.random(len(src)) < 0.8
    dst[wrong] = rng.uniform(-20, 20, (int(wrong.sum()), 3))
    near = register_correspondences(src, dst, resolution=0.05, seed=0)
    ds, dt = offset(magnitude, 4), offset(magnitude, 5)
    far = register_correspondences(src + ds, dst + dt, resolution=0.05, seed=0)
    assert near.valid and far.valid, far.reason
    assert same(to_local(far.transform, ds, dt), near.transform)
    assert np.array_equal(far.inliers, near.inliers)


def test_a_georeferenced_map_file_keeps_its_doubles_and_is_cached_with_its_origin(
        pair, on_map_at_origin, tmp_path):
    source, target, _, _ = pair
    d = np.array([512345.678901, 5412345.678901, 265.4321])  # UTM easting, northing, height
    path = tmp_path / 'map.ply'
    write_cloud(path, target + d)
    assert np.array_equal(read_cloud(path), target + d)  # doubles read back exactly
    pcd = tmp_path / 'map.pcd'
    write_cloud(pcd, target + d)
    assert np.array_equal(read_cloud(pcd), target + d)
    cfg = pipeline_config_from({'voxel_size': VOXEL})
    for expected in ('miss', 'hit'):
        prepared = load_map(path, cfg, tmp_path / 'cache')
        assert prepared.cache == expected
        assert np.allclose(prepared.origin, local_origin(target + d))
        assert np.abs(prepared.features.points).max() < SENSOR_REACH  # worked on near zero
        result = register_clouds(source, prepared, config=cfg)
        assert result.valid, result.reason
        assert same(result.transform, translation(d) @ on_map_at_origin.transform)


def test_a_float32_cloud_at_utm_magnitude_is_warned_about_not_silently_used(pair):
    source, target, _, _ = pair
    d = np.array([512345.7, 5412345.7, 265.4])
    stored = (target + d).astype(np.float32)  # what a float32 PCD or PointCloud2 keeps
    message = coarse_coordinates(stored.astype(np.float64), VOXEL, 'map')
    assert message and 'float32' in message and 'doubles' in message
    assert '0.5 m' in message  # float32's step at 5.4e6 m, said in metres
    with pytest.warns(CoarseCoordinatesWarning, match='float32'):
        register_clouds(source, stored, voxel_size=VOXEL)
    # Doubles at that magnitude, and float32 near the origin, are fine.
    assert coarse_coordinates(target + d, VOXEL, 'map') is None
    assert coarse_coordinates(target.astype(np.float32).astype(np.float64), VOXEL,
                              'map') is None
    with warnings.catch_warnings():
        warnings.simplefilter('error', CoarseCoordinatesWarning)
        register_clouds(source, target + d, voxel_size=VOXEL)


@pytest.mark.parametrize('magnitude', (1e6,))
def test_a_tracked_stream_onto_a_georeferenced_target(pair, magnitude):
    source, target, _, at_origin = pair
    d = offset(magnitude, seed=2)
    tracker = Tracker()
    cfg = pipeline_config_from({'voxel_size': VOXEL})
    first = tracker.register(source, target + d, 0.0, config=cfg)
    second = tracker.register(source, target + d, 0.1, config=cfg)
    assert first.valid and first.path == 'global'
    assert second.valid and second.path == 'tracked', second.reason
    for result in (first, second):
        assert same(result.transform, translation(d) @ at_origin.transform)


def test_the_relocalizer_in_a_georeferenced_map(pair, on_map_at_origin, tmp_path):
    source, target, _, _ = pair
    d = offset(1e7, seed=6)
    path = tmp_path / 'map.ply'
    write_cloud(path, target + d)
    cfg = pipeline_config_from({'voxel_size': VOXEL})
    answer = Relocalizer(load_map(path, cfg), cfg).add(source)
    assert answer.confirmed and answer.valid, answer.reason
    assert same(answer.transform, translation(d) @ on_map_at_origin.transform)


def test_calibration_refuses_clouds_that_are_not_in_their_sensor_frames(pair):
    source, target, _, _ = pair
    cfg = pipeline_config_from({'voxel_size': VOXEL})
    with pytest.raises(InvalidInputError, match='not in its sensor'):
        gather(Frame(parent=target + offset(1e5), child=source), cfg)
