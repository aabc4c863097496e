"""
Places of a prepared map (pipeline/places.py, pipeline/locate.py) on a floor of real rooms.

The floor: three 3DMatch scenes (redkitchen, home_at, mit_lab), each fused from its even
fragments with their normals facing each fragment's sensor, turned and placed as rooms 30 m
apart; queries are odd fragments in their own frames, held out of the map; a hotel_uc
fragment is a scan from outside it.
"""

from __future__ import annotations

import json

from bench.datasets import threedmatch as tdm
from cgags_ros.config import pipeline_config_from
from cgags_ros.errors import InvalidInputError
from cgags_ros.frontend.descriptor_index import Cells, DescriptorIndex
from cgags_ros.frontend.features import CloudFeatures, estimate_normals, extract_features
from cgags_ros.frontend.matching import match_features
from cgags_ros.frontend.refine import refine_finer
from cgags_ros.geometry import apply_transform, make_transform, rotation_error_deg
from cgags_ros.geometry import translation_error
from cgags_ros.io.clouds import write_cloud
from cgags_ros.pipeline import locate, polish, register_clouds
from cgags_ros.pipeline.confidence import refused_at_most
from cgags_ros.pipeline.hint import Hint, HINT_SIGMAS
from cgags_ros.pipeline.locate import TESTED
from cgags_ros.pipeline.map import load_map
from cgags_ros.pipeline.places import PlaceIndex, submap_features
from cgags_ros.refusal import RefusalCode as Code
from cgags_ros.relocalization.relocalizer import Relocalizer
from cgags_ros.tools import map_cli, relocalize_cli
import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

# scene -> (x of the room, its yaw in degrees)
ROOMS = {'7-scenes-redkitchen': (0.0, 30.0),
         'sun3d-home_at-home_at_scan1_2013_jan_1': (30.0, 250.0),
         'sun3d-mit_lab_hj-lab_hj_tea_nov_2_2012_scan1_erika': (60.0, 120.0)}
QUERY = ('sun3d-home_at-home_at_scan1_2013_jan_1', 53)  # (scene, odd fragment)
OUTSIDE = ('sun3d-hotel_uc-scan3', 27)
VOXEL = 0.05
RIGHT = (15.0, 0.3)  # RE (deg), TE (m): 3DMatch's registration recall


@pytest.fixture(scope='module')
def floor(data_dir, tmp_path_factory):
    """Return the floor's prepared map (cached), its config, path, rooms and a query maker."""
    root = data_dir / '3dmatch_benchmark'
    cfg = pipeline_config_from({'voxel_size': VOXEL})
    points, normals, rooms = [], [], {}
    for scene, (x, yaw) in ROOMS.items():
        poses, fragments = tdm.fragment_poses(root, scene), tdm.Fragments(root, scene)
        place = make_transform(Rotation.from_euler('z', yaw, degrees=True).as_matrix(),
                               [x, 0.0, 0.0])
        room = [apply_transform(place @ P, fragments[k]) for k, P in poses.items() if k % 2 == 0]
        normals += [estimate_normals(fragments[k], VOXEL, cfg.frontend) @ (place @ P)[:3, :3].T
                    for k, P in poses.items() if k % 2 == 0]
        points += room
        rooms[scene] = (place, np.vstack(room).mean(axis=0))
    folder = tmp_path_factory.mktemp('floor')
    path = folder / 'floor.ply'
    write_cloud(path, np.vstack(points), np.vstack(normals))
    prepared = load_map(path, cfg, folder / 'cache')

    def query(scene, k):
        """Return fragment ``k`` of ``scene`` (its frame) and its pose on the floor (or None)."""
        fragment = tdm.Fragments(root, scene)[k]
        if scene not in rooms:
            return fragment, None
        return fragment, rooms[scene][0] @ tdm.fragment_poses(root, scene)[k]

    return prepared, cfg, path, rooms, query


def test_places_are_stored_with_the_map_and_memory_mapped(floor, capsys):
    prepared, cfg, path, _, _ = floor
    again = load_map(path, cfg, prepared.cache_path.rsplit('/', 1)[0])
    assert again.cache == 'hit'
    places = again.places
    assert len(places) > 2 * len(ROOMS)  # many places a room
    for array in (places.centres, places.vote_place, places.index.arrays.points,
                  places.cells.label, places.cells.order):
        assert isinstance(array.base, np.memmap)  # a view of the cache, not a copy
    assert np.array_equal(places.centres, prepared.places.centres)
    assert map_cli.main(['inspect', str(path), '--cache-dir',
                         prepared.cache_path.rsplit('/', 1)[0], '--json']) == 0
    [entry] = json.loads(capsys.readouterr().out)['entries']
    assert entry['places'] == len(places) == again.info()['places']


