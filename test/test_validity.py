"""
cgags_ros.validity and cgags_ros.refusal: every refusal code from a real or constructed case.

Real cases run the core or the pipeline on data that must be refused for one reason; the
constructed ones give :mod:`cgags_ros.validity` measurements (some of them measured on real
geometry by the gates' own functions) and check the verdict and its order.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
import pickle
import re

from cgags_ros import fitted, validity
from cgags_ros.config import pipeline_config_from, PipelineConfig
from cgags_ros.config.core import CoreConfig
from cgags_ros.config.node import configs_from_parameters
from cgags_ros.engine.interface import PairResult, StartFailed
from cgags_ros.errors import (BagError, CgagsError, DegenerateCorrespondencesError,
                              EmptyCloudError, InvalidConfigError, InvalidInputError,
                              MalformedCloudError)
from cgags_ros.frontend.refine import Alignment
from cgags_ros.geometry import apply_transform, cross_spread
from cgags_ros.pipeline import register_clouds
from cgags_ros.pipeline.free_space import depth_status, free_space_violation
from cgags_ros.pipeline.gates import observability
from cgags_ros.pipeline.result import Candidate, PipelineResult
from cgags_ros.pipeline.twins import add_twin
from cgags_ros.refusal import Refusal, RefusalCode as Code, summary
from cgags_ros.registration import register_correspondences, RegistrationResult
from cgags_ros.relocalization.service_calls import not_localized
from cgags_ros.runtime.supervisor import ProcessCrashed, RegistrationTimeout
from cgags_ros.tracking.prediction import difference
from cgags_ros.validity import consensus
import numpy as np
import pytest
from waiting import box_room

DOCS = Path(__file__).resolve().parents[1] / 'docs' / 'refusals.md'
CFG = PipelineConfig()
NO_OVERLAP = {Code.FEW_INLIERS, Code.CHANCE_LEVEL, Code.NO_ESTIMATE}


def passing(**values) -> PipelineResult:
    """Return a valid result whose measurements pass every gate of the default config."""
    fields = {'inliers': np.arange(50), 'num_correspondences': 400, 'num_hypotheses': 100,
              'inlier_threshold': 0.05, 'inlier_spread': 1.0, 'chance_level': 8,
              'runner_up': 5, 'chance_inliers': 1.0, 'chance_bound': 9.0,
              'observability': 0.3, 'fitness': 0.8, 'free_space_violation': 0.05,
              'refusal': None}
    fields.update(values)
    return PipelineResult(**fields)


def _yaw(angle, shift=(0.0, 0.0, 0.0)):
    c, s = np.cos(angle), np.sin(angle)
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    T[:3, 3] = shift
    return T


# --- the codes, their forms and the docs ------------------------------------------------------
def test_every_code_is_stable_snake_case_and_documented_once():
    values = [c.value for c in Code]
    assert len(set(values)) == len(values)
    assert all(re.fullmatch(r'[a-z]+(_[a-z]+)*', v) for v in values), values
    documented = re.findall(r'^\| `([a-z_]+)` \|', DOCS.read_text(encoding='utf-8'), re.M)
    assert sorted(documented) == sorted(values)  # each code has its row, no stale row


def test_a_refusal_reads_as_code_and_message_in_every_form():
    r = Refusal(Code.TILT, 'the clouds are not levelled')
    assert str(r) == 'tilt: the clouds are not levelled'
    assert r.summary() == {'code': 'tilt', 'message': 'the clouds are not levelled'}
    assert summary(r) == r.summary() and summary(None) is None
    assert Refusal(Code(r.summary()['code']), r.summary()['message']) == r  # read back
    result = RegistrationResult()
    assert not result.valid and result.refusal.code is Code.NO_ESTIMATE  # nothing ran yet
    result.finish(0.0, r)
    assert (result.valid, result.reason, result.summary()['refusal']) == (
        False, r.message, r.summary())
    assert result.finish(0.0).valid and result.reason == '' and (
        result.summary()['refusal'] is None)


def test_a_refusal_says_its_code_once():
    """The code leads ``str()`` and a failed request's answer; the message never repeats it."""
    best = Candidate(np.eye(4), 40, 0.8)
    twin = passing(candidates=[best, Candidate(_yaw(np.pi, (1.0, 0.0, 0.0)), 35, 0.8, 35 / 40)],
                   ambiguous=True)
    twin.refusal = validity.ambiguity_refusal(twin, CFG)
    turned = difference(np.eye(4), _yaw(np.radians(CFG.tracking.max_correction_deg + 1.0)))
    node = configs_from_parameters({})[1]
    refusals = [
        twin.refusal, validity.quality_refusal(twin, node),
        validity.sequence_ambiguity_refusal(3, 180.0, 1.0),
        validity.confidence_refusal(passing(confidence=0.1), CFG.gates.min_confidence),
        validity.overlap_refusal(passing(observability=0.0), CFG),
        validity.overlap_refusal(passing(free_space_violation=0.9), CFG),
        validity.tracking_refusal(*turned, 0.8, 0.8, CFG),
        validity.tracking_refusal(0.0, 0.0, 0.1, 1.0, CFG)]
    for refusal in refusals:
        words = refusal.code.value.split('_')
        lead = re.split(r'[^a-z]+', refusal.message.lower())[:len(words)]
        assert lead != words and lead[:1] != words[:1], refusal  # 'tracking', 'degenerate', ...
    answer = not_localized(validity.quality_refusal(twin, node))
    assert answer.startswith('ambiguous: not localized: a distinct pose') and (
        answer.count('ambiguous') == 1), answer


