"""
The shared-surface gate: clouds of different places are refused as ``no_shared_surface``.

Real fragments of two different 3DMatch scenes (pairs :mod:`bench.no_overlap` measured:
one the defaults accepted before this gate, three they called ambiguous), a synthetic pair
that shares only a floor and one wall corner (measured by the gates' own functions), right
low-overlap 3DLoMatch pairs that must stay valid, and a scan taken outside the map.
"""

from __future__ import annotations

import dataclasses

from bench.datasets import threedmatch as tdm
from cgags_ros import validity
from cgags_ros.config import PipelineConfig
from cgags_ros.frontend.features import extract_features
from cgags_ros.frontend.refine import evaluate_alignment
from cgags_ros.pipeline import register_clouds
from cgags_ros.pipeline.gates import descriptor_ratio, shared_area
from cgags_ros.pipeline.result import PipelineResult
from cgags_ros.refusal import Refusal, RefusalCode as Code
from cgags_ros.validity.shared import MAX_FREE_SPACE_SURFACE, THIN_OVERLAP
import numpy as np
import pytest
from test_validity import passing as passing_gates

CFG = PipelineConfig()
SCENES = {'kitchen': '7-scenes-redkitchen', 'home': 'sun3d-home_at-home_at_scan1_2013_jan_1',
          'hotel': 'sun3d-hotel_uc-scan3',
          'lab': 'sun3d-mit_lab_hj-lab_hj_tea_nov_2_2012_scan1_erika'}
# (source scene, fragment, target scene, fragment) of bench.no_overlap's seeded sample
ACCEPTED_BEFORE = ('home', 23, 'lab', 16)  # valid at confidence 0.81 without the gate
AMBIGUOUS_BEFORE = [('lab', 6, 'home', 51), ('home', 42, 'hotel', 4), ('kitchen', 26, 'home', 19)]
LOW_OVERLAP = [('7-scenes-redkitchen', 0, 26)]  # 3DLoMatch (target, source), right and valid


@pytest.fixture(scope='module')
def fragment(data_dir):
    root = data_dir / '3dmatch_benchmark'
    scenes = {name: tdm.Fragments(root, scene) for name, scene in SCENES.items()}
    return lambda name, k: scenes[name][k]


def passing(**values) -> PipelineResult:
    """Return :func:`test_validity.passing` with a shared surface that passes the gate too."""
    return passing_gates(**{'shared_area': 5.0, 'descriptor_ratio': 0.5, 'voxel_size': 0.05,
                            **values})


def test_the_gate_reads_the_area_then_the_descriptors_and_outranks_an_ambiguity():
    gates = CFG.gates
    assert validity.gate_refusal(passing(), CFG) is None
    small = passing(shared_area=0.9 * gates.min_shared_area * 0.05 ** 2)
    assert validity.gate_refusal(small, CFG).code is Code.NO_SHARED_SURFACE
    assert 'too little to tell one place' in validity.gate_refusal(small, CFG).message
    unlike = passing(descriptor_ratio=gates.max_descriptor_ratio + 0.05)
    assert validity.gate_refusal(unlike, CFG).code is Code.NO_SHARED_SURFACE
    assert 'look unalike' in validity.gate_refusal(unlike, CFG).message
    assert validity.gate_refusal(passing(shared_area=np.nan, descriptor_ratio=np.nan),
                                 CFG) is None  # not measured: the other gates decide
    # a thin overlap that stands surfaces where both sensors saw free space
    above = MAX_FREE_SPACE_SURFACE + 0.01
    seen = passing(free_space_surface=above, overlap=THIN_OVERLAP - 0.1)
    assert validity.gate_refusal(seen, CFG).code is Code.NO_SHARED_SURFACE
    assert 'free space' in validity.gate_refusal(seen, CFG).message
    for fine in (passing(free_space_surface=above, overlap=THIN_OVERLAP),  # one place
                 passing(free_space_surface=MAX_FREE_SPACE_SURFACE, overlap=0.1),
                 passing(free_space_surface=np.nan, overlap=0.1)):  # not sensor frames
        assert validity.gate_refusal(fine, CFG) is None
    off = dataclasses.replace(CFG, gates=dataclasses.replace(
        gates, min_shared_area=0.0, max_descriptor_ratio=0.0))
    assert validity.gate_refusal(small, off) is None and validity.gate_refusal(unlike, off) \
        is None
    # said before chance level: it says what the evidence shows, where the count only fails
    assert validity.gate_refusal(passing(shared_area=0.0, chance_bound=60.0), CFG).code is (
        Code.NO_SHARED_SURFACE)
    # an ambiguity overrides every other gate, not this one
    twin = Refusal(Code.AMBIGUOUS, 'a twin')
    none = validity.gate_refusal(small, CFG)
    assert validity.said_over_ambiguity(none, twin) is none
    free = Refusal(Code.FREE_SPACE, 'stacked')
    assert validity.said_over_ambiguity(free, twin) is twin
    assert validity.said_over_ambiguity(None, None) is None


