"""
The temporal prior (cgags_ros/tracking/tracker.py) on real KITTI scans, ROS-free.

Scan-to-map against scan 0 as the map; ``pseudo_gt.txt`` holds each scan's pose in scan
0's frame, i.e. the source->target transform of scan k onto scan 0.
"""

from cgags_ros.config import PipelineConfig, TrackingConfig
from cgags_ros.geometry import apply_transform, rotation_error_deg, translation_error
from cgags_ros.pipeline import PipelineResult
from cgags_ros.refusal import Refusal, RefusalCode as Code
from cgags_ros.tracking import Tracker
import numpy as np
from scipy.spatial.transform import Rotation

VOXEL = 0.5
PERIOD = 0.1  # seconds between scans: a 10 Hz LiDAR


def _config(**tracking) -> PipelineConfig:
    return PipelineConfig(voxel_size=VOXEL, tracking=TrackingConfig(**tracking))


def _within(result: PipelineResult, truth: np.ndarray, degrees: float = 1.0,
            metres: float = 0.2) -> bool:
    return (rotation_error_deg(result.transform, truth) <= degrees
            and translation_error(result.transform, truth) <= metres)


def _run(tracker, scans, indices, target, config, start=0):
    return [tracker.register(scans[k], target, (start + i) * PERIOD, config=config)
            for i, k in enumerate(indices)]


def test_smooth_sequence_is_tracked_within_pseudo_ground_truth(kitti):
    scans, truth = kitti
    tracker = Tracker()
    indices = [0, 1, 2, 3, 4, 5, 4, 3]  # forward, then back: the velocity reverses
    results = _run(tracker, scans, indices, scans[0], _config())
    assert [r.path for r in results] == ['global'] + ['tracked'] * (len(indices) - 1)
    for k, result in zip(indices, results):
        assert result.valid, result.reason
        assert _within(result, truth[k]), k
    assert results[2].stats['prediction'] == 'constant velocity'
    assert set(results[1].timings) >= {'downsample', 'refinement', 'validation'}
    assert 'fpfh' not in results[1].timings and 'matching' not in results[1].timings
    assert results[1].summary()['path'] == 'tracked'
    assert np.all(np.diag(results[1].covariance) < 1.0)
    # The covariance of a tracked pose is the global path's, and it holds the truth: every
    # tracked pose inside its 95 % ellipsoid (the point-to-point one over the overlap had a
    # few millimetres for errors of centimetres, NEES in the hundreds; docs/tracking.md).
    for k, result in zip(indices[1:], results[1:]):
        error = np.concatenate([truth[k][:3, 3] - result.transform[:3, 3], Rotation.from_matrix(
            truth[k][:3, :3] @ result.transform[:3, :3].T).as_rotvec()])
        assert error @ np.linalg.solve(result.covariance, error) <= 12.592, k
    counts = tracker.counts()
    assert (counts['tracked'], counts['global'], counts['tracking_failures']) == (7, 1, 0)


def test_odometry_gives_the_prediction(kitti):
    scans, truth = kitti
    tracker = Tracker()
    config = _config()
    tracker.register(scans[2], scans[0], 0.0, config=config)
    odometry = np.linalg.inv(truth[2]) @ truth[4]  # scan 4 in scan 2's frame: two steps
    result = tracker.register(scans[4], scans[0], PERIOD, config=config, odometry=odometry)
    assert result.path == 'tracked' and result.stats['prediction'] == 'odometry'
    assert _within(result, truth[4])


def test_jump_falls_back_to_global(kitti):
    scans, truth = kitti
    tracker = Tracker()
    config = _config()
    _run(tracker, scans, [13, 14, 15], scans[0], config)
    result = tracker.register(scans[0], scans[0], 3 * PERIOD, config=config)  # 12 m back
    assert result.path == 'global', 'a jump must not be tracked'
    assert result.stats['tracking_failure']  # which gate caught it depends on the settings
    assert result.stats['tracking_failure_code'] in {
        Code.TRACKING_LOST.value, Code.FREE_SPACE.value, Code.DEGENERATE_AXIS.value,
        Code.LOW_FITNESS.value}
    assert result.valid and _within(result, truth[0])
    # tracking resumes from the global pose
    after = tracker.register(scans[1], scans[0], 4 * PERIOD, config=config)
    assert after.path == 'tracked' and _within(after, truth[1])
    assert tracker.counts()['tracking_failures'] == 1