@pytest.mark.parametrize('error, code', [
    (InvalidInputError, Code.BAD_INPUT), (MalformedCloudError, Code.BAD_INPUT),
    (BagError, Code.BAD_INPUT), (EmptyCloudError, Code.TOO_FEW_POINTS),
    (InvalidConfigError, Code.BAD_CONFIG),
    (DegenerateCorrespondencesError, Code.NO_CORRESPONDENCES),
    (RegistrationTimeout, Code.TIMEOUT), (ProcessCrashed, Code.PROCESS_CRASHED),
    (StartFailed, Code.START_FAILED), (CgagsError, Code.INTERNAL_ERROR),
])
def test_every_error_carries_its_code(error, code):
    exc = error('what went wrong')
    assert exc.code is code and exc.refusal == Refusal(code, 'what went wrong')
    # a code given where it is raised survives the pipe from the registration process
    moved = pickle.loads(pickle.dumps(error('a line', code=Code.COLLINEAR)))
    assert type(moved) is error and moved.refusal == Refusal(Code.COLLINEAR, 'a line')


# --- the input --------------------------------------------------------------------------------
def test_empty_nan_and_malformed_input():
    rng = np.random.default_rng(0)
    cloud = rng.uniform(-1, 1, (2000, 3))
    with pytest.raises(EmptyCloudError) as info:
        register_clouds(np.full((50, 3), np.nan), cloud, voxel_size=0.1)
    assert info.value.code is Code.TOO_FEW_POINTS
    with pytest.raises(InvalidInputError) as info:
        register_clouds(np.zeros((10, 2)), cloud, voxel_size=0.1)
    assert info.value.code is Code.BAD_INPUT
    with pytest.raises(InvalidInputError) as info:
        register_correspondences(np.full((5, 3), np.nan), np.zeros((5, 3)), resolution=0.1)
    assert info.value.code is Code.BAD_INPUT
    # finite but too small for the voxel size: a result, refused, not an error
    result = register_clouds(cloud[:5], cloud, voxel_size=0.1)
    assert result.refusal.code is Code.TOO_FEW_POINTS and 'MIN_POINTS' in result.reason