def _floor_and_corner(rng, clutter_at):
    """Return a 0.6 m floor patch, one wall corner (0.4 m high) and a box of its own."""
    n = 4000
    floor = np.c_[rng.uniform(0, 0.6, (n, 2)), np.zeros(n)]
    wall_x = np.c_[np.zeros(n), rng.uniform(0, 0.6, n), rng.uniform(0, 0.4, n)]
    wall_y = np.c_[rng.uniform(0, 0.6, n), np.zeros(n), rng.uniform(0, 0.4, n)]
    box = rng.uniform(-0.4, 0.4, (3 * n, 3))
    face = rng.integers(0, 3, 3 * n)
    box[np.arange(3 * n), face] = np.sign(box[np.arange(3 * n), face]) * 0.4
    return np.vstack([floor, wall_x, wall_y, box + clutter_at])


def test_a_pair_that_shares_only_a_floor_and_a_wall_corner_shares_no_surface():
    rng = np.random.default_rng(0)
    source = _floor_and_corner(rng, np.array([2.5, 0.5, 0.4]))  # its own furniture
    target = _floor_and_corner(rng, np.array([0.5, 2.5, 0.4]))  # another room's
    cfg = dataclasses.replace(CFG, voxel_size=0.05)
    fs = extract_features(source, cfg.voxel_size, cfg.frontend)
    ft = extract_features(target, cfg.voxel_size, cfg.frontend)
    distance = cfg.refine.max_correspondence_distance_factor * cfg.voxel_size
    align = evaluate_alignment(fs.points, ft.tree, np.eye(4), distance)
    back = evaluate_alignment(ft.points, fs.tree, np.eye(4), distance)
    area = shared_area(align, back, cfg.voxel_size)
    assert 0.6 < area < 1.1  # the floor and the corner: about 0.36 + 0.48 m^2
    measured = passing(shared_area=area,
                       descriptor_ratio=descriptor_ratio(fs.descriptors, ft.descriptors,
                                                         align))
    refusal = validity.gate_refusal(measured, cfg)
    assert refusal is not None and refusal.code is Code.NO_SHARED_SURFACE, refusal


@pytest.mark.parametrize('pair', [ACCEPTED_BEFORE, *AMBIGUOUS_BEFORE])
def test_fragments_of_two_buildings_are_refused_as_sharing_no_surface(fragment, pair):
    source_scene, s, target_scene, t = pair
    result = register_clouds(fragment(source_scene, s), fragment(target_scene, t),
                             voxel_size=0.05)
    assert not result.valid
    assert result.refusal.code is Code.NO_SHARED_SURFACE, result.refusal
    assert np.isfinite(result.shared_area) and result.summary()['refusal']['code'] == (
        'no_shared_surface')


@pytest.mark.parametrize('scene, target, source', LOW_OVERLAP)
def test_right_low_overlap_pairs_stay_valid(benchmark_pair, scene, target, source):
    src, tgt, truth = benchmark_pair(scene, target, source)
    result = register_clouds(src, tgt, voxel_size=0.05)
    assert result.valid, result.refusal
    assert tdm.registered(result.transform, truth)
    assert result.shared_area >= CFG.gates.min_shared_area * 0.05 ** 2
