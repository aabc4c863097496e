"""
Surfaces in free space as both sensors see it: the pose between clouds of two places.

Synthetic rooms seen from their sensors (the measure of :mod:`cgags_ros.pipeline.gates`),
the gate's decision (:mod:`cgags_ros.validity`), and real fragments of two different
3DMatch scenes that the other gates accepted (:mod:`bench.no_overlap`'s two seeded
samples), refused; right low-overlap 3DLoMatch poses stay valid.
"""

from __future__ import annotations

from bench.datasets import threedmatch as tdm
from cgags_ros import validity
from cgags_ros.config import PipelineConfig
from cgags_ros.pipeline import register_clouds
from cgags_ros.pipeline.gates import free_space_surface, free_space_violation
from cgags_ros.refusal import RefusalCode as Code
import numpy as np
import pytest
from scipy.spatial import cKDTree
from test_no_shared_surface import SCENES
from test_validity import passing

CFG = PipelineConfig()
V = 0.05
# (source scene, fragment, target scene, fragment): valid before this gate, at confidence
# 0.69 (seed 0 of bench.no_overlap cross) and 0.97 (seed 1)
ACCEPTED_BEFORE = [('hotel', 32, 'kitchen', 35), ('home', 17, 'hotel', 22)]
# 3DLoMatch (scene, target, source), right and valid: of those the gate keeps, the poses that
# put the most surface in free space from both sensors in three scenes (bench.no_overlap)
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


def _measured(source, target, T=np.eye(4)):
    return free_space_surface(source, cKDTree(source), target, cKDTree(target), T, V)


def test_surfaces_in_free_space_count_only_when_both_sensors_see_them():
    rng = np.random.default_rng(0)
    room = _room(4.0, 1.5, rng)
    # the same room seen again: nothing in free space
    assert _measured(_room(4.0, 1.5, rng), room) < 0.01
    # another room on the same floor: its wall ahead stands in front of this room's (the
    # target's sensor saw through it), this room's left wall in front of the other's
    other = _room(2.5, 3.0, rng)
    both = _measured(other, room)
    assert both > 0.2
    # a smaller room inside this one: only this room's sensor sees surfaces in its free
    # space (the other's walls stand in front of this one's); its own view has nothing
    inside = _room(2.5, 1.0, rng)
    assert free_space_violation(inside, room, np.eye(4), 2 * V, 2.0) > 0.3
    assert _measured(inside, room) < 0.01
    # the gate reads the measure (NaN: not measured, e.g. against a map, passes)
    refusal = validity.gate_refusal(passing(free_space_surface=both), CFG)
    assert refusal is not None and refusal.code is Code.FREE_SPACE
    assert 'both sensors' in refusal.message
    assert validity.gate_refusal(passing(free_space_surface=np.nan), CFG) is None
    assert validity.overlap_refusal(passing(free_space_surface=0.0), CFG) is None
    assert both > 2 * validity.MAX_FREE_SPACE_SURFACE


@pytest.fixture(scope='module')
def fragment(data_dir):
    root = data_dir / '3dmatch_benchmark'
    scenes = {name: tdm.Fragments(root, scene) for name, scene in SCENES.items()}
    return lambda name, k: scenes[name][k]


@pytest.mark.parametrize('pair', ACCEPTED_BEFORE)
def test_fragments_of_two_buildings_that_passed_every_other_gate_are_refused(fragment, pair):
    source_scene, s, target_scene, t = pair
    result = register_clouds(fragment(source_scene, s), fragment(target_scene, t),
                             voxel_size=0.05)
    assert not result.valid
    assert result.refusal.code is Code.FREE_SPACE, result.refusal
    # the other gates pass it: the shared surface, the free space from either sensor alone
    assert validity.shared_surface_refusal(result, CFG) is None
    assert result.free_space_violation <= CFG.gates.max_free_space_violation
    summary = result.summary()
    assert summary['free_space_surface'] > validity.MAX_FREE_SPACE_SURFACE
    assert summary['refusal']['code'] == 'free_space'


@pytest.mark.parametrize('scene, target, source', LOW_OVERLAP)
def test_right_low_overlap_poses_stay_valid(benchmark_pair, scene, target, source):
    src, tgt, truth = benchmark_pair(scene, target, source)
    result = register_clouds(src, tgt, voxel_size=0.05)
    assert result.valid, result.refusal
    assert tdm.registered(result.transform, truth)
    assert result.free_space_surface <= validity.MAX_FREE_SPACE_SURFACE