# --- the correspondences and the core ---------------------------------------------------------
def test_too_few_or_identical_correspondences():
    with pytest.raises(DegenerateCorrespondencesError, match='at least 3') as info:
        register_correspondences(np.zeros((2, 3)), np.ones((2, 3)), inlier_threshold=0.1)
    assert info.value.code is Code.NO_CORRESPONDENCES
    src = np.tile([1.0, 2.0, 3.0], (6, 1))
    with pytest.raises(DegenerateCorrespondencesError, match='identical') as info:
        register_correspondences(src, np.eye(3)[[0, 1, 2, 0, 1, 2]], inlier_threshold=0.1)
    assert info.value.code is Code.NO_CORRESPONDENCES


def test_line_like_clouds_and_correspondences_are_collinear():
    rng = np.random.default_rng(1)
    line = np.c_[rng.uniform(-2, 2, 5000), rng.normal(0, 0.002, (5000, 2))]
    result = register_clouds(line, apply_transform(_yaw(0.5, (0.2, 0.1, 0.0)), line),
                             voxel_size=0.05)
    assert result.refusal.code is Code.COLLINEAR and 'degenerate source cloud' in result.reason
    assert validity.line_cloud_refusal(cross_spread(line), 'source', 0.05).code is Code.COLLINEAR
    assert validity.line_cloud_refusal(cross_spread(box_room(rng, 2000)), 'source', 0.05) is None
    exact = np.outer(np.arange(6.0), [1.0, 0.5, 0.2])
    with pytest.raises(DegenerateCorrespondencesError, match='collinear') as info:
        register_correspondences(exact, exact + 1.0, inlier_threshold=0.1)
    assert info.value.code is Code.COLLINEAR


def test_no_estimate_without_length_consistent_pairs_or_subsets():
    rng = np.random.default_rng(1)
    res = register_correspondences(rng.uniform(0, 1, (50, 3)), rng.uniform(0, 1000, (50, 3)),
                                   inlier_threshold=1e-4)
    assert res.refusal.code is Code.NO_ESTIMATE and 'length-consistent' in res.reason
    assert consensus.no_model_refusal(0, yaw_only=False).code is Code.NO_ESTIMATE
    assert consensus.no_model_refusal(0, yaw_only=True).code is Code.NO_ESTIMATE
    assert consensus.no_model_refusal(4, yaw_only=False).code is Code.COLLINEAR
    assert 'vertical' in consensus.no_model_refusal(4, yaw_only=True).message


def test_random_correspondences_are_refused_as_no_overlap():
    rng = np.random.default_rng(4)
    res = register_correspondences(rng.uniform(0, 1, (800, 3)), rng.uniform(0, 1, (800, 3)),
                                   inlier_threshold=0.02, seed=0)
    assert res.refusal.code in NO_OVERLAP, res.refusal
    # the measurements the verdict came from are on the result
    assert res.chance_level > 0 and res.runner_up >= 0


def test_the_consensus_verdict_in_order():
    cfg = CoreConfig()
    good = RegistrationResult(inliers=np.arange(30), inlier_threshold=0.05, inlier_spread=0.4,
                              chance_level=10, runner_up=6)
    assert consensus.consensus_refusal(good, cfg) is None
    few = dataclasses.replace(good, inliers=np.arange(cfg.min_inliers - 1), inlier_spread=0.0)
    assert consensus.consensus_refusal(few, cfg).code is Code.FEW_INLIERS  # before its shape
    line = dataclasses.replace(good, inlier_spread=0.01)
    assert consensus.consensus_refusal(line, cfg).code is Code.COLLINEAR
    vertical = consensus.consensus_refusal(line, CoreConfig(motion_model='4dof'))
    assert vertical.code is Code.COLLINEAR and 'vertical line' in vertical.message
    chance = dataclasses.replace(good, chance_level=31)
    assert consensus.consensus_refusal(chance, cfg).code is Code.CHANCE_LEVEL
    rival = dataclasses.replace(good, runner_up=int(np.ceil(30 / cfg.distinct_ratio)) + 1)
    assert consensus.consensus_refusal(rival, cfg).code is Code.AMBIGUOUS
    # 4-DoF: a tilt is what the user acts on, said beside the other reason
    four = CoreConfig(motion_model='4dof')
    tilted = dataclasses.replace(good, tilt_deg=four.max_tilt_deg + 1)
    assert consensus.consensus_refusal(tilted, four).code is Code.TILT
    both = consensus.consensus_refusal(dataclasses.replace(tilted, chance_level=31), four)
    assert both.code is Code.TILT and 'does not stand out' in both.message
    assert 'not levelled' in both.message
    assert consensus.consensus_refusal(dataclasses.replace(good, tilt_deg=np.nan), four) is None


