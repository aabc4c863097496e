"""
``cgags-tune --live``: a running register_node tuned through its own parameter services.

The node runs in its own process, as a user starts it (its defaults but a reliable source
subscription, ``pairing.source_qos:=reliable``, as docs/tuning.md advises while tuning;
the shipped Fast DDS profile on both sides, as ``LiveSession`` and the node each load it);
the tuner sets its parameters over DDS, replays the turntable bag through it in lockstep
and reads its ``~/result``. Clouds of ~0.6 MB: on the default best-effort subscription one
of four was lost once in a full suite's run.
"""

from __future__ import annotations

import os
from pathlib import Path
import subprocess
import sys

import pytest

rclpy = pytest.importorskip('rclpy')

from cgags_ros.tools import tune, tuning  # noqa: E402, I100

pytestmark = [pytest.mark.ros, pytest.mark.slow]
DOMAIN_ID = 41  # distinct from the other DDS test modules
REPO = Path(__file__).resolve().parents[1]
PROFILE = REPO / 'config' / 'fastdds_large_data.xml'


@pytest.fixture
def node(monkeypatch, tmp_path):
    """Start a node on its defaults, sources reliable, in its own process and domain."""
    env = {'ROS_DOMAIN_ID': str(DOMAIN_ID), 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST',
           'FASTRTPS_DEFAULT_PROFILES_FILE': str(PROFILE)}
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    log = open(tmp_path / 'node.log', 'w+', encoding='utf-8')
    proc = subprocess.Popen([sys.executable, '-m', 'cgags_ros.register_node', '--ros-args',
                             '-p', 'pairing.source_qos:=reliable'], cwd=REPO,
                            env=dict(os.environ, PYTHONPATH=str(REPO), PYTHONUNBUFFERED='1'),
                            stdout=log, stderr=subprocess.STDOUT)
    yield proc
    proc.send_signal(2)
    try:
        proc.wait(timeout=20)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
    log.close()


def _options(data_dir: Path, tmp_path: Path, **extra) -> tune.Options:
    return tune.Options(bags=[data_dir / 'bags' / 'bunny'], live=True, quiet=True,
                        output=tmp_path / 'out', storage=f"sqlite:///{tmp_path / 'study.db'}",
                        max_re_deg=5.0, max_te=0.01, timeout=120.0, **extra)


def test_live_trials_change_the_node_and_leave_it_on_the_best(node, data_dir, tmp_path,
                                                              monkeypatch):
    from cgags_ros.tools import replay_common
    from cgags_ros.tools.tune_live import LiveTrials

    opts = _options(data_dir, tmp_path, voxel_size=0.024, trials=3)
    pairs, contents = tuning.load_bags(opts.bags, opts.source_topic, opts.target_topic, None)
    criteria = tuning.criteria_for(0.0024, 5.0, 0.01)
    trials = LiveTrials(opts, {'tuned on': pairs, 'held out': []}, criteria, contents)
    try:
        assert trials.defaults()['voxel_size'] == pytest.approx(0.05)  # the node's default
        coarse = trials.score({'voxel_size': 0.024}, ('tuned on',))['tuned on']
        assert [r['voxel_size'] for r in trials.session.results] == [pytest.approx(0.024)] * 4
        fine = trials.score({'voxel_size': 0.0024}, ('tuned on',))['tuned on']
        # The node's ~/result shows the change, and so does the score.
        assert [r['voxel_size'] for r in trials.session.results] == [pytest.approx(0.0024)] * 4
        assert coarse.right < 4 and (fine.right, fine.wrong) == (4, 0)
        with pytest.raises(tuning.SettingRefused, match='voxel_size'):  # out of the node's range
            trials.score({'voxel_size': -1.0}, ('tuned on',))
    finally:
        trials.close()

    opened = []

    class CountingReader(replay_common.BagReader):
        def __init__(self, path, *args, **kwargs):
            opened.append(str(path))
            super().__init__(path, *args, **kwargs)

    monkeypatch.setattr(replay_common, 'BagReader', CountingReader)
    outcome = tune.tune(opts)  # the whole study, through the node
    assert opened == [str(opts.bags[0])]  # each bag read once a run, live too
    assert [t['voxel_size'] for t in outcome.trials[:2]] == pytest.approx([0.024, 0.0024])
    best = outcome.scores['best', 'tuned on']
    assert (best.right, best.wrong) == (4, 0)
    assert outcome.defaults['voxel_size'] == pytest.approx(0.0024)  # left there by the test
    assert 'register_node:' in outcome.paths['params'].read_text()
    check = LiveTrials(opts, {'tuned on': pairs, 'held out': []}, criteria, contents)
    try:
        assert check.defaults()['voxel_size'] == pytest.approx(outcome.written['voxel_size'])
    finally:
        check.close()
