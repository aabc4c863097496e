"""cgags-tune: the search space, the objective, the hold-out, the parameters file, the study."""

from __future__ import annotations

import json
from pathlib import Path

from cgags_ros.config import PipelineConfig
from cgags_ros.config.node import configs_from_file, configs_from_parameters
from cgags_ros.errors import InvalidConfigError
from cgags_ros.tools import tune, tuning
from cgags_ros.tools.replay import build_parser as replay_parser
from cgags_ros.tools.replay import options_from_args, run
from cgags_ros.tools.replay_common import ReplayError
import numpy as np
import pytest


def _pair(i: int) -> tuning.TunePair:
    return tuning.TunePair('bag', i, np.zeros((3, 3)), np.zeros((3, 3)), np.eye(4), i, 's', 't')


def test_the_search_space_holds_what_the_refusals_name_as_their_fix():
    assert tuning.search_space([]) == {}
    assert tuning.search_space(['ambiguous', 'chance_level']) == {}
    space = tuning.search_space(['free_space', 'free_space'])
    assert space == {'frontend.normal_orientation': ('origin', 'centroid')}
    space = tuning.search_space(['tilt', 'timeout', 'low_confidence'])
    assert set(space) == {'core.motion_model', 'core.time_budget'}
    # Every searched setting is a key of the node's configuration and takes each choice.
    for name, choices in tuning.search_space([c.value for c in tuning.FIXES]).items():
        for choice in choices:
            pipe, _ = configs_from_parameters({name: choice})
            assert pipe != PipelineConfig() or choice in ('origin', '6dof', 0.0)


def test_a_wrong_valid_pair_past_the_allowance_outweighs_every_right_one():
    clean = tuning.Score(pairs=10, right=6, wrong=0, median_s=0.5, refusals={})
    greedy = tuning.Score(pairs=10, right=9, wrong=1, median_s=0.1, refusals={})
    assert clean.value(max_wrong=0) > greedy.value(max_wrong=0)
    assert greedy.value(max_wrong=1) > clean.value(max_wrong=1)
    assert clean.recall == pytest.approx(0.6)
    # Time is no part of the value (a seed replays the same proposals).
    slow = tuning.Score(pairs=10, right=6, wrong=0, median_s=5.0, refusals={})
    assert slow.value(0) == clean.value(0)


def test_the_holdout_is_seeded_disjoint_and_its_share():
    pairs = [_pair(i) for i in range(10)]
    tuned, held = tuning.holdout_split(pairs, 0.3, seed=4)
    assert len(held) == 3 and len(tuned) == 7
    assert not {p.index for p in tuned} & {p.index for p in held}
    again = tuning.holdout_split(pairs, 0.3, seed=4)
    assert [p.index for p in again[1]] == [p.index for p in held]
    assert tuning.holdout_split(pairs, 0.0, seed=4)[1] == []
    assert len(tuning.holdout_split(pairs[:1], 0.5, seed=0)[0]) == 1  # one pair: tune on it
    # One held-out pair could never warn (a miss is within noise): a bag of four is tuned whole.
    assert tuning.holdout_split(pairs[:4], 0.3, seed=4) == (pairs[:4], [])
    assert len(tuning.holdout_split(pairs[:7], 0.3, seed=4)[1]) == tuning.MIN_HELD_OUT


def test_one_or_two_held_out_pairs_missed_never_warn_and_more_do():
    from cgags_ros.tools.tune_report import holdout_warning

    def score(right, pairs):
        return tuning.Score(pairs=pairs, right=right, wrong=0, median_s=0.1, refusals={})

    assert holdout_warning(score(3, 3), score(0, 1)) == ''
    assert holdout_warning(score(6, 6), score(1, 2)) == ''
    assert 'fare worse' in holdout_warning(score(6, 6), score(0, 2))
    assert 'fare worse' in holdout_warning(score(20, 20), score(2, 5))


