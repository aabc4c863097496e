"""
Tests of cgags-replay on the bundled bags.

They cover offline and live replay (through register_node), the output files, broken
messages and the CLI's errors. Bags: ../shared/data/bags (see conftest).
"""

from __future__ import annotations

import csv
import json
import os
from pathlib import Path
import subprocess
import sys

from cgags_ros.io.bag import read_messages
from cgags_ros.io.pointcloud2 import pose_to_transform
from cgags_ros.tools import replay, replay_common
from cgags_ros.tools.demo import DEMO_BAGS, demo_options
from cgags_ros.tools.replay import run
from cgags_ros.tools.replay_common import auto_voxel_size, LiveOptions, ReplayOptions
import numpy as np
import pytest

pytestmark = [pytest.mark.ros, pytest.mark.subprocess, pytest.mark.slow]
BAGS = sorted(DEMO_BAGS)  # bunny, lidar, redkitchen with their RE/TE thresholds
TARGET_FRAMES = {'bunny': 'turntable', 'redkitchen': 'map', 'lidar': 'map'}
ROS_ENV = {'ROS_DOMAIN_ID': '83', 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'}


@pytest.fixture(scope='module')
def bags(data_dir: Path) -> Path:
    path = data_dir / 'bags'
    if not (path / 'bunny').is_dir():
        pytest.fail(f'bundled bags not found at {path}')
    return path


@pytest.fixture(scope='module')
def out(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp('replay')


@pytest.fixture(scope='module')
def ros_env():
    """Own DDS domain, localhost only, for this module's live replays (and their nodes)."""
    saved = {k: os.environ.get(k) for k in ROS_ENV}
    os.environ.update(ROS_ENV)
    yield
    for key, value in saved.items():
        if value is None:
            os.environ.pop(key, None)
        else:
            os.environ[key] = value


@pytest.fixture(scope='module')
def offline_reports(bags, out):
    return {bag: run(demo_options(bag, out / 'offline', quiet=True)) for bag in BAGS}


@pytest.fixture(scope='module')
def live_reports(bags, out, ros_env):
    return {bag: run(demo_options(bag, out / 'live', quiet=True), LiveOptions()) for bag in BAGS}


def _check_accuracy(report, bag):
    max_re, max_te = DEMO_BAGS[bag]
    assert report.rows, f'{bag}: no pairs'
    assert report.recall == 1.0, [(r.index, r.reason, r.re_deg, r.te_m) for r in report.rows]
    for row in report.rows:
        assert row.valid and row.re_deg < max_re and row.te_m < max_te, row


@pytest.mark.parametrize('bag', BAGS)
def test_offline_replay_meets_ground_truth(offline_reports, bag):
    report = offline_reports[bag]
    _check_accuracy(report, bag)
    assert not report.broken
    assert all(r.time_s > 0 and r.inliers > 0 for r in report.rows)


@pytest.mark.parametrize('bag', BAGS)
def test_live_replay_meets_ground_truth(live_reports, offline_reports, bag):
    report = live_reports[bag]
    _check_accuracy(report, bag)
    assert report.mode == 'live'
    # Same pairs as offline (the node and the offline replay share the pairing code).
    assert [r.source_stamp_ns for r in report.rows] == \
        [r.source_stamp_ns for r in offline_reports[bag].rows]
    assert all(r.latency_s is not None and r.latency_s > 0 for r in report.rows)
    assert all(r.time_s > 0 and r.inliers > 0 for r in report.rows)  # from the node's ~/result


@pytest.mark.parametrize('mode', ['offline', 'live'])
def test_output_files(offline_reports, live_reports, out, mode):
    reports = offline_reports if mode == 'offline' else live_reports
    for bag in BAGS:
        report, folder = reports[bag], out / mode / bag
        valid = [row for row in report.rows if row.valid]  # only valid estimates are written
        assert valid, f'{bag}: no valid estimate'
        records = list(read_messages(folder / 'poses'))
        assert [r.topic for r in records] == [replay_common.DEFAULT_POSE_TOPIC] * len(valid)
        assert {r.msgtype for r in records} == {'geometry_msgs/msg/PoseStamped'}
        assert [r.stamp_ns for r in records] == [row.source_stamp_ns for row in valid]
        assert {r.frame_id for r in records} == {TARGET_FRAMES[bag]}
        for rec, row in zip(records, valid):
            assert rec.log_time_ns == row.source_stamp_ns
            np.testing.assert_allclose(pose_to_transform(rec.msg), row.transform, atol=1e-6)
        with open(folder / 'results.csv', newline='') as f:
            rows = list(csv.DictReader(f))
        assert [int(r['source_stamp_ns']) for r in rows] == \
            [row.source_stamp_ns for row in report.rows]
        assert [r['success'] for r in rows] == [str(int(row.success)) for row in report.rows]
        assert all(float(r['re_deg']) >= 0 for r in rows if r['re_deg'])
        results = json.loads((folder / 'results.json').read_text())
        summary = results['summary']
        assert summary['recall'] == report.recall and summary['pairs'] == len(report.rows)
        for pair, row in zip(results['pairs'], report.rows):
            if row.valid:  # the estimate's covariance (offline: the result's; live: the node's)
                cov = np.asarray(pair['covariance'])
                assert cov.shape == (6, 6) and np.allclose(cov, cov.T), bag
                assert np.all(np.diag(cov) > 0), bag
        assert (folder / 'errors.png').stat().st_size > 1000


def test_ground_truth_matched_by_stamp(bags):
    contents = replay_common.read_bag_contents(bags / 'lidar', '/source_cloud', '/target_cloud',
                                               '/ground_truth')
    stamps = [c.stamp_ns for c in contents.sources]
    assert sorted(contents.ground_truth) == stamps


def test_auto_voxel_size_follows_scene_scale(offline_reports):
    voxels = {bag: offline_reports[bag].voxel_size for bag in BAGS}
    assert 0.001 <= voxels['bunny'] <= 0.005
    assert 0.03 <= voxels['redkitchen'] <= 0.08
    assert 0.2 <= voxels['lidar'] <= 0.6
    with pytest.raises(replay_common.ReplayError):
        auto_voxel_size(np.zeros((10, 3)))


def test_faulty_bag_counts_broken_messages(bags, out, capsys):
    opts = ReplayOptions(bag=bags / 'faulty', output=out / 'faulty', max_te=0.01)
    report = run(opts)
    assert len(report.broken) == 4  # empty, all-NaN, no z field, truncated data
    assert all(b.topic == '/source_cloud' for b in report.broken)
    assert report.recall == 1.0 and len(report.evaluated) == 1  # the one good pair with GT
    text = capsys.readouterr().out
    assert 'broken messages 4' in text and 'truncated' in text
    # the refused pairs say why with a code, in the report and in both result files
    assert [_code(r.refusal) for r in report.rows] == FAULTY_CODES
    with open(out / 'faulty' / 'results.csv', newline='') as f:
        assert [r['refusal'] or None for r in csv.DictReader(f)] == FAULTY_CODES
    pairs = json.loads((out / 'faulty' / 'results.json').read_text())['pairs']
    assert [p['refusal'] and p['refusal']['code'] for p in pairs] == FAULTY_CODES
    assert all(p['refusal']['message'] == p['reason'] for p in pairs if p['refusal'])


def test_faulty_bag_live(bags, out, ros_env):
    opts = ReplayOptions(bag=bags / 'faulty', output=out / 'faulty_live', max_te=0.01,
                         quiet=True)
    report = run(opts, LiveOptions(timeout=30.0))
    assert len(report.broken) == 4
    assert report.recall == 1.0
    assert not any('stopped waiting' in n for n in report.notes)  # the node accounted for all
    assert any('rejected.bad_input' in n for n in report.notes)
    # the node's code for each refused pair (no_pose: no diagnostics sample caught that pair)
    for row, code in zip(report.rows, FAULTY_CODES, strict=True):
        assert _code(row.refusal) in ({code, 'no_pose'} if code else {None}), row


FAULTY_CODES = ['too_few_points', None, 'collinear', None]  # a single point, a line


def _code(refusal):
    return None if refusal is None else refusal.code.value


def _main_error(capsys, *argv) -> str:
    code = replay.main([str(a) for a in argv])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1 and err[0].startswith('cgags-replay: error: '), err
    return err[0]


def test_cli_errors(bags, tmp_path, capsys):
    assert "'/nope' is not in" in _main_error(capsys, bags / 'bunny', '--source-topic', '/nope',
                                              '--output', tmp_path)
    assert '/ground_truth' in _main_error(capsys, bags / 'bunny', '--ground-truth-topic', '/gt',
                                          '--output', tmp_path)
    garbage = tmp_path / 'broken.mcap'
    garbage.write_bytes(b'\x00not an mcap file')
    assert 'cannot read bag' in _main_error(capsys, garbage)
    corrupt = tmp_path / 'corrupt_bag'
    corrupt.mkdir()
    (corrupt / 'metadata.yaml').write_text('rosbag2_bagfile_information: [')
    assert 'cannot read bag' in _main_error(capsys, corrupt)
    assert 'not a rosbag2 bag' in _main_error(capsys, bags.parent / 'README.md')
    assert 'without metadata.yaml' in _main_error(capsys, tmp_path)
    assert 'does not exist' in _main_error(capsys, tmp_path / 'missing')
    assert "unknown configuration key 'no_such_key'" in _main_error(
        capsys, bags / 'bunny', '--set', 'no_such_key=1')


def test_cli_exit_code_and_single_line(bags, tmp_path):
    proc = subprocess.run([sys.executable, '-m', 'cgags_ros.tools.replay', str(bags / 'bunny'),
                           '--target-topic', '/nope', '--output', str(tmp_path)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert proc.stderr.strip().count('\n') == 0 and 'Traceback' not in proc.stderr
    assert "topic '/nope' is not in" in proc.stderr
