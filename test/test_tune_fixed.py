"""
cgags-tune's fixed settings (``--config``, ``--set``): every trial runs with them, none searched.

The outcome: the bundled redkitchen bag moved out of its camera's frame (as
test_sensor_frame moves it), its two pairs that no searched setting recovers (right poses
refused at the frame's origin, ``centroid`` or not); with the sensors' positions fixed, the
tuner gets both, and the ``params.yaml`` it writes gives them to ``cgags-replay --config``.
"""

from __future__ import annotations

import json
from pathlib import Path

from cgags_ros.config.node import configs_from_file, ros_parameter_descriptions
from cgags_ros.config.pipeline import load_yaml
from cgags_ros.errors import InvalidConfigError
from cgags_ros.tools import tune, tune_fixed, tune_search, tune_study, tuning
from cgags_ros.tools.replay import build_parser as replay_parser
from cgags_ros.tools.replay import options_from_args, run
import numpy as np
import pytest

ORIENTATION = 'frontend.normal_orientation'
SENSORS = ('frontend.source_sensor', 'frontend.target_sensor')


def test_a_fixed_setting_is_never_opened_whatever_the_refusals():
    assert tuning.search_space(['free_space', 'tilt'], fixed=[ORIENTATION]) == {
        'core.motion_model': ('6dof', '4dof')}
    from test_tune_search import _only_the_second_stage_succeeds, _replayed, _setup, Fake

    trials = Fake(_only_the_second_stage_succeeds)
    setup = _setup(trials)
    setup.fixed = {ORIENTATION: 'origin'}
    opts = tune.Options(bags=[], trials=4)
    tune_study._start(setup, opts, start=0.004, automatic=0.002)
    tune_search.run_trials(setup, opts)
    # The automatic voxel's free-space refusals would open the orientation (test_tune_search).
    assert setup.study.trials[1].user_attrs['refusals'] == {'free_space': 3}
    assert not setup.study.user_attrs['stages'] and tune_search.stored_space(setup.study) == {}
    assert all(ORIENTATION not in s for s in _replayed(trials))


def test_a_fixed_voxel_leaves_the_voxel_out_of_every_trial():
    from test_tune_search import _replayed, _setup, Fake

    class FixedVoxel(Fake):
        def defaults(self):
            return {}  # as OfflineTrials' with voxel_size fixed: nothing of it searched

        def score(self, settings, splits):
            self.calls.append((dict(settings), tuple(splits)))
            right, wrong, refusals = self.rule(settings, 'tuned on')
            return {'tuned on': tuning.Score(self.pairs, right, wrong, 0.1, refusals)}

    def rule(settings, _split):
        return (4, 0, {}) if settings.get(ORIENTATION) == 'centroid' else (1, 0, {'free_space': 3})

    trials = FixedVoxel(rule)
    setup = _setup(trials, grid=[])
    opts = tune.Options(bags=[], trials=5)
    tune_study._start(setup, opts, start=None, automatic=None)
    tune_search.run_trials(setup, opts)  # the start opens the orientation; then all is tried
    assert _replayed(trials) == [{}, {ORIENTATION: 'centroid'}]
    assert all('voxel_size' not in t.params for t in setup.study.trials)
    assert setup.study.best_trial.params == {ORIENTATION: 'centroid'}


def test_a_rerun_with_other_fixed_settings_starts_its_own_study(tmp_path):
    bag = tmp_path / 'bag'
    plain = tune.Options(bags=[bag], output=tmp_path / 'a')
    assert tune.Options(bags=[bag], output=tmp_path / 'a', fixed={}).study_name == \
        plain.study_name
    names = {tune.Options(bags=[bag], output=tmp_path / 'a', fixed=fixed).study_name
             for fixed in ({'frontend.source_sensor': [1, 2, 3]},
                           {'frontend.source_sensor': [1, 2, 4]},
                           {'frontend.source_sensor': [1, 2, 3], ORIENTATION: 'centroid'})}
    assert len(names) == 3 and plain.study_name not in names