def test_the_voxel_grid_spans_the_reference_and_the_start_on_a_log_scale():
    grid = tuning.voxel_grid(0.3, 3.0)
    assert min(grid) < 0.3 / 10 and max(grid) > 3.0 * 10
    assert any(abs(v - 0.3) < 1e-9 for v in grid) and any(abs(v - 3.0) < 0.01 for v in grid)
    steps = np.diff(np.log10(grid))
    assert np.allclose(steps, 1 / tuning.GRID_STEPS, atol=0.01)
    # A LiDAR start ten times too large: the grid stops at the largest voxel the node takes.
    coarse = tuning.voxel_grid(0.32, 3.2)
    assert max(coarse) <= 100.0 and min(coarse) < 0.3 / 10
    for voxel in coarse:
        configs_from_parameters({'voxel_size': voxel})  # every one valid


def test_the_parameters_file_is_read_back_by_the_node(tmp_path):
    settings = {'voxel_size': 0.378, 'frontend.normal_orientation': 'centroid',
                'core.motion_model': '4dof', 'core.time_budget': 0.5}
    path = tmp_path / 'params.yaml'
    path.write_text(tuning.params_yaml(settings, 'tuned\non two lines'), encoding='utf-8')
    text = path.read_text(encoding='utf-8')
    assert text.startswith('# tuned\n# on two lines\nregister_node:\n  ros__parameters:')
    pipe, _ = configs_from_file(str(path))  # what config_file and the node's loader read
    assert pipe.voxel_size == pytest.approx(0.378)
    assert pipe.frontend.normal_orientation == 'centroid'
    assert pipe.core.motion_model == '4dof' and pipe.core.time_budget == pytest.approx(0.5)
    opts, _ = options_from_args(replay_parser().parse_args(['bag', '--config', str(path)]))
    assert opts.parameters['voxel_size'] == pytest.approx(0.378)  # cgags-replay --config


def test_ground_truth_lines_and_their_errors(tmp_path):
    good = tmp_path / 'gt.txt'
    good.write_text('# stamp x y z qx qy qz qw\n5 1 2 3 0 0 0 1\n\n7 0 0 0 0 0 1 0\n')
    truth = tuning.read_ground_truth(good)
    assert set(truth) == {5, 7}
    np.testing.assert_allclose(truth[5][:3, 3], [1, 2, 3])
    np.testing.assert_allclose(truth[7][:3, :3], np.diag([-1.0, -1.0, 1.0]), atol=1e-12)
    bad = tmp_path / 'bad.txt'
    bad.write_text('5 1 2 3\n')
    with pytest.raises(ReplayError, match='bad.txt:1'):
        tuning.read_ground_truth(bad)
    with pytest.raises(ReplayError, match='cannot read'):
        tuning.read_ground_truth(tmp_path / 'missing.txt')


@pytest.fixture(scope='module')
def bunny(data_dir) -> Path:
    path = data_dir / 'bags' / 'bunny'
    if not path.is_dir():
        pytest.fail(f'bundled bags not found at {path}')
    return path


def _error(capsys, *argv) -> str:
    code = tune.main([str(a) for a in argv])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and err[0].startswith('cgags-tune: error: '), err
    return err[0]


def test_bad_bags_and_options_are_one_line_errors(bunny, tmp_path, capsys):
    assert "'/nope' is not in" in _error(capsys, bunny, '--source-topic', '/nope')
    assert '/gt' in _error(capsys, bunny, '--ground-truth-topic', '/gt')
    stamps = tmp_path / 'gt.txt'
    stamps.write_text('1 0 0 0 0 0 0 1\n')
    assert 'matches no source stamp' in _error(capsys, bunny, '--ground-truth', stamps)
    assert 'does not exist' in _error(capsys, tmp_path / 'missing')
    assert '--holdout' in _error(capsys, bunny, '--holdout', '1.5')
    assert '--trials' in _error(capsys, bunny, '--trials', '0')
    assert 'cannot open the study storage' in _error(capsys, bunny, '--storage', 'nosuch://x')
    assert '--jobs' in _error(capsys, bunny, '--jobs', '0')
    with pytest.raises(InvalidConfigError, match='one at a time'):  # one node, one trial
        tune.Options(bags=[bunny], live=True, jobs=2).check()
    with pytest.raises(InvalidConfigError, match='--timeout'):
        tune.Options(bags=[bunny], timeout=0.0).check()


