"""
Surfaces in free space as both sensors see it (:mod:`cgags_ros.pipeline.free_space`).

Synthetic rooms seen from their sensors; real fragments of two different 3DMatch scenes that
every other gate accepts (:mod:`bench.no_overlap`'s two seeded samples), refused as sharing
no surface, against right low-overlap 3DLoMatch poses, still accepted.
"""

from __future__ import annotations

from types import SimpleNamespace

from bench.datasets import threedmatch as tdm
from cgags_ros.config import PipelineConfig
from cgags_ros.config.fields import update_from_flat
from cgags_ros.pipeline import cached_features, register_clouds
from cgags_ros.pipeline.confidence import refused_at_most
from cgags_ros.pipeline.free_space import (free_space_surface, free_space_violation,
                                           measured_free_space_surface)
from cgags_ros.refusal import RefusalCode
from cgags_ros.validity.shared import THIN_OVERLAP
import numpy as np
import pytest
from scipy.spatial import cKDTree
from test_no_shared_surface import SCENES

V = 0.05
# (source scene, fragment, target scene, fragment): every gate but this one accepts them
# (seeds 0 and 1 of bench.no_overlap cross)
ACCEPTED = [('hotel', 32, 'kitchen', 35), ('home', 17, 'hotel', 22)]
# 3DLoMatch (scene, target, source), right and valid: of those below the largest value, the
# poses that put the most surface in free space from both sensors in three scenes
LOW_OVERLAP = [('7-scenes-redkitchen', 26, 59),
               ('sun3d-mit_lab_hj-lab_hj_tea_nov_2_2012_scan1_erika', 3, 6),
               ('sun3d-home_at-home_at_scan1_2013_jan_1', 36, 38)]


def _patch(corner, u, w, step=V):
    """Return a grid of points over the parallelogram ``corner + a u + b w`` (a, b in 0..1)."""
    a = np.arange(0.0, 1.0, step / np.linalg.norm(u))
    b = np.arange(0.0, 1.0, step / np.linalg.norm(w))
    A, B = np.meshgrid(a, b)
    return np.asarray(corner) + A.reshape(-1, 1) * u + B.reshape(-1, 1) * w


def _room(front_wall_x, side_wall_y, rng):
    """Return a floor, a wall ahead (x) and one to the left (y), as seen from the origin."""
    floor = _patch([0.5, -2.0, -1.0], np.array([front_wall_x - 0.5, 0, 0]),
                   np.array([0, 2.0 + side_wall_y, 0]))
    ahead = _patch([front_wall_x, -2.0, -1.0], np.array([0, 2.0 + side_wall_y, 0]),
                   np.array([0, 0, 2.5]))
    left = _patch([0.5, side_wall_y, -1.0], np.array([front_wall_x - 0.5, 0, 0]),
                  np.array([0, 0, 2.5]))
    points = np.vstack([floor, ahead, left])
    return points + rng.normal(0, 0.003, points.shape)


def _cloud(points, sensor_at_origin=True):
    return SimpleNamespace(points=points, tree=cKDTree(points),
                           sensor_at_origin=sensor_at_origin)


def test_surfaces_in_free_space_count_only_when_both_sensors_see_them():
    rng = np.random.default_rng(0)
    room = _cloud(_room(4.0, 1.5, rng))
    # the same room seen again: nothing in free space
    assert free_space_surface(_cloud(_room(4.0, 1.5, rng)), room, np.eye(4), V) < 0.01
    # another room on the same floor: its wall ahead stands in front of this room's (this
    # room's sensor saw through it), this room's left wall in front of the other's
    assert free_space_surface(_cloud(_room(2.5, 3.0, rng)), room, np.eye(4), V) > 0.2
    # a smaller room inside this one: only this room's sensor sees surfaces in its free
    # space (the other's walls stand in front of this one's); the other view has nothing
    inside = _cloud(_room(2.5, 1.0, rng))
    assert free_space_violation(inside.points, room.points, np.eye(4), 2 * V, 2.0) > 0.3
    assert free_space_surface(inside, room, np.eye(4), V) < 0.01


def test_measured_only_where_both_clouds_are_their_sensors_views():
    rng = np.random.default_rng(1)
    room, other = _cloud(_room(4.0, 1.5, rng)), _cloud(_room(2.5, 3.0, rng))
    cfg = PipelineConfig(voxel_size=V)
    assert measured_free_space_surface(other, room, np.eye(4), cfg) > 0.2
    centroid = update_from_flat(cfg, {'frontend.normal_orientation': 'centroid'})
    gate_off = update_from_flat(cfg, {'gates.max_free_space_violation': 1.0})
    for unseen in (measured_free_space_surface(other, room, np.eye(4), centroid),
                   measured_free_space_surface(other, room, np.eye(4), gate_off),
                   measured_free_space_surface(other, room, np.eye(4), cfg, map_target=True),
                   measured_free_space_surface(_cloud(other.points, False), room, np.eye(4),
                                               cfg)):
        assert np.isnan(unseen)


@pytest.fixture(scope='module')
def fragment(data_dir):
    root = data_dir / '3dmatch_benchmark'
    scenes = {name: tdm.Fragments(root, scene) for name, scene in SCENES.items()}
    return lambda name, k: scenes[name][k]


def _measured(source, target):
    cfg = PipelineConfig(voxel_size=V)
    result = register_clouds(source, target, config=cfg)
    fs = cached_features(source, V, cfg.frontend, 'source')
    ft = cached_features(target, V, cfg.frontend, 'target')
    return result, free_space_surface(fs, ft, result.transform, V)


@pytest.mark.slow
def test_cross_pairs_other_gates_accept_are_refused_and_right_thin_poses_kept(
        fragment, benchmark_pair):
    cross = []
    for source_scene, s, target_scene, t in ACCEPTED:
        result, measured = _measured(fragment(source_scene, s), fragment(target_scene, t))
        assert not result.valid
        assert result.refusal.code is RefusalCode.NO_SHARED_SURFACE, result.refusal
        assert 'free space' in result.refusal.message
        assert result.free_space_surface == pytest.approx(measured)
        assert result.confidence <= refused_at_most('no_shared_surface')
        cross.append(measured)
    right = []
    for scene, target, source in LOW_OVERLAP:
        src, tgt, truth = benchmark_pair(scene, target, source)
        result, measured = _measured(src, tgt)
        assert result.valid and tdm.registered(result.transform, truth)
        assert result.overlap < THIN_OVERLAP  # judged, and passed
        right.append(measured)
    assert min(cross) > 2 * max(right), (cross, right)