# --- the gates on the refined estimate --------------------------------------------------------
def test_the_gates_in_order_on_measured_geometry():
    assert validity.gate_refusal(passing(), CFG) is None
    # a plane under the plane: in-plane motion is free (measured by the gate's function)
    rng = np.random.default_rng(0)
    plane = np.c_[rng.uniform(-1, 1, (2000, 2)), rng.normal(0, 0.002, 2000)]
    idx = np.arange(len(plane))
    flat = observability(plane, np.tile([0.0, 0.0, 1.0], (len(plane), 1)),
                         Alignment(np.eye(4), 1.0, 0.0, 0.1, idx, idx))
    assert validity.gate_refusal(passing(observability=flat), CFG).code is Code.DEGENERATE_AXIS
    assert validity.gate_refusal(passing(observability=np.nan), CFG).code is (
        Code.DEGENERATE_AXIS)  # not measurable: not trusted
    # a room turned by 90 degrees puts its long walls inside the other view's free space
    room = box_room(rng, 6000)
    T = _yaw(0.4, (0.5, -0.3, 0.1))
    source = apply_transform(np.linalg.inv(T), box_room(rng, 6000))
    turned = free_space_violation(source, room, _yaw(np.pi / 2) @ T, 0.1, 2.0)
    assert validity.gate_refusal(passing(free_space_violation=turned), CFG).code is (
        Code.FREE_SPACE)
    right = free_space_violation(source, room, T, 0.1, 2.0)
    assert validity.gate_refusal(passing(free_space_violation=right), CFG) is None
    # an estimate the correspondences did not settle is held to a tighter bound
    between = 0.9 * CFG.gates.max_free_space_violation
    assert validity.gate_refusal(passing(free_space_violation=between), CFG) is None
    assert validity.gate_refusal(passing(free_space_violation=between), CFG,
                                 unsettled=True).code is Code.FREE_SPACE
    fit = dataclasses.replace(CFG, gates=dataclasses.replace(CFG.gates, min_fitness=0.5))
    assert validity.gate_refusal(passing(fitness=0.2), fit).code is Code.LOW_FITNESS
    four = pipeline_config_from({'core.motion_model': '4dof'})
    steep = four.core.max_tilt_deg + 0.5
    assert validity.gate_refusal(passing(tilt_deg=steep), four).code is Code.TILT
    # the first gate that fails is the one said
    worst = passing(chance_bound=60.0, fitness=0.2, observability=flat, tilt_deg=steep)
    assert validity.gate_refusal(worst, fit).code is Code.CHANCE_LEVEL
    assert validity.gate_refusal(passing(chance_bound=np.nan), CFG).code is Code.CHANCE_LEVEL
    off = dataclasses.replace(CFG, gates=dataclasses.replace(CFG.gates, significance=0.0))
    assert validity.gate_refusal(passing(chance_bound=np.nan), off) is None


