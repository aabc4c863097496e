"""
Relocalization without ROS: ranked candidates, ambiguity, the map loader and its cache, the CLI.

Real data: the redkitchen fragments 0 and 4 merged at full resolution (the map), fragments 6
and 4 under random any-angle motions (the scans), checked against ground truth.
"""

from __future__ import annotations

from cgags_ros.config import pipeline_config_from
from cgags_ros.errors import EmptyCloudError, InvalidConfigError, InvalidInputError
from cgags_ros.geometry import apply_transform, make_transform
from cgags_ros.geometry import rotation_error_deg, translation_error
from cgags_ros.io.clouds import read_cloud
from cgags_ros.pipeline import register_clouds
from cgags_ros.pipeline.map import load_map
from cgags_ros.refusal import RefusalCode as Code
from cgags_ros.tools import register_cli
from cgags_ros.tools.replay_common import auto_voxel_size, MAP_SCANS, map_voxel_size
from cgags_ros.tools.replay_common import read_bag_contents
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from waiting import merged_kitchen_map

INDOOR = (15.0, 0.3)  # RE (deg), TE (m)
# Scans moved by arbitrary motions: normals oriented to the frame origin would depend on it.
MOVED = {'voxel_size': 0.05, 'frontend.normal_orientation': 'centroid'}


@pytest.fixture(scope='module')
def kitchen(data_dir, tmp_path_factory):
    path, merged, frag6, frag4 = merged_kitchen_map(data_dir, tmp_path_factory.mktemp('map'))
    return path, merged, {'fragment 6': frag6, 'fragment 4': frag4}


def moved(rng):
    return make_transform(Rotation.random(random_state=rng).as_matrix(), rng.uniform(-3, 3, 3))


@pytest.mark.parametrize('name', ['fragment 6', 'fragment 4'])
def test_scans_localize_in_the_merged_map_with_ranked_candidates(kitchen, tmp_path, name):
    path, _, scans = kitchen
    assert len(np.load(path)) >= 500_000
    cfg = pipeline_config_from(MOVED)
    prepared = load_map(path, cfg, tmp_path)
    scan, gt = scans[name]
    rng = np.random.default_rng(7)
    for _ in range(2):
        A = moved(rng)
        result = register_clouds(apply_transform(A, scan), prepared, config=cfg)
        T_gt = gt @ np.linalg.inv(A)
        re = rotation_error_deg(result.transform, T_gt)
        te = translation_error(result.transform, T_gt)
        assert result.valid and not result.ambiguous, result.reason
        assert re < INDOOR[0] and te < INDOOR[1], f'{name}: RE {re:.2f} deg, TE {te:.3f} m'
        cands = result.candidates
        assert 2 <= len(cands) <= cfg.num_candidates
        assert np.array_equal(cands[0].transform, result.transform) and cands[0].ratio == 1.0
        assert [c.num_inliers for c in cands[1:]] == sorted((c.num_inliers for c in cands[1:]),
                                                            reverse=True)
        assert result.runner_up_ratio == cands[0].num_inliers / cands[1].num_inliers > 1.5
        for i, a in enumerate(cands):  # pairwise distinct
            for b in cands[i + 1:]:
                assert (rotation_error_deg(a.transform, b.transform) > 10.0
                        or translation_error(a.transform, b.transform) > 0.5)


def test_the_map_cache_hits_with_the_same_settings_and_misses_on_a_change(kitchen, tmp_path):
    path, _, _ = kitchen
    cfg = pipeline_config_from({'voxel_size': 0.08})
    first = load_map(path, cfg, tmp_path)
    again = load_map(path, cfg, tmp_path)
    assert (first.cache, again.cache) == ('miss', 'hit')
    for name in ('points', 'normals', 'descriptors'):
        assert np.array_equal(getattr(first.features, name), getattr(again.features, name))
    # Matching options do not change the features; the voxel size and FPFH radius do.
    assert load_map(path, pipeline_config_from({'voxel_size': 0.08,
                                                'frontend.max_correspondences': 100}),
                    tmp_path).cache == 'hit'
    assert load_map(path, pipeline_config_from({'voxel_size': 0.09}), tmp_path).cache == 'miss'
    assert load_map(path, pipeline_config_from({'voxel_size': 0.08,
                                                'frontend.fpfh_radius_factor': 4.0}),
                    tmp_path).cache == 'miss'
    assert load_map(path, cfg, None).cache == 'off'
    with pytest.raises(InvalidConfigError, match='other feature settings'):
        register_clouds(np.load(path)[:5000], first,
                        config=pipeline_config_from({'voxel_size': 0.09}))