def test_kidnap_falls_back_and_never_returns_the_stale_pose(kitti, monkeypatch):
    scans, truth = kitti
    tracker = Tracker()
    config = _config()
    _run(tracker, scans, [4, 5, 6], scans[0], config)
    # The robot is carried to scan 10's place and turned about: nothing near the prediction.
    turn = np.diag([-1.0, -1.0, 1.0, 1.0])
    kidnapped = apply_transform(turn, scans[10])
    result = tracker.register(kidnapped, scans[0], 3 * PERIOD, config=config)
    assert result.path == 'global' and result.stats['tracking_failure']
    assert result.valid and _within(result, truth[10] @ np.linalg.inv(turn))
    # Again, with the global search refusing too: the result is invalid, not the prediction.
    tracker = Tracker()
    _run(tracker, scans, [4, 5, 6], scans[0], config)

    def refuse(source, target, *, config=None):
        return PipelineResult().finish(0.0, Refusal(Code.NO_ESTIMATE, 'refused'))

    tracker.global_registration = refuse
    result = tracker.register(kidnapped, scans[0], 3 * PERIOD, config=config)
    assert not result.valid and result.path == 'global'
    assert result.refusal.code is Code.NO_ESTIMATE  # the global search's, not the tracker's
    assert not _within(result, truth[7], 10.0, 2.0), 'the stale pose came back'
    counts = tracker.counts()
    assert (counts['tracking_failures'], counts['invalid']) == (1, 1)
    # the prior is gone: the next scan is not tracked from the pose before the kidnap
    assert tracker.register(scans[7], scans[0], 4 * PERIOD, config=config).path == 'global'


def test_degenerate_corridor_is_not_tracked(kitti):
    scans, truth = kitti
    tracker = Tracker()
    config = _config()
    _run(tracker, scans, [3, 4, 5], scans[0], config)
    # scan 6 seen as a corridor: only the road surface and what rises from it within 1.5 m
    # of the car's axis; its lengthwise motion is unconstrained
    scan = scans[6]
    corridor = scan[(np.abs(scan[:, 1]) < 1.5) & (scan[:, 2] < -1.2)]
    result = tracker.register(corridor, scans[0], 3 * PERIOD, config=config)
    assert result.path == 'global', 'a degenerate view must not be tracked'
    assert result.stats['tracking_failure_code'] == Code.DEGENERATE_AXIS.value
    assert not result.valid or _within(result, truth[6])


def test_target_change_drops_the_prior(kitti):
    scans, truth = kitti
    tracker = Tracker()
    config = _config()
    _run(tracker, scans, [1, 2, 3], scans[0], config)
    result = tracker.register(scans[4], scans[8], 3 * PERIOD, config=config)  # a new map
    assert result.path == 'global'
    assert result.stats['global_because'] == 'no recent valid pose of this pair'
    assert result.valid and _within(result, np.linalg.inv(truth[8]) @ truth[4])
    assert tracker.counts()['target_changes'] == 1
    # the same map sent again (a re-latched copy) keeps the prior
    again = tracker.register(scans[5], scans[8].copy(), 4 * PERIOD, config=config)
    assert again.path == 'tracked' and _within(again, np.linalg.inv(truth[8]) @ truth[5])


def test_periodic_global_checks(kitti):
    scans, truth = kitti
    tracker = Tracker()
    config = _config(global_check_interval=3, global_check_period=0.0)
    indices = list(range(7))
    results = _run(tracker, scans, indices, scans[0], config)
    assert [r.path for r in results] == ['global', 'tracked', 'tracked'] * 2 + ['global']
    assert all(r.valid and _within(r, truth[k]) for k, r in zip(indices, results))
    counts = tracker.counts()
    assert (counts['periodic_checks'], counts['check_disagreements']) == (2, 0)
    assert results[3].stats['global_because'] == 'periodic check'
    # by time: with the stamps 1 s apart every scan is due, yet within max_age
    config = _config(global_check_interval=0, global_check_period=0.5, max_age=2.0)
    tracker = Tracker()
    paths = [tracker.register(scans[k], scans[0], float(k), config=config).path
             for k in range(3)]
    assert paths == ['global'] * 3


def test_stale_pose_and_disabled_tracking_go_global(kitti):
    scans, _ = kitti
    tracker = Tracker()
    config = _config(max_age=0.15)
    tracker.register(scans[1], scans[0], 0.0, config=config)
    late = tracker.register(scans[2], scans[0], 0.3, config=config)  # 0.3 s > max_age
    assert late.path == 'global' and 'tracking.max_age' in late.stats['global_because']
    tracker = Tracker()
    config = _config(enabled=False)
    paths = [r.path for r in _run(tracker, scans, [1, 2], scans[0], config)]
    assert paths == ['global', 'global']