def _tune(bag: Path, tmp_path: Path, trials: int, **extra) -> tune.Outcome:
    opts = tune.Options(bags=[bag], trials=trials, output=tmp_path / 'out',
                        storage=f"sqlite:///{tmp_path / 'study.db'}", quiet=True, **extra)
    return tune.tune(opts)


@pytest.mark.slow
def test_a_voxel_ten_times_too_large_is_tuned_back_and_the_node_file_reproduces_it(
        bunny, tmp_path):
    # Two trials: the start, then the automatic choice the study queues first. What the
    # sampler proposes after them is test_tune_search's, and costs most at the finest voxels.
    outcome = _tune(bunny, tmp_path, trials=2, voxel_size=0.024)
    assert outcome.trials[0]['voxel_size'] == pytest.approx(0.024)  # where it started
    start = outcome.trials[0]
    assert start['right'] < start['pairs']  # ten times too large fails some pairs
    best = {k: outcome.scores[k] for k in outcome.scores if k[0] == 'best'}
    assert all(s.wrong == 0 for s in best.values())
    assert sum(s.right for s in best.values()) == 4  # every pair of the bag: the documented 4/4
    # The written file, given to cgags-replay as a node's parameters, gives that recall.
    args = replay_parser().parse_args([str(bunny), '--config', str(outcome.paths['params']),
                                       '--output', str(tmp_path / 'replay'), '--quiet'])
    report = run(*options_from_args(args))
    assert sum(bool(r.success) for r in report.rows) == 4
    assert outcome.paths['report'].read_text().startswith('# cgags-tune')
    summary = json.loads(outcome.paths['summary'].read_text())
    assert summary['best'] == outcome.best and len(summary['trials']) == 2
    assert outcome.paths['plot'].stat().st_size > 0


@pytest.mark.slow
def test_a_study_resumes_without_repeating_trials_and_a_seed_replays_it(bunny, tmp_path):
    first = _tune(bunny, tmp_path / 'a', trials=3)
    with pytest.raises(Exception, match='--resume'):
        _tune(bunny, tmp_path / 'a', trials=5)
    resumed = _tune(bunny, tmp_path / 'a', trials=5, resume=True)
    assert [t['number'] for t in resumed.trials] == list(range(len(resumed.trials)))
    assert sum('repeat_of' not in t for t in resumed.trials) == 5  # repeats do not count
    assert resumed.trials[:len(first.trials)] == first.trials  # read back, not run again

    def proposals(outcome):
        return [{k: v for k, v in t.items() if k != 'median_s'} for t in outcome.trials]

    assert proposals(_tune(bunny, tmp_path / 'b', trials=3)) == proposals(first)


def moved_bunny_bag(data_dir: Path, path: Path) -> Path:
    """
    Write the turntable scans' four pairs as a bag whose clouds are not in their sensor frame.

    Every scan moved by one rigid motion (as a tool that re-centres clouds would), the
    ground truth moved with them: the sensors' origins are no longer the clouds' origins.
    """
    from bench.datasets.gt_pairs import read_gt_pairs
    from cgags_ros.geometry import apply_transform, make_transform
    from cgags_ros.io.bag import write_bag
    from cgags_ros.io.clouds import read_cloud
    from scipy.spatial.transform import Rotation

    M = make_transform(Rotation.from_euler('xyz', [70, -40, 120], degrees=True).as_matrix(),
                       [0.4, -0.3, 0.25])
    messages = []
    pairs = read_gt_pairs(data_dir / 'objects' / 'stanford_bunny_scans' / 'gt_pairs.txt')
    for k, (source, target, truth) in enumerate(pairs):
        stamp = (k + 1) * 10**9
        messages += [('/target_cloud', stamp, 'turntable', apply_transform(M, read_cloud(target))),
                     ('/source_cloud', stamp + 10**7, 'scanner',
                      apply_transform(M, read_cloud(source))),
                     ('/ground_truth', stamp + 10**7, 'turntable',
                      M @ truth @ np.linalg.inv(M))]
    write_bag(path, messages)
    return path