@pytest.mark.slow
def test_a_map_file_with_normals_signs_the_map_normals_and_a_sensor_frame_scan_localizes(
        data_dir, tmp_path):
    """
    Normals in the map file (each fragment's facing its own sensor) sign the map's normals.

    With the defaults (normals facing the sensor, the scan kept in its sensor frame) the map
    is described as the scan is, and the free-space gate applies (the scan's view).
    """
    from scipy.spatial import cKDTree

    from bench.datasets.gt_pairs import find_pair
    from cgags_ros.frontend.features import estimate_normals
    from cgags_ros.io.clouds import write_cloud

    base = data_dir / 'indoor_3dmatch'
    f4, f0, T40 = find_pair(base / 'gt_pairs.txt', 'cloud_bin_4.ply', 'cloud_bin_0.ply')
    cfg = pipeline_config_from({'voxel_size': 0.05})
    frags = [(read_cloud(f0), np.eye(4)), (read_cloud(f4), T40)]
    turn = moved(np.random.default_rng(5))  # the map's frame is arbitrary
    points = np.vstack([apply_transform(turn @ T, f) for f, T in frags])

    def facing_its_sensor(fragment):
        # Estimated on a centimetre thinning of the fragment and given to each point from its
        # nearest kept point: the radius search on every point of a full-resolution
        # fragment would cost most of this module.
        _, keep = np.unique(np.floor(fragment / 0.01), axis=0, return_index=True)
        thin = fragment[np.sort(keep)]
        return estimate_normals(thin, 0.05, cfg.frontend)[cKDTree(thin).query(fragment)[1]]

    sides = np.vstack([facing_its_sensor(f) @ (turn @ T)[:3, :3].T for f, T in frags])
    write_cloud(tmp_path / 'map.ply', points, sides)
    write_cloud(tmp_path / 'bare.ply', points)
    prepared = load_map(tmp_path / 'map.ply', cfg, tmp_path / 'cache')
    bare = load_map(tmp_path / 'bare.ply', cfg)
    assert (prepared.oriented_by, bare.oriented_by) == ('file normals', 'origin')
    assert load_map(tmp_path / 'map.ply', cfg, tmp_path / 'cache').oriented_by == 'file normals'
    assert load_map(tmp_path / 'map.ply', pipeline_config_from(MOVED)).oriented_by == 'centroid'
    # Same points; the signs follow the file's normals (near every one), not the frame origin.
    assert np.array_equal(prepared.features.points, bare.features.points)
    tree_side = sides[cKDTree(points).query(prepared.features.points)[1]]
    agree = np.einsum('ij,ij->i', prepared.features.normals, tree_side) > 0
    assert agree.mean() > 0.95
    assert np.mean(np.einsum('ij,ij->i', bare.features.normals, tree_side) > 0) < 0.9
    scan = np.load(base / 'geotransformer_demo' / 'src.npy')  # fragment 6, its sensor frame
    gt = turn @ np.load(base / 'geotransformer_demo' / 'gt.npy')
    result = register_clouds(scan, prepared, config=cfg)
    assert result.valid, result.reason
    assert rotation_error_deg(result.transform, gt) < 5.0
    assert translation_error(result.transform, gt) < 0.1
    assert np.isfinite(result.free_space_violation)


def test_bad_map_files_are_clear_errors(tmp_path):
    cfg = pipeline_config_from({'voxel_size': 0.05})
    with pytest.raises(InvalidInputError, match='no such file'):
        load_map(tmp_path / 'missing.ply', cfg)
    (tmp_path / 'empty.xyz').write_text('')
    with pytest.raises(InvalidInputError):
        load_map(tmp_path / 'empty.xyz', cfg)
    np.save(tmp_path / 'nan.npy', np.full((50, 3), np.nan))
    with pytest.raises(EmptyCloudError, match='no finite points'):
        load_map(tmp_path / 'nan.npy', cfg)


def test_a_map_with_some_nans_loads_and_counts_them(kitchen, tmp_path):
    _, merged, _ = kitchen
    part = merged[::20].copy()
    part[::7] = np.nan
    np.save(tmp_path / 'holes.npy', part)
    prepared = load_map(tmp_path / 'holes.npy', pipeline_config_from({'voxel_size': 0.05}))
    assert prepared.num_nonfinite == len(part[::7]) and prepared.num_raw_points == len(part)
    assert np.isfinite(prepared.features.points).all()


def twin_scene(kitchen):
    """Return a scan, the kitchen map once, and twice (the copy turned 180 deg about z)."""
    _, merged, scans = kitchen
    once = merged[::4]
    centre = once.mean(axis=0) + [5.0, 0.0, 0.0]
    twin = np.vstack([once, (once - centre) @ np.diag([-1.0, -1.0, 1.0]).T + centre])
    return scans['fragment 6'][0], once, twin


