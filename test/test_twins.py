"""cgags_ros.pipeline.twins: the poses a symmetric or loosely constrained scene also accepts."""

from __future__ import annotations

from cgags_ros import fitted, validity
from cgags_ros.config import GatesConfig, PipelineConfig
from cgags_ros.frontend.matching import Correspondences
from cgags_ros.frontend.refine import evaluate_alignment
from cgags_ros.geometry import rotation_error_deg, translation_error
from cgags_ros.pipeline import cached_features, twins
from cgags_ros.pipeline.candidates import MIN_ROTATION_DEG
from cgags_ros.pipeline.free_space import measured_free_space
from cgags_ros.pipeline.result import Candidate, PipelineResult
from cgags_ros.pipeline.settle import Pair, settle, TWIN
from cgags_ros.pipeline.twins import add_twin, find_twin
import numpy as np
from scipy.spatial.transform import Rotation

VOXEL = 0.1


def _box(lo, hi, step: float = 0.05) -> np.ndarray:
    """Return points on the faces of the axis-aligned box ``lo``..``hi`` (metres)."""
    faces = []
    for axis in range(3):
        u, w = [a for a in range(3) if a != axis]
        gu = np.arange(lo[u], hi[u] + 1e-9, step)
        gw = np.arange(lo[w], hi[w] + 1e-9, step)
        a, b = np.meshgrid(gu, gw)
        for level in (lo[axis], hi[axis]):
            face = np.zeros((a.size, 3))
            face[:, axis], face[:, u], face[:, w] = level, a.ravel(), b.ravel()
            faces.append(face)
    return np.vstack(faces)


def _room() -> np.ndarray:
    """Return a 6 x 4 m room seen from its centre, two boxes a half turn maps onto each other."""
    return np.vstack([_box((-3.0, -2.0, -1.2), (3.0, 2.0, 1.3)),
                      _box((1.5, 0.5, -1.2), (2.5, 1.5, -0.4)),
                      _box((-2.5, -1.5, -1.2), (-1.5, -0.5, -0.4))])


def _corner() -> np.ndarray:
    """Return the corner of a room (floor and two walls) with a box, seen from inside."""
    points = _box((-2.0, -2.0, -1.2), (2.0, 2.0, 1.3))
    keep = (points[:, 0] > 2.0 - 1e-9) | (points[:, 1] > 2.0 - 1e-9) \
        | (points[:, 2] < -1.2 + 1e-9)
    return np.vstack([points[keep], _box((0.5, 0.8, -1.2), (1.2, 1.6, -0.5))])


def _estimate(points: np.ndarray, cfg: PipelineConfig):
    """Return the room's features and the right estimate (identity) as the gates leave it."""
    fs = cached_features(points, VOXEL, cfg.frontend, 'source')
    ft = cached_features(points + 0.0, VOXEL, cfg.frontend, 'target')
    distance = cfg.refine.max_correspondence_distance_factor * VOXEL
    align = evaluate_alignment(fs.points, ft.tree, np.eye(4), distance)
    result = PipelineResult(voxel_size=VOXEL, transform=np.eye(4), fitness=align.fitness,
                            overlap=align.fitness, inlier_threshold=3 * VOXEL)
    result.candidates = [Candidate(np.eye(4), 50, align.fitness)]
    idx = np.arange(0, len(fs.points), 97)
    corr = Correspondences(idx, idx, np.zeros(len(idx)))
    return fs, ft, corr, result


def test_a_symmetric_room_turned_half_way_is_a_plausible_twin():
    cfg = PipelineConfig(voxel_size=VOXEL)
    fs, ft, corr, result = _estimate(_room(), cfg)
    twin = find_twin(fs, ft, corr, result, cfg)
    assert twin is not None
    assert rotation_error_deg(twin.transform, np.eye(4)) > 170  # the half turn about up
    add_twin(result, twin)
    assert result.candidates[1] is twin and twin.ratio == twin.num_inliers / 50


def test_an_asymmetric_corner_has_no_twin():
    """Turned or slid, a corner with a box overlaps far less: nothing to confuse it with."""
    cfg = PipelineConfig(voxel_size=VOXEL)
    fs, ft, corr, result = _estimate(_corner(), cfg)
    assert find_twin(fs, ft, corr, result, cfg) is None


def test_a_wrong_pose_with_a_twin_is_refused_and_a_right_pose_kept(benchmark_pair,
                                                                   redkitchen_pair):
    """Two real 3DMatch pairs: a wrong pose the gates alone pass is ambiguous, a right one kept."""
    from cgags_ros.pipeline import register_clouds

    src, tgt, gt = benchmark_pair('sun3d-mit_lab_hj-lab_hj_tea_nov_2_2012_scan1_erika', 19, 21)
    result = register_clouds(src, tgt, voxel_size=0.05)
    assert translation_error(result.transform, gt) > 0.3  # the estimate is wrong ...
    assert result.ambiguous and not result.valid  # ... and no longer called valid
    assert result.refusal.code.value == 'ambiguous'
    twin = result.candidates[1].transform  # another pose that fits about as well
    assert translation_error(twin, result.transform) > fitted.TWIN_APART * 0.05
    off = register_clouds(src, tgt, voxel_size=0.05,
                          config=PipelineConfig(gates=GatesConfig(
                              check_twins=False, min_confidence=0.0,
                              max_position_sigma=0.0)))
    assert off.valid  # the gates alone would have let the slid pose through
    src, tgt, gt = redkitchen_pair(0, 2)
    kept = register_clouds(src, tgt, voxel_size=0.05)
    assert kept.valid and translation_error(kept.transform, gt) < 0.3