def test_a_query_is_registered_in_its_own_place_as_against_the_whole_map(floor):
    prepared, cfg, _, rooms, query = floor
    scan, truth = query(*QUERY)
    located = register_clouds(scan, prepared, config=cfg)
    whole = register_clouds(scan, prepared.whole(), config=cfg)
    assert located.valid and whole.valid, (located.reason, whole.reason)
    assert rotation_error_deg(located.transform, truth) < RIGHT[0]
    assert translation_error(located.transform, truth) < RIGHT[1]
    # Its place is in its room, a part of the map, and the pose is the whole map's.
    place = located.map_info['place']
    assert np.linalg.norm(np.array(place['centre']) - rooms[QUERY[0]][1]) < 5.0
    assert place['points'] < 0.7 * len(prepared.features.points)
    assert located.num_target_points == place['points']
    assert len(located.stats['places']['ranked']) <= TESTED
    # The whole map's short search put it in its room too; that place was tested first.
    first = located.stats['places']['ranked'][0]
    assert first['by'] == 'consensus'
    assert np.linalg.norm(np.array(first['centre']) - rooms[QUERY[0]][1]) < 5.0
    assert rotation_error_deg(located.transform, whole.transform) < 0.5
    assert translation_error(located.transform, whole.transform) < 0.02


def test_the_consensus_place_scores_at_least_its_bound_in_its_own_test(floor):
    # Untested unless another place scores more: its own test must reach the bound.
    prepared, cfg, _, rooms, query = floor
    for scene in rooms:
        points, _ = query(scene, 5)
        scan = extract_features(points - points.mean(axis=0), VOXEL, cfg.frontend)
        ranked = prepared.places.rank(scan, VOXEL, TESTED, prepared.features.tree)
        places, bound, _ = locate._with_consensus(scan, ranked, prepared, cfg)
        assert places[0].by == 'consensus' and bound > 0
        part = prepared.places.submap(prepared.features, places[0].rows)
        assert locate._tested(scan, ranked.keypoints, part, cfg).inliers >= bound


def test_a_pose_in_another_room_is_refused_by_the_whole_maps_matches(floor):
    # A place's registration sees no other room; the whole map's matches see them all.
    prepared, cfg, _, rooms, query = floor
    scan_points, truth = query(*QUERY)
    located = register_clouds(scan_points, prepared, config=cfg)
    said = located.stats['places']['whole_map_support']
    assert located.valid and not said['distinct'] and said['pose'] > said['chance_bound'], said
    scan = extract_features(scan_points, VOXEL, cfg.frontend)
    ranked = prepared.places.rank(scan, VOXEL, TESTED, prepared.features.tree)
    _, _, whole = locate._with_consensus(scan, ranked, prepared, cfg)
    local = make_transform(np.eye(3), -prepared.origin) @ truth
    assert whole.support(local) >= 10
    (scene, _), (other, _) = QUERY, next(r for r in rooms.items() if r[0] != QUERY[0])
    # The same spot in another room: the pose a look-alike surface there would give.
    elsewhere = make_transform(np.eye(3), -prepared.origin) @ rooms[other][0] @ np.linalg.inv(
        rooms[scene][0]) @ truth
    for pose in (local, elsewhere):
        result = register_clouds(scan_points, prepared, config=cfg)
        said = locate._judged_elsewhere(result, whole, pose, cfg)
        assert said['distinct'] is (pose is elsewhere)
        assert result.valid is (pose is local), result.reason
    assert said['pose'] <= said['chance_bound'] < said['consensus'], said
    assert result.refusal.code is Code.AMBIGUOUS
    assert result.ambiguous
    assert 'elsewhere' in result.reason
    assert result.confidence <= refused_at_most(Code.AMBIGUOUS.value)  # as the gates cap it