def test_a_prepared_map_is_tracked(kitti, tmp_path):
    from cgags_ros.pipeline.map import load_map

    scans, truth = kitti
    np.save(tmp_path / 'map.npy', scans[0])
    config = _config()
    prepared = load_map(tmp_path / 'map.npy', config)
    tracker = Tracker()
    results = _run(tracker, scans, [1, 2, 3], prepared, config)
    assert [r.path for r in results] == ['global', 'tracked', 'tracked']
    assert all(r.valid and _within(r, truth[k]) for k, r in zip([1, 2, 3], results))
    # a map is recognised by its file and digest: the same points sent as a cloud are new
    assert tracker.register(scans[4], scans[0], 3 * PERIOD, config=config).path == 'global'
    assert tracker.counts()['target_changes'] == 1


def test_a_check_beside_the_stream_resets_the_motion_only_when_it_disagrees(kitti):
    """With ``defer_checks`` the due scan is tracked; the caller's verdict decides later."""
    scans, truth = kitti
    tracker, config = Tracker(), _config(global_check_interval=3, global_check_period=0.0)

    def register(k):
        return tracker.register(scans[k], scans[0], k * PERIOD, config=config,
                                defer_checks=True)

    assert [register(k).path for k in (1, 2, 3, 4)] == ['global'] + ['tracked'] * 3
    assert tracker.check_due  # scan 4's check is the caller's to run
    tracker.apply_check(4 * PERIOD, truth[4])  # a global result that agrees
    assert [register(k).path for k in (5, 6, 7)] == ['tracked'] * 3 and tracker.check_due
    counts = tracker.counts()
    assert (counts['periodic_checks'], counts['check_disagreements'], counts['global']) == (
        1, 0, 1)
    turned = truth[7] @ np.block([[Rotation.from_euler('z', 10, degrees=True).as_matrix(),
                                   np.zeros((3, 1))], [np.zeros((1, 3)), np.ones((1, 1))]])
    tracker.apply_check(7 * PERIOD, turned)  # one that disagrees: the motion is reset
    tracker.apply_check(7 * PERIOD, turned)  # a verdict is applied once
    tracker.apply_check(5 * PERIOD, turned)  # and only for a scan asked to be checked
    assert tracker.counts()['check_disagreements'] == 1
    result = register(8)
    assert result.path == 'global' and result.valid and _within(result, truth[8])


def test_a_jump_is_found_by_the_global_search_and_tracked_after(kitti):
    scans, truth = kitti
    tracker, config = Tracker(), _config()
    first = _run(tracker, scans, [1, 2, 3], scans[0], config)
    assert [r.path for r in first] == ['global', 'tracked', 'tracked']
    jump = tracker.register(scans[12], scans[0], 3 * PERIOD, config=config)  # 9 m ahead
    assert jump.path == 'global' and jump.valid and _within(jump, truth[12])
    assert jump.voxel_size == VOXEL and jump.num_inliers > 0
    assert tracker.register(scans[13], scans[0], 4 * PERIOD, config=config).path == 'tracked'


def test_a_scan_of_few_voxels_is_tracked_onto_a_map_where_the_global_path_puts_it(
        tmp_path, monkeypatch):
    """Both paths refine it once more with its own points (pipeline/polish.py): one pose."""
    from pathlib import Path

    from cgags_ros.frontend import refine
    from cgags_ros.pipeline.map import load_map
    from cgags_ros.tracking import refined

    fixture = Path(__file__).resolve().parent / 'fixtures' / 'small_gicp'
    source = np.load(fixture / 'source.npy').astype(np.float64)
    np.save(tmp_path / 'map.npy', np.load(fixture / 'target.npy').astype(np.float64))
    truth = np.loadtxt(fixture / 'T_target_source.txt')
    config = PipelineConfig(voxel_size=0.3)
    prepared = load_map(tmp_path / 'map.npy', config)
    calls = []

    def spy(*args, **kwargs):
        calls.append(args[1])
        return refine.refine_finer(*args, **kwargs)

    monkeypatch.setattr(refined, 'refine_finer', spy)
    tracker = Tracker()
    first, second = _run(tracker, [source, source], [0, 1], prepared, config)
    assert (first.path, second.path) == ('global', 'tracked') and second.valid, second.reason
    assert calls and calls[0] < refine.FINER_MAX_VOXELS
    assert _within(first, truth) and _within(second, truth)
    assert rotation_error_deg(second.transform, first.transform) < 0.01
    assert translation_error(second.transform, first.transform) < 0.01
    # A pair of clouds is not refined again, on either path.
    calls.clear()
    pair = _run(Tracker(), [source, source], [0, 1], np.load(tmp_path / 'map.npy'), config)
    assert [r.path for r in pair] == ['global', 'tracked'] and calls == []