@pytest.mark.slow
def test_clouds_out_of_their_sensor_frame_are_tuned_to_the_fix_free_space_names(
        data_dir, tmp_path):
    """The defaults refuse right poses for free space; the tuned setting keeps them."""
    bag = moved_bunny_bag(data_dir, tmp_path / 'moved_bunny')
    # Two trials: the start, then the fix its refusals open (queued first, as a stage).
    outcome = _tune(bag, tmp_path, trials=2, holdout=0.0)
    start = outcome.scores['defaults', 'tuned on']
    assert start.refusals.get('free_space', 0) >= 1 and start.right < 4
    assert [stage['opened'] for stage in outcome.stages] == [['frontend.normal_orientation']]
    assert outcome.best['frontend.normal_orientation'] == 'centroid'
    best = outcome.scores['best', 'tuned on']
    assert best.right == 4 and best.wrong == 0


def bunny_without_truth(data_dir: Path, path: Path) -> Path:
    """Write the turntable scans' four pairs as a bag without a ground-truth topic."""
    from bench.datasets.gt_pairs import read_gt_pairs
    from cgags_ros.io.bag import write_bag
    from cgags_ros.io.clouds import read_cloud

    messages = []
    pairs = read_gt_pairs(data_dir / 'objects' / 'stanford_bunny_scans' / 'gt_pairs.txt')
    for k, (source, target, _) in enumerate(pairs):
        stamp = (k + 1) * 10**9
        messages += [('/target_cloud', stamp, 'turntable', read_cloud(target)),
                     ('/source_cloud', stamp + 10**7, 'scanner', read_cloud(source))]
    write_bag(path, messages)
    return path


@pytest.mark.slow
def test_without_ground_truth_pairs_are_judged_by_their_reverse_registration(
        bunny, data_dir, tmp_path):
    """Right poses are confirmed by the reverse registration; a wrong one is contradicted."""
    pairs = tuning.load_pairs([bunny], '/source_cloud', '/target_cloud', None)
    criteria = tuning.criteria_for(0.0024, 5.0, 0.01)
    settings = {'voxel_size': 0.0024}
    truth_score, rows = tuning.replay(pairs, settings, criteria)
    assert truth_score.judged_by == 'ground truth' and truth_score.right == 4
    blind = [tuning.TunePair(**{**vars(p), 'truth': None}) for p in pairs]
    confirmed = tuning.score(blind, rows, settings, criteria)
    assert (confirmed.judged_by, confirmed.right, confirmed.wrong) == ('consistency', 4, 0)
    from scipy.spatial.transform import Rotation
    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_euler('z', 30, degrees=True).as_matrix()
    rows[1].transform = rows[1].transform @ turn  # a valid pose 30 degrees off
    contradicted = tuning.score(blind, rows, settings, criteria)
    assert (contradicted.right, contradicted.wrong) == (3, 1)
    assert rows[1].re_deg == pytest.approx(30, abs=3)
    # A bag without the topic is judged so; bags with and without it do not mix.
    bare = bunny_without_truth(data_dir, tmp_path / 'bare')
    assert all(p.truth is None for p in
               tuning.load_pairs([bare], '/source_cloud', '/target_cloud', None))
    with pytest.raises(ReplayError, match='tune them apart'):
        tuning.load_pairs([bunny, bare], '/source_cloud', '/target_cloud', None)
    with pytest.raises(Exception, match='/ground_truth'):  # a topic named is a topic required
        tuning.load_pairs([bare], '/source_cloud', '/target_cloud', '/ground_truth')


@pytest.mark.slow
@pytest.mark.subprocess
def test_several_processes_share_one_study(bunny, tmp_path):
    outcome = _tune(bunny, tmp_path, trials=5, jobs=2, voxel_size=0.024)
    distinct = sum('repeat_of' not in t for t in outcome.trials)
    assert distinct in (5, 6)  # a second process may start one as the first stops
    assert {t['number'] for t in outcome.trials} == set(range(len(outcome.trials)))
    assert all('right' in t for t in outcome.trials)
    assert outcome.scores['best', 'tuned on'].right == 4
