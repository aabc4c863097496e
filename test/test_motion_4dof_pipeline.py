"""
4-DoF mode through the pipeline, the CLI and replay, on the real LiDAR pair and bag.

The LiDAR pair's ground truth has a 0.17 deg tilt; the source is levelled by that tilt
(a rigid rotation of the scan, as an IMU would level it), so the truth is yaw-only, and
random yaw-only rotations and offsets are added. Every check is against ground truth.
"""

from __future__ import annotations

import json

from cgags_ros.config import PipelineConfig
from cgags_ros.config.fields import update_from_flat
from cgags_ros.geometry import apply_transform, rotation_error_deg, translation_error
from cgags_ros.io.clouds import read_cloud, write_cloud
from cgags_ros.pipeline import register_clouds
from cgags_ros.refusal import RefusalCode as Code
from cgags_ros.tools import register_cli, replay
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

VOXEL = 0.3


def yaw_matrix(angle: float) -> np.ndarray:
    return Rotation.from_euler('z', angle).as_matrix()


@pytest.fixture(scope='module')
def levelled_pair(data_dir):
    """Return the LiDAR pair with its source levelled: (source, target, yaw-only truth)."""
    folder = data_dir / 'lidar' / 'small_gicp'
    src, tgt = read_cloud(folder / 'source.ply'), read_cloud(folder / 'target.ply')
    T = np.loadtxt(folder / 'T_target_source.txt')
    R = T[:3, :3]
    yaw = np.arctan2(R[1, 0] - R[0, 1], R[0, 0] + R[1, 1])
    tilt = yaw_matrix(yaw).T @ R  # R = R_z(yaw) @ tilt
    truth = np.eye(4)
    truth[:3, :3], truth[:3, 3] = yaw_matrix(yaw), T[:3, 3]
    return src @ tilt.T, tgt, truth


def moved(pair, rng):
    """Return the source under a random yaw + offset, the target and the new truth."""
    src, tgt, truth = pair
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = yaw_matrix(rng.uniform(-np.pi, np.pi)), rng.uniform(-5, 5, 3)
    return apply_transform(M, src), tgt, truth @ np.linalg.inv(M)


def config(motion: str, **extra) -> PipelineConfig:
    return update_from_flat(PipelineConfig(), {'voxel_size': VOXEL, 'core.motion_model': motion,
                                               **extra})


def test_pipeline_yaw_only_lidar_at_least_as_good_as_6dof(levelled_pair):
    errors = {'4dof': [], '6dof': []}
    for trial in range(3):
        src, tgt, truth = moved(levelled_pair, np.random.default_rng(trial))
        for motion in errors:
            res = register_clouds(src, tgt, config=config(motion))
            assert res.valid, (motion, res.reason)
            errors[motion].append((rotation_error_deg(res.transform, truth),
                                   translation_error(res.transform, truth)))
            if motion == '4dof':
                assert res.transform[2, 2] == 1.0  # roll and pitch exactly zero
                np.testing.assert_array_equal(res.transform[2, :2], [0.0, 0.0])
                assert res.tilt_deg < 0.5  # the levelled pair shows no tilt (noise ~0.15)
    re4, te4 = np.mean(errors['4dof'], axis=0)
    re6, te6 = np.mean(errors['6dof'], axis=0)
    assert re4 <= re6 and te4 <= te6, errors
    assert re4 < 0.3 and te4 < 0.05


def test_pipeline_gicp_refinement_stays_yaw_only(levelled_pair):
    src, tgt, truth = moved(levelled_pair, np.random.default_rng(11))
    res = register_clouds(src, tgt, config=config('4dof', **{'refine.method': 'gicp'}))
    assert res.valid, res.reason
    assert res.transform[2, 2] == 1.0
    assert rotation_error_deg(res.transform, truth) < 0.2
    assert translation_error(res.transform, truth) < 0.1


def test_pipeline_reports_a_tilted_pair(levelled_pair):
    src, tgt, _ = levelled_pair
    tilted = src @ Rotation.from_euler('x', 4.0, degrees=True).as_matrix().T
    res = register_clouds(tilted, tgt, config=config('4dof'))
    assert not res.valid and res.refusal.code is Code.TILT, res.refusal
    assert 'not levelled' in res.reason, res.reason
    assert res.transform[2, 2] == 1.0  # reported, not forced flat and called valid


def test_cli_4dof_on_levelled_lidar_files(levelled_pair, tmp_path, capsys):
    src, tgt, truth = moved(levelled_pair, np.random.default_rng(5))
    write_cloud(tmp_path / 'source.npy', src)
    write_cloud(tmp_path / 'target.npy', tgt)
    args = [str(tmp_path / 'source.npy'), str(tmp_path / 'target.npy'), '--voxel-size',
            str(VOXEL), '--json']
    out = {}
    for motion, extra in (('4dof', ['--4dof', '--gravity', '0', '0', '2']), ('6dof', [])):
        assert register_cli.main(args + extra) == 0
        out[motion] = np.array(json.loads(capsys.readouterr().out)['transform'])
    assert out['4dof'][2, 2] == 1.0
    assert rotation_error_deg(out['4dof'], truth) <= rotation_error_deg(out['6dof'], truth)
    assert translation_error(out['4dof'], truth) < 0.05


@pytest.mark.slow
def test_replay_4dof_flag_on_the_lidar_bag(data_dir, tmp_path):
    """
    Replay the LiDAR bag offline with --4dof and without.

    The bag's truth carries the real pair's 0.17 deg tilt, which a yaw-only estimate
    cannot represent: RE is compared up to that tilt, TE directly.
    """
    reports = {}
    for motion, flag in (('4dof', ['--4dof']), ('6dof', [])):
        args = replay.build_parser().parse_args(
            [str(data_dir / 'bags' / 'lidar'), '--output', str(tmp_path / motion), '--quiet']
            + flag)
        replay.run(*replay.options_from_args(args))
        reports[motion] = json.loads((tmp_path / motion / 'results.json').read_text())
    s4, s6 = reports['4dof']['summary'], reports['6dof']['summary']
    assert s4['pairs'] == s4['successes'] == s6['successes'] > 0
    truth_tilt = max(np.degrees(np.arccos(np.clip(np.array(p['ground_truth'])[2, 2], -1, 1)))
                     for p in reports['4dof']['pairs'])
    assert s4['mean_re_deg'] <= s6['mean_re_deg'] + truth_tilt
    assert s4['mean_te_m'] <= 1.1 * s6['mean_te_m']
    for p in reports['4dof']['pairs']:
        assert np.array(p['transform'])[2][2] == 1.0