def test_params_yaml_carries_the_fixed_settings_as_the_node_and_cgags_replay_read_them(
        tmp_path):
    fixed = {SENSORS[0]: [8.0, -6.0, 5.0], SENSORS[1]: [1.0, 2.0, 3.0],
             ORIENTATION: 'centroid', 'frontend.max_correspondences': 4000}
    paths = tune_fixed.write_params(tmp_path, {'voxel_size': 0.05}, fixed, 'tuned')
    ros = load_yaml(paths['params'])
    # The node refuses a params file key that is no ROS parameter: each of these is one.
    assert set(ros) <= set(ros_parameter_descriptions())
    assert ros[ORIENTATION] == 'centroid' and ros['voxel_size'] == 0.05
    assert not set(SENSORS) & set(ros)
    # The rest reach the node through the config_file it names (as the node reads it).
    pipe, _ = configs_from_file(ros['config_file'])
    assert pipe.frontend.source_sensor == (8.0, -6.0, 5.0)
    assert pipe.frontend.target_sensor == (1.0, 2.0, 3.0)
    assert pipe.frontend.max_correspondences == 4000
    # cgags-replay --config params.yaml reads both files, as the node does.
    opts, _ = options_from_args(replay_parser().parse_args(['bag', '--config',
                                                            str(paths['params'])]))
    assert opts.parameters == {'voxel_size': 0.05, **fixed}
    # Nothing but ROS parameters fixed: no config.yaml, no config_file.
    (tmp_path / 'b').mkdir()
    only = tune_fixed.write_params(tmp_path / 'b', {'voxel_size': 0.05}, {ORIENTATION: 'origin'},
                                   '')
    assert set(only) == {'params'} and 'config_file' not in load_yaml(only['params'])


def test_fixed_settings_no_trial_could_run_with_fail_before_any_trial(
        tmp_path, capsys, monkeypatch, data_dir):
    def no_trial(*args, **kwargs):
        raise AssertionError('a trial ran')

    monkeypatch.setattr(tuning, 'replay', no_trial)
    monkeypatch.setattr(tuning, 'load_bags', no_trial)
    bunny = data_dir / 'bags' / 'bunny'
    out = tmp_path / 'out'
    unknown = tmp_path / 'unknown.yaml'
    unknown.write_text('frontend:\n  source_sensors: [0, 0, 1]\n')
    cases = [(['--config', unknown], "unknown configuration key 'frontend.source_sensors'"),
             (['--config', tmp_path / 'missing.yaml'], 'cannot read config file'),
             (['--set', 'frontend.source_sensor=[0, 1]'], 'frontend.source_sensor must be'),
             (['--set', 'voxel_size=-1'], 'voxel_size'),
             (['--set', 'map.file=map.ply'], 'not a map'),
             (['--set', 'mode=calibrate'], 'calibrate'),
             (['--set', 'voxel_size=0.01', '--voxel-size', '0.02'], 'give one of them')]
    for argv, message in cases:
        code = tune.main([str(a) for a in [bunny, '--output', out, *argv]])
        err = capsys.readouterr().err.strip()
        assert code == 2 and err.startswith('cgags-tune: error: ') and message in err, err
        assert '\n' not in err
    assert not out.exists()
    with pytest.raises(InvalidConfigError, match='config_file'):
        tune_fixed.check({'config_file': 'x.yaml'}, live=False, voxel_size=None)
    # Tuning a running node, only what it takes at run time: no sensor, nothing read-only.
    for key, value in (('frontend.source_sensor', [0, 0, 1]), ('pairing.mode', 'synchronized')):
        with pytest.raises(InvalidConfigError, match=f'{key} cannot be'):
            tune.Options(bags=[bunny], live=True, fixed={key: value}).check()
    tune.Options(bags=[bunny], live=True, fixed={ORIENTATION: 'centroid'}).check()