def test_the_verdict_on_measured_twins_is_the_pipelines():
    """
    Each start settled and judged by validity's tests refuses as find_twin does.

    A study judging recorded twins (their start's fit, where they settle, their fitness and
    violation) calls these tests, so it judges them as the pipeline does.
    """
    cfg = PipelineConfig(voxel_size=VOXEL)
    distance = cfg.refine.max_correspondence_distance_factor * VOXEL
    verdicts = []
    for points in (_room(), _corner()):
        fs, ft, corr, result = _estimate(points, cfg)
        starts = twins.twin_starts(fs, ft, np.eye(4), distance, VOXEL)
        assert [name for name, _ in starts] == [
            'flip0', 'flip1', 'flip2', 'slide1', 'slide-1',
            'turn0+', 'turn0-', 'turn1+', 'turn1-', 'turn2+', 'turn2-']
        refused = False
        for _, start in starts:
            first = evaluate_alignment(fs.points[::TWIN.stride], ft.tree, start, distance)
            if not twins.worth_refining(first.fitness, result.fitness):
                continue
            R = settle(Pair(fs, ft, cfg), start, result.inlier_threshold, TWIN).transform
            refused |= (validity.settled_apart(rotation_error_deg(R, np.eye(4)),
                                               translation_error(R, np.eye(4)), VOXEL,
                                               MIN_ROTATION_DEG)
                        and validity.fits_as_well(
                            evaluate_alignment(fs.points, ft.tree, R, distance).fitness,
                            result.fitness)
                        and validity.clear_of_free_space(measured_free_space(fs, ft, R, cfg)))
        assert refused == (find_twin(fs, ft, corr, result, cfg) is not None)
        verdicts.append(refused)
    assert verdicts == [True, False]


def test_the_screen_at_its_limit():
    """The shipped screen by default, a study's by argument."""
    assert twins.worth_refining(fitted.TWIN_PROMISING, 1.0)
    assert not twins.worth_refining(0.2, 1.0, promising=0.25)


def test_the_twins_judged_side_by_side_are_those_judged_in_turn():
    """The starts are judged on several threads; the first plausible one is still the twin."""
    cfg = PipelineConfig(voxel_size=VOXEL)
    for points in (_room(), _corner()):
        fs, ft, corr, result = _estimate(points, cfg)
        alone = find_twin(fs, ft, corr, result, cfg, workers=1)
        side_by_side = find_twin(fs, ft, corr, result, cfg, workers=3)
        assert (alone is None) == (side_by_side is None)
        if alone is not None:
            np.testing.assert_array_equal(alone.transform, side_by_side.transform)
            assert alone.num_inliers == side_by_side.num_inliers


def _square_room_pair(source: tuple, target: tuple):
    """Return two depth scans of a near-square room (sensor frames) and the truth."""
    from bench.datasets import square_room

    room, furniture = square_room.square_room(clutter=2, seed=0)
    return square_room.pair(room, furniture, square_room.sensor_pose(*source, pitch_deg=15),
                            square_room.sensor_pose(*target, pitch_deg=15))


def test_a_quarter_turn_in_a_square_room_is_refused():
    """
    A room that looks alike turned a quarter of the way: the half turns do not catch it.

    The core settles on the truth turned 90 degrees about the vertical, with more inliers
    than the truth; without its twins checked that pose is valid. The correspondences'
    other candidate, settled as a twin, is the truth and fits better: ambiguous.
    """
    from cgags_ros.pipeline import register_clouds

    src, tgt, gt = _square_room_pair((0.28, -0.28, 246.8), (1.19, 1.15, 264.9))
    off = register_clouds(src, tgt, config=PipelineConfig(
        voxel_size=0.05, gates=GatesConfig(check_twins=False, min_confidence=0.0,
                                           max_position_sigma=0.0)))
    assert off.valid and abs(rotation_error_deg(off.transform, gt) - 90) < 5
    result = register_clouds(src, tgt, voxel_size=0.05)
    assert not result.valid and result.refusal.code.value == 'ambiguous'
    twin = result.candidates[1].transform
    assert rotation_error_deg(twin, gt) < 2 and translation_error(twin, gt) < 0.05


def test_a_right_pose_in_a_square_room_stays_valid():
    """The quarter turns of a right pose in the same room settle nowhere plausible."""
    from cgags_ros.pipeline import register_clouds

    src, tgt, gt = _square_room_pair((0.86, -1.12, 310.7), (0.55, -0.78, 315.7))
    result = register_clouds(src, tgt, voxel_size=0.05)
    assert result.valid
    assert rotation_error_deg(result.transform, gt) < 2
    assert translation_error(result.transform, gt) < 0.05


def test_the_directions_a_room_faces_are_found_where_two_walls_look_alike():
    """
    A room's floor and walls give its facing axes, turned with it, whichever two look alike.

    Two walls with as many points make two principal axes of the normals' scatter equal, and
    their eigenvectors any mix of the two: the axes found are the room's, within a degree.
    """
    rng = np.random.default_rng(0)
    normals = np.vstack([np.tile(axis, (n, 1)) for axis, n in
                         (([0, 0, 1], 3000), ([1, 0, 0], 2000), ([0, 1, 0], 2000))])
    normals = normals + rng.normal(0, 0.05, normals.shape)  # a real surface's noise
    R = Rotation.from_euler('zyx', [30, 10, -20], degrees=True).as_matrix()
    axes = twins.facing_axes(normals @ R.T)
    assert np.allclose(np.abs(axes @ axes.T), np.eye(3), atol=1e-9)  # orthonormal
    found = np.abs(axes @ R)  # each row: one room axis (either sign)
    assert np.all(np.degrees(np.arccos(np.clip(found.max(axis=1), -1, 1))) < 1.0)
    assert found[0].argmax() == 2  # the floor, faced by the most surface, first