def test_a_submap_index_cut_from_the_maps_cells_matches_as_one_fitted_to_it(floor):
    prepared, cfg, _, rooms, _ = floor
    features = prepared.features
    centre = rooms[QUERY[0]][1] - prepared.origin
    rows = np.sort(np.asarray(features.tree.query_ball_point(centre, 3.0), dtype=np.int64))
    cut, fitted = prepared.places.submap(features, rows), submap_features(features, rows)
    index = cut.descriptor_index()
    assert len(index.centres) > 1  # the pruning bounds are exercised
    assert all((prepared.places.cells.centres == c).all(axis=1).any() for c in index.centres)
    np.testing.assert_array_equal(index.rows, fitted.descriptor_index().rows)
    others = np.setdiff1d(np.arange(len(features.points)), rows)[::40]
    a = match_features(features.descriptors[others], cut.descriptors, cfg.frontend, 2, index)
    b = match_features(features.descriptors[others], fitted.descriptors, cfg.frontend, 2,
                       fitted.descriptor_index())
    assert len(a) > 100
    np.testing.assert_array_equal(a.source_index, b.source_index)
    np.testing.assert_array_equal(a.target_index, b.target_index)


def test_a_hint_ranks_only_the_places_it_covers(floor):
    prepared, cfg, _, rooms, query = floor
    scan, truth = query(*QUERY)
    here = register_clouds(scan, prepared, config=cfg, hint=Hint(truth[:3, 3], 2.0))
    assert here.valid and translation_error(here.transform, truth) < RIGHT[1]
    assert all(p['tested_inliers'] is not None for p in here.stats['places']['ranked'])
    # A hint so tight it leaves one place: registered untested (there is nothing to rank).
    tight = register_clouds(scan, prepared, config=cfg, hint=Hint(truth[:3, 3], 0.1))
    [place] = tight.stats['places']['ranked']
    assert place['tested_inliers'] is None and place['by'] in ('votes', 'hint')
    assert tight.valid and translation_error(tight.transform, truth) < RIGHT[1]
    other = rooms['7-scenes-redkitchen'][1]
    there = register_clouds(scan, prepared, config=cfg, hint=Hint(other, 2.0))
    ranked = there.stats['places']['ranked']
    assert ranked and all(np.linalg.norm(np.array(p['centre']) - other) < 2.0 + 5.0
                          for p in ranked)
    assert not there.valid  # the kitchen does not hold the scan


def test_a_planar_hint_restricts_only_x_and_y(floor):
    """A 2-D pose (RViz's, at height 0) says nothing of the height: 300 m off in z still finds."""
    prepared, cfg, _, _, query = floor
    scan, truth = query(*QUERY)
    up = truth[:3, 3] + [0.0, 0.0, 300.0]
    here = register_clouds(scan, prepared, config=cfg, hint=Hint(up, 2.0, planar=True))
    assert here.valid and translation_error(here.transform, truth) < RIGHT[1]
    above = register_clouds(scan, prepared, config=cfg, hint=Hint(up, 2.0))
    assert above.refusal.code is Code.NO_SHARED_SURFACE


def test_a_hint_that_covers_no_place_refuses_before_any_registration(floor):
    prepared, cfg, path, _, query = floor
    scan, _ = query(*QUERY)
    far = register_clouds(scan, prepared, config=cfg, hint=Hint([500.0, 500.0, 0.0], 10.0))
    assert far.refusal.code is Code.NO_SHARED_SURFACE and 'covers no place' in far.reason
    assert far.num_target_points == 0 and 'places' not in far.stats
    reloc = Relocalizer(prepared, cfg)
    answer = reloc.add(scan, hint=Hint([500.0, 500.0, 0.0], 10.0))
    assert not answer.confirmed and answer.refusal.code is Code.NO_SHARED_SURFACE
    with pytest.raises(InvalidInputError, match='prepared map'):
        register_clouds(scan, scan, voxel_size=VOXEL, hint=Hint([0.0, 0.0, 0.0], 1.0))


def test_a_scan_from_outside_the_map_is_refused_against_one_place(floor):
    prepared, cfg, _, _, query = floor
    scan, _ = query(*OUTSIDE)
    result = register_clouds(scan, prepared, config=cfg)
    assert not result.valid
    # Cheap: one place's registration, not the whole map's.
    assert 0 < result.num_target_points < 0.7 * len(prepared.features.points)
    assert result.map_info['place']['points'] == result.num_target_points