@pytest.mark.slow
def test_fixed_settings_reach_every_trial_and_params_yaml_and_are_never_searched(
        data_dir, tmp_path, monkeypatch):
    """The moved turntable bag: its free-space refusals would open the orientation."""
    from test_tune import moved_bunny_bag

    bag = moved_bunny_bag(data_dir, tmp_path / 'moved_bunny')
    config = tmp_path / 'fixed.yaml'
    config.write_text(f'frontend:\n  {ORIENTATION.split(".")[1]}: centroid\n')
    fixed = {ORIENTATION: 'origin', 'frontend.max_correspondences': 4000}
    replayed, refusals = [], {}
    real_replay = tuning.replay

    def recorded(pairs, settings, criteria):
        replayed.append(dict(settings))
        score, rows = real_replay(pairs, settings, criteria)
        refusals.update(score.refusals)
        return score, rows

    monkeypatch.setattr(tuning, 'replay', recorded)
    code = tune.main([str(bag), '--config', str(config), '--set', f'{ORIENTATION}=origin',
                      '--set', 'frontend.max_correspondences=4000', '--trials', '2',
                      '--holdout', '0', '--output', str(tmp_path / 'out'), '--quiet'])
    assert code == 0
    summary = json.loads((tmp_path / 'out' / 'summary.json').read_text())
    assert summary['fixed'] == fixed  # --set over --config
    assert len(replayed) >= 3  # two trials and the defaults
    assert all(s[k] == v for s in replayed for k, v in fixed.items())
    trial_keys = {k for t in summary['trials'] for k in t}
    assert not trial_keys & set(fixed) and not summary['stages']
    assert refusals.get('free_space')  # what would have opened the orientation
    assert 'fixed by the user' in (tmp_path / 'out' / 'report.md').read_text()
    params = load_yaml(tmp_path / 'out' / 'params.yaml')
    assert params[ORIENTATION] == 'origin'
    pipe, _ = configs_from_file(params['config_file'])
    assert pipe.frontend.max_correspondences == 4000


def moved_kitchen_bag(data_dir: Path, path: Path) -> Path:
    """Write the two redkitchen pairs test_sensor_frame's motion leaves to the sensors alone."""
    from cgags_ros.geometry import apply_transform
    from cgags_ros.io.bag import read_messages, write_bag
    from cgags_ros.io.pointcloud2 import pointcloud2_to_xyz, pose_to_transform
    from test_sensor_frame import MOTION

    clouds: dict[str, list] = {'/source_cloud': [], '/target_cloud': [], '/ground_truth': []}
    for rec in read_messages(data_dir / 'bags' / 'redkitchen', list(clouds)):
        if rec.topic == '/ground_truth':
            value = MOTION @ pose_to_transform(rec.msg) @ np.linalg.inv(MOTION)
        else:
            value = apply_transform(MOTION, pointcloud2_to_xyz(rec.msg))
        clouds[rec.topic].append((rec.stamp_ns, value))
    messages = []
    for k in (2, 3):  # refused at the origin with centroid too (docs/tuning.md: 2 of 4)
        stamp = clouds['/source_cloud'][k][0]
        messages += [('/target_cloud', stamp - 1, 'moved', clouds['/target_cloud'][k][1]),
                     ('/source_cloud', stamp, 'moved', clouds['/source_cloud'][k][1]),
                     ('/ground_truth', stamp, 'moved', clouds['/ground_truth'][k][1])]
    write_bag(path, messages)
    return path


@pytest.mark.slow
def test_with_the_sensors_positions_fixed_the_tuner_recovers_what_it_cannot_without(
        data_dir, tmp_path):
    from test_sensor_frame import SENSOR

    bag = moved_kitchen_bag(data_dir, tmp_path / 'kitchen_moved')
    # Limits in the moved frame: the rotation error (1.5 degrees) times the camera's 11 m
    # lever arm adds to the translation error; a wrong pose here is 175 degrees off.
    limits = {'max_re_deg': 5.0, 'max_te': 0.5}

    def tuned(name, fixed):
        return tune.tune(tune.Options(bags=[bag], trials=2, voxel_size=0.05, quiet=True,
                                      output=tmp_path / name, fixed=fixed, **limits))

    blind = tuned('blind', {})
    assert blind.scores['best', 'tuned on'].right == 0
    fixed = {SENSORS[0]: SENSOR, SENSORS[1]: SENSOR}
    sighted = tuned('sighted', fixed)
    best = sighted.scores['best', 'tuned on']
    assert (best.right, best.wrong, best.pairs) == (2, 0, 2)
    assert sighted.fixed == fixed and not set(sighted.best) & set(fixed)
    args = replay_parser().parse_args([str(bag), '--config', str(sighted.paths['params']),
                                       '--output', str(tmp_path / 'replay'), '--quiet',
                                       '--max-re-deg', '5', '--max-te', '0.5'])
    report = run(*options_from_args(args))
    assert [bool(r.success) for r in report.rows] == [True, True]