def test_free_space_reads_only_the_points_within_the_other_sensors_reach():
    """The share from a scan's view is the same as with every map point judged (depth_status)."""
    rng = np.random.default_rng(3)
    room = box_room(rng, 6000)
    far = box_room(rng, 20000, size=(60.0, 40.0, 5.0)) + [500.0, 0.0, 0.0]
    world = np.vstack([room, far])
    T = _yaw(0.4, (0.5, -0.3, 0.1))
    scan = apply_transform(np.linalg.inv(T), box_room(rng, 6000))
    for pose in (T, _yaw(np.pi / 2) @ T, _yaw(0.1, (2.0, 0.0, 0.0)) @ T):
        front, on = depth_status(apply_transform(np.linalg.inv(pose), world), scan, 0.1, 2.0)
        every = front.sum() / (front.sum() + on.sum())
        assert free_space_violation(scan, world, pose, 0.1, 2.0, target_view=False) == every
    assert free_space_violation(scan, world, _yaw(np.pi / 2) @ T, 0.1, 2.0, False) > 0.1


def test_a_symmetric_room_is_ambiguous():
    rng = np.random.default_rng(0)
    room = box_room(rng, 40000)
    T = _yaw(0.4, (0.3, -0.2, 0.0))
    source = apply_transform(np.linalg.inv(T), box_room(rng, 40000))
    result = register_clouds(source, room, voxel_size=0.1)
    assert result.refusal.code is Code.AMBIGUOUS and result.ambiguous, result.refusal
    turned = result.candidates[1].transform @ np.linalg.inv(result.candidates[0].transform)
    assert abs(np.degrees(np.arccos(np.clip(turned[0, 0], -1, 1))) - 180) < 10  # its twin


def test_ambiguity_names_the_rival():
    best = Candidate(np.eye(4), 40, 0.8)
    rival = Candidate(_yaw(np.pi, (1.0, 0.0, 0.0)), 35, 0.8, 35 / 40)
    assert validity.ambiguity_refusal(passing(candidates=[best, rival]), CFG) is None
    refusal = validity.ambiguity_refusal(passing(candidates=[best, rival], ambiguous=True), CFG)
    assert refusal.code is Code.AMBIGUOUS
    assert '180 deg, 1.00 m away' in refusal.message and '35 inliers against 40' in (
        refusal.message)


def test_a_place_the_whole_map_backs_no_more_than_chance_is_ambiguous_if_it_backs_another():
    # Above the chance bound, or no better supported elsewhere: not judged ambiguous.
    assert validity.elsewhere_refusal(3, 2, 20, 90.0, 30.0, CFG) is None
    assert validity.elsewhere_refusal(2, 2, 2, 90.0, 30.0, CFG) is None
    refusal = validity.elsewhere_refusal(2, 2, 5, 90.0, 30.0, CFG)
    assert refusal.code is Code.AMBIGUOUS
    assert '90 deg, 30.00 m away' in refusal.message and 'has 2 of them' in refusal.message
    assert validity.elsewhere_refusal(0, 1, 1, 90.0, 30.0, CFG).code is Code.AMBIGUOUS


def test_only_a_collinear_core_refusal_is_left_to_the_gates():
    collinear = Refusal(Code.COLLINEAR, 'the inliers are nearly collinear')
    core = RegistrationResult(inliers=np.arange(20), refusal=collinear)
    assert validity.unsettled(core, CFG)
    assert not validity.unsettled(dataclasses.replace(core, inliers=np.arange(2)), CFG)
    assert not validity.unsettled(
        dataclasses.replace(core, refusal=Refusal(Code.CHANCE_LEVEL, 'chance')), CFG)
    assert not validity.unsettled(dataclasses.replace(core, refusal=None), CFG)
    for other in ({'refine.method': 'none'}, {'core.motion_model': '4dof'}):
        assert not validity.unsettled(core, pipeline_config_from(other)), other


class _Twin:
    """A twin's measures, counted as they are read (validity reads them lazily)."""

    def __init__(self, fitness: float, free_space: float):
        self._fitness, self._free_space, self.read = fitness, free_space, []

    @property
    def fitness(self) -> float:
        self.read.append('fitness')
        return self._fitness

    @property
    def free_space(self) -> float:
        self.read.append('free_space')
        return self._free_space