def test_a_symmetric_scene_is_ambiguous_and_the_same_scene_once_is_not(kitchen):
    """The kitchen map twice, the copy turned 180 deg about a vertical axis: two poses fit."""
    scan, once, twin = twin_scene(kitchen)
    cfg = pipeline_config_from(MOVED)
    result = register_clouds(scan, twin, config=cfg)
    assert result.ambiguous and not result.valid and result.refusal.code is Code.AMBIGUOUS
    second = result.candidates[1].transform
    assert rotation_error_deg(result.candidates[0].transform, second) > 150  # the twin pose
    single = register_clouds(scan, once, config=cfg)
    assert single.valid and not single.ambiguous, single.reason


def test_candidates_searched_beside_the_gates_equal_those_searched_after(kitchen, monkeypatch):
    """The candidate search runs in a thread beside the gates; on one thread after them."""
    import cgags_ros.pipeline.register as register

    scan, _, twin = twin_scene(kitchen)
    cfg = pipeline_config_from(MOVED)
    beside = register_clouds(scan, twin, config=cfg)
    monkeypatch.setattr(register, 'DEFAULT_WORKERS', 1)
    after = register_clouds(scan, twin, config=cfg)
    assert len(beside.candidates) >= 2 and beside.ambiguous
    assert (beside.valid, beside.reason, beside.ambiguous) == (after.valid, after.reason,
                                                               after.ambiguous)
    for a, b in zip(beside.candidates, after.candidates, strict=True):
        assert (a.num_inliers, a.ratio) == (b.num_inliers, b.ratio)
        # ICP's OpenMP reductions differ in the last bits between runs
        np.testing.assert_allclose(a.transform, b.transform, atol=1e-9)
        assert a.fitness == pytest.approx(b.fitness, abs=1e-9)


def test_an_unrelated_scene_gives_no_confident_pose(kitchen, data_dir):
    _, merged, _ = kitchen
    bunny = read_cloud(data_dir / 'objects' / 'stanford_bunny_scans' / 'bun000.ply') * 20
    result = register_clouds(bunny, merged[::4], config=pipeline_config_from(MOVED))
    assert not result.valid and result.refusal.code in {
        Code.CHANCE_LEVEL, Code.AMBIGUOUS, Code.NO_ESTIMATE, Code.FEW_INLIERS, Code.FREE_SPACE,
        Code.LOW_FITNESS, Code.NO_SHARED_SURFACE}, result.refusal


def test_cli_prints_the_candidates(kitchen, data_dir, tmp_path, capsys):
    path, _, scans = kitchen
    scan, gt = scans['fragment 6']
    A = moved(np.random.default_rng(3))
    np.save(tmp_path / 'scan.npy', apply_transform(A, scan))
    code = register_cli.main([str(tmp_path / 'scan.npy'), str(path), '--voxel-size', '0.05',
                              '--set', 'frontend.normal_orientation=centroid',
                              '--candidates', '3', '--json'])
    out = __import__('json').loads(capsys.readouterr().out)
    # Up to 3: the search stops at the first chance-level alternative (pipeline/candidates.py)
    assert code == 0 and 2 <= len(out['candidates']) <= 3 and not out['ambiguous']
    assert out['candidates'][1]['num_inliers'] < out['candidates'][0]['num_inliers'] / 1.5
    T = np.array(out['candidates'][0]['transform'])
    T_gt = gt @ np.linalg.inv(A)
    assert rotation_error_deg(T, T_gt) < INDOOR[0] and translation_error(T, T_gt) < INDOOR[1]
    register_cli.main([str(tmp_path / 'scan.npy'), str(path), '--voxel-size', '0.05',
                       '--set', 'frontend.normal_orientation=centroid', '--candidates', '3'])
    text = capsys.readouterr().out
    assert 'candidate 0: inliers' in text and 'candidate 1: inliers' in text


@pytest.mark.slow
def test_replay_localizes_every_bag_scan_in_a_map(data_dir, tmp_path):
    from cgags_ros.tools import replay

    code = replay.main([str(data_dir / 'bags' / 'lidar'), '--map',
                        str(data_dir / 'lidar' / 'small_gicp' / 'target.ply'),
                        '--map-cache-dir', str(tmp_path / 'cache'), '--output',
                        str(tmp_path / 'out'), '--quiet'])
    out = __import__('json').loads((tmp_path / 'out' / 'results.json').read_text())
    assert code == 0 and out['summary']['recall'] == 1.0
    rows = out['pairs']
    assert len(rows) == 6 and all(r['success'] for r in rows)
    assert all(len(r['candidates']) >= 1 for r in rows)
    assert any('cache miss' in n for n in out['notes'])
    # No voxel given: the bag's first source scans choose the map's, not its target cloud.
    contents = read_bag_contents(data_dir / 'bags' / 'lidar', '/source_cloud',
                                 '/target_cloud', None)
    chosen = map_voxel_size([c.xyz for c in contents.sources[:MAP_SCANS]])
    assert chosen != auto_voxel_size(contents.first_target_points())
    assert f'voxel size {chosen:g} m (auto for a map' in ' '.join(out['notes'])