def test_a_scan_of_few_voxels_is_refined_again_with_its_own_points(floor, monkeypatch):
    prepared, cfg, _, _, query = floor
    scan, truth = query(*QUERY)
    seen = []

    def spy(source, voxels, *args, **kwargs):
        seen.append((len(source), voxels))
        return refine_finer(source, voxels, *args, **kwargs)

    monkeypatch.setattr(polish, 'refine_finer', spy)
    result = register_clouds(scan, prepared, config=cfg)
    assert result.valid and rotation_error_deg(result.transform, truth) < RIGHT[0]
    # The scan's own points (not its voxel centroids), in the place's registration.
    assert seen == [(len(scan), result.num_source_points)]
    assert np.array_equal(result.candidates[0].transform, result.transform)
    seen.clear()
    pair = register_clouds(scan, apply_transform(truth, scan), config=cfg)
    assert pair.valid and seen == []  # a pair of clouds is not (pipeline/polish.py)


def test_a_pose_hint_covers_its_position_to_three_standard_deviations():
    pose = make_transform(np.eye(3), [1.0, 2.0, 3.0])
    cov = np.diag([0.25, 0.04, 0.01, 0.1, 0.1, 0.1])  # sigma x 0.5 m
    hint = Hint.from_pose(pose, cov.reshape(-1))
    assert np.allclose(hint.position, [1.0, 2.0, 3.0])
    assert hint.radius == pytest.approx(HINT_SIGMAS * 0.5)
    with pytest.raises(InvalidInputError):
        Hint([0.0, np.nan, 0.0], 1.0)
    with pytest.raises(InvalidInputError):
        Hint([0.0, 0.0, 0.0], -1.0)


def test_the_relocalize_command_takes_a_hint(floor, tmp_path, capsys):
    prepared, _, path, _, query = floor
    scan, truth = query(*QUERY)
    np.save(tmp_path / 'scan.npy', scan)
    argv = [str(path), str(tmp_path / 'scan.npy'), '--voxel-size', str(VOXEL), '--json',
            '--map-cache-dir', prepared.cache_path.rsplit('/', 1)[0], '--hint']
    assert relocalize_cli.main(argv + [*map(str, truth[:3, 3]), '2']) == 0
    [found] = json.loads(capsys.readouterr().out)['scans']
    assert found['place']['points'] < len(prepared.features.points)
    assert relocalize_cli.main(argv + ['500', '500', '0', '10']) == 1
    out = json.loads(capsys.readouterr().out)
    assert out['refusal']['code'] == Code.NO_SHARED_SURFACE.value


def test_places_are_ranked_by_votes_less_chance_not_by_raw_votes():
    """
    A scan's own room outranks a room with four times its voting points and more raw votes.

    Synthetic descriptors: each map point's is random; the scan's keypoints are 120 copies of
    the small room's (its true matches) and 380 random ones, which vote by chance for
    wherever the map has most voting points: the large room gets more votes in all.
    """
    rng = np.random.default_rng(0)
    small = rng.uniform(-5, 5, (400, 3))
    large = rng.uniform(-10, 10, (1600, 3)) + [200.0, 0.0, 0.0]
    points = np.vstack([small, large])
    descriptors = rng.random((len(points), 33))
    centres = np.array([[0.0, 0.0, 0.0], [200.0, 0.0, 0.0]])
    vote_place = (np.arange(len(points)) >= len(small)).astype(np.int64)
    index = PlaceIndex(centres, vote_place, DescriptorIndex(descriptors), spacing=3.0,
                       cells=Cells.fit(descriptors, 400))
    own = rng.choice(len(small), 120, replace=False)
    scan_descriptors = np.vstack([descriptors[own], rng.random((380, 33))])
    scan = CloudFeatures(rng.uniform(-5, 5, (500, 3)), np.tile([0.0, 0.0, 1.0], (500, 1)),
                         scan_descriptors, 0.5, None)
    nearest = index.index.query(scan_descriptors, 1)[0][:, 0]
    raw = np.bincount(vote_place[nearest], minlength=2)
    assert raw[1] > raw[0]  # the large room has more votes...
    ranked = index.rank(scan, 0.5, 2, cKDTree(points))
    assert not ranked.whole
    assert np.linalg.norm(ranked.places[0].centre) < 10.0  # ...the small one is first