def test_a_plausible_twin_makes_the_estimate_ambiguous():
    """Apart, as good a fit and clear of free space: each test read only when the last passed."""
    voxel, fitness = 0.05, 0.8
    good = _Twin(0.79, 0.02)
    assert validity.plausible_twin(90.0, 0.0, good, fitness, voxel, 10.0)
    assert good.read == ['fitness', 'free_space']
    back = _Twin(0.79, 0.02)  # settled back onto the estimate: nothing else is measured
    assert not validity.plausible_twin(2.0, 0.1, back, fitness, voxel, 10.0) and not back.read
    worse = _Twin(0.3, 0.02)
    assert not validity.plausible_twin(0.0, 0.5, worse, fitness, voxel, 10.0)
    assert worse.read == ['fitness']
    assert not validity.plausible_twin(90.0, 0.0, _Twin(0.79, 0.2), fitness, voxel, 10.0)
    best = Candidate(np.eye(4), 40, 0.8)
    result = passing(candidates=[best])
    assert validity.ambiguity_refusal(result, CFG) is None
    add_twin(result, Candidate(_yaw(np.pi / 2), 38, 0.79))
    result.ambiguous = True
    assert validity.ambiguity_refusal(result, CFG).code is Code.AMBIGUOUS


def test_each_test_of_the_twins_verdict_at_its_limit():
    """The shipped limits by default, a study's by argument; an unmeasured violation is clear."""
    voxel = 0.1
    assert validity.settled_apart(10.5, 0.0, voxel, 10.0)
    assert validity.settled_apart(0.0, (fitted.TWIN_APART + 0.1) * voxel, voxel, 10.0)
    assert not validity.settled_apart(10.0, fitted.TWIN_APART * voxel, voxel, 10.0)
    assert not validity.settled_apart(0.0, 3 * voxel, voxel, 10.0, apart=6.0)
    assert validity.fits_as_well(1.01 / fitted.TWIN_OVERLAP_RATIO, 1.0)
    assert not validity.fits_as_well(0.5, 1.0, ratio=1.5)
    assert validity.clear_of_free_space(fitted.TWIN_MAX_VIOLATION)
    assert not validity.clear_of_free_space(0.2, limit=0.15)
    assert validity.clear_of_free_space(float('nan'))


def test_candidates_are_ambiguous_on_inliers_and_after_settling():
    ratio = CFG.gates.ambiguity_ratio
    assert validity.outnumbered(ratio * 0.99, CFG) and not validity.outnumbered(ratio, CFG)
    assert not validity.outnumbered(float('inf'), CFG)  # no runner-up
    limit = validity.free_space_limit(CFG, unsettled=True)
    settled = dataclasses.make_dataclass(
        'Settled', ['overlap', 'free_space', 'others', 'alone'])
    assert not validity.still_ambiguous(settled(0.6, 0.0, [0.6 / ratio - 0.01], False), CFG)
    assert validity.still_ambiguous(settled(0.6, 0.0, [0.6 / ratio + 0.01], False), CFG)
    assert validity.still_ambiguous(settled(0.6, limit + 0.01, [], False), CFG)
    assert not validity.still_ambiguous(settled(0.6, float('nan'), [], False), CFG)
    assert not validity.still_ambiguous(settled(0.6, limit + 0.01, [0.9], True), CFG)
    assert validity.passes_free_space(CFG.gates.max_free_space_violation, CFG)
    assert not validity.passes_free_space(CFG.gates.max_free_space_violation + 0.01, CFG)
    assert validity.passes_free_space(float('nan'), CFG)


def test_a_low_calibrated_confidence_is_refused():
    assert validity.confidence_refusal(passing(confidence=0.9), CFG.gates.min_confidence) is None
    low = validity.confidence_refusal(passing(confidence=0.1), CFG.gates.min_confidence)
    assert low.code is Code.LOW_CONFIDENCE and 'P(right) 0.10' in low.message
    assert validity.confidence_refusal(passing(confidence=0.1), 0.0) is None  # off


# --- the tracked path and the relocalizer -----------------------------------------------------
def test_a_tracked_pose_is_judged_by_the_overlap_and_the_tracker_checks():
    # the overlap gates need no correspondences: a chance-level count does not refuse
    assert validity.overlap_refusal(passing(chance_bound=60.0), CFG) is None
    assert validity.overlap_refusal(passing(observability=0.0), CFG).code is (
        Code.DEGENERATE_AXIS)
    track = CFG.tracking
    small = difference(np.eye(4), _yaw(np.radians(0.5 * track.max_correction_deg)))
    assert validity.tracking_refusal(*small, 0.8, 0.8, CFG) is None
    turned = difference(np.eye(4), _yaw(np.radians(track.max_correction_deg + 1.0)))
    jump = validity.tracking_refusal(*turned, 0.8, 0.8, CFG)
    assert jump.code is Code.TRACKING_LOST and 'a jump' in jump.message
    slid = difference(np.eye(4), _yaw(0.0, (2 * track.max_correction_factor * CFG.voxel_size,
                                            0.0, 0.0)))
    assert validity.tracking_refusal(*slid, 0.8, 0.8, CFG).code is Code.TRACKING_LOST
    drop = validity.tracking_refusal(*small, 0.5 * track.min_fitness_ratio, 1.0, CFG)
    assert drop.code is Code.TRACKING_LOST and 'fitness' in drop.message


def test_the_relocalizer_refusals():
    missed = validity.unexplained_refusal([1, 2])
    assert missed.code is Code.UNEXPLAINED and 'misses scan(s) 1, 2' in missed.message
    twin = validity.sequence_ambiguity_refusal(3, 180.0, 1.0)
    assert twin.code is Code.AMBIGUOUS and '180 deg, 1.00 m away' in twin.message
    assert validity.more_scans_refusal(1, 2).code is Code.MORE_SCANS
    assert validity.more_scans_refusal(2, 2) is None


def test_the_result_topic_carries_the_refusal():
    rejected = Refusal(Code.BAD_INPUT, 'source cloud rejected: no x field')
    out = json.loads(PairResult(5, 'lidar', 'rejected', refusal=rejected).to_json())
    assert out['refusal'] == {'code': 'bad_input', 'message': rejected.message}
    assert (out['cause'], out['message']) == ('bad_input', rejected.message)  # one classification
    assert out['reason'] == rejected.message and out['valid'] is False
    refused = passing(refusal=Refusal(Code.LOW_FITNESS, 'fitness 0.1'))
    out = json.loads(PairResult(5, 'lidar', 'published', result=refused).to_json())
    assert out['refusal'] == {'code': 'low_fitness', 'message': 'fitness 0.1'}
    out = json.loads(PairResult(5, 'lidar', 'published', valid=True, result=passing()).to_json())
    assert out['refusal'] is None and out['valid'] is True


# --- the node's initial pose ------------------------------------------------------------------
def test_the_initial_pose_guards_in_order():
    cfg = configs_from_parameters({'relocalization.min_inliers': 20,
                                   'relocalization.min_ratio': 2.0,
                                   'relocalization.min_fitness': 0.3})[1]
    assert validity.quality_refusal(passing(), cfg) is None
    invalid = Refusal(Code.FREE_SPACE, 'stacked walls')
    assert validity.quality_refusal(passing(refusal=invalid), cfg) is invalid  # its own
    assert validity.quality_refusal(
        passing(ambiguous=True, refusal=Refusal(Code.AMBIGUOUS, 'twin')), cfg).code is (
        Code.AMBIGUOUS)
    assert validity.quality_refusal(passing(inliers=np.arange(19)), cfg).code is (
        Code.FEW_INLIERS)
    assert validity.quality_refusal(passing(runner_up_ratio=1.5), cfg).code is Code.LOW_RATIO
    assert validity.quality_refusal(passing(fitness=0.2), cfg).code is Code.LOW_FITNESS
