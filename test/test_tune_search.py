"""cgags-tune's search and choice: stages, repeats, trial 0, the tie-break, the guard, storage."""

from __future__ import annotations

from pathlib import Path

from cgags_ros.tools import tune, tune_choice, tune_search, tune_study, tuning
import pytest

GRID = [0.001, 0.002, 0.003, 0.004, 0.008]
ORIENTATION = 'frontend.normal_orientation'


class Fake:
    """Trials scored by a table: ``rule(settings, split)`` -> (right, wrong, refusals)."""

    def __init__(self, rule, pairs=4, held=0):
        self.rule, self.pairs, self.held, self.calls = rule, pairs, held, []

    def defaults(self):
        return {'voxel_size': 0.002}

    def score(self, settings, splits):
        self.calls.append((dict(settings), tuple(splits)))
        out = {}
        for split in splits:
            n = self.pairs if split == 'tuned on' else self.held
            if n:
                right, wrong, refusals = self.rule(settings, split)
                out[split] = tuning.Score(n, right, wrong, settings['voxel_size'], refusals)
        return out

    lost = 0

    def leave_on(self, settings):
        pass

    def close(self):
        pass


def _setup(trials, grid=GRID):
    import optuna

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.create_study(direction='maximize',
                                sampler=optuna.samplers.TPESampler(seed=3))
    return tune_study.Setup(study, {}, None, grid, {}, 0.002, trials, [])


def _replayed(trials):
    return [settings for settings, splits in trials.calls if splits == ('tuned on',)]


def test_repeated_proposals_are_read_back_and_do_not_eat_the_budget():
    trials = Fake(lambda s, _: (int(1000 * s['voxel_size']) % 3, 0, {}))
    setup = _setup(trials)
    for v in (0.002, 0.003, 0.002):
        setup.study.enqueue_trial({'voxel_size': v})
    tune_search.run_trials(setup, tune.Options(bags=[], trials=3))
    # The repeat of 0.002 is recorded, read back, and the nearest untried voxel runs instead.
    assert _replayed(trials) == [{'voxel_size': 0.002}, {'voxel_size': 0.003},
                                 {'voxel_size': 0.001}]
    again = setup.study.trials[2]
    assert again.user_attrs['repeat_of'] == 0 and again.value == setup.study.trials[0].value
    assert tune_search.counted(setup.study) == 3 and len(setup.study.trials) == 4


def test_a_study_stops_when_every_setting_was_tried():
    trials = Fake(lambda s, _: (1, 0, {}))
    setup = _setup(trials, grid=[0.001, 0.002])
    tune_search.run_trials(setup, tune.Options(bags=[], trials=10))
    assert sorted(s['voxel_size'] for s in _replayed(trials)) == [0.001, 0.002]


def _only_the_second_stage_succeeds(settings, _split):
    """Score a trial: the start refuses nothing for free space; the fix works at 0.002."""
    if settings['voxel_size'] == 0.004:
        return 0, 0, {'chance_level': 4}
    if settings['voxel_size'] == 0.002:
        if settings.get(ORIENTATION) == 'centroid':
            return 4, 0, {}
        return 1, 0, {'free_space': 3}
    return 0, 0, {'few_inliers': 4}


def test_trial_0_is_the_start_replayed_once_and_the_space_follows_the_best_refusals():
    trials = Fake(_only_the_second_stage_succeeds)
    setup = _setup(trials)
    opts = tune.Options(bags=[], trials=4)
    tune_study._start(setup, opts, start=0.004, automatic=0.002)
    study = setup.study
    assert study.trials[0].params == {'voxel_size': 0.004}
    assert study.trials[0].user_attrs['refusals'] == {'chance_level': 4}
    assert tune_search.stored_space(study) == {}  # the start names no fix
    tune_search.run_trials(setup, opts)
    replayed = _replayed(trials)
    assert replayed.count({'voxel_size': 0.004}) == 1  # the start, once: trial 0
    assert replayed[1] == {'voxel_size': 0.002}  # the automatic choice
    # Its free-space refusals open the fix, tried at once at that voxel: 4 of 4.
    assert replayed[2] == {'voxel_size': 0.002, ORIENTATION: 'centroid'}
    stages = study.user_attrs['stages']
    assert [(s['trial'], s['opened']) for s in stages] == [(1, [ORIENTATION])]
    assert study.best_trial.params == {'voxel_size': 0.002, ORIENTATION: 'centroid'}


def _choose(rule, held, scored):
    trials = Fake(rule, pairs=4, held=held)
    return tune_choice.choose(trials, scored, held > 0, max_wrong=0), trials


def _tuned(right, median_s, wrong=0):
    return tuning.Score(4, right, wrong, median_s, {})


def test_ties_are_broken_on_every_pair_before_time():
    held = {0.002: 2, 0.008: 0, 0.004: 1}  # right of the 2 held-out pairs, by voxel

    def rule(settings, split):
        return (held[settings['voxel_size']] if split == 'held out' else 2), 0, {}

    scored = [({'voxel_size': 0.002}, _tuned(2, 0.5)), ({'voxel_size': 0.008}, _tuned(2, 0.1)),
              ({'voxel_size': 0.004}, _tuned(2, 0.3)), ({'voxel_size': 0.001}, _tuned(1, 0.9))]
    choice, _ = _choose(rule, 2, scored)
    assert choice.best == choice.written == {'voxel_size': 0.002}  # 4 of 6, not the fastest
    assert not choice.guard
    # Without held-out pairs, the fastest of the tied.
    choice, _ = _choose(rule, 0, scored)
    assert choice.best == {'voxel_size': 0.008}


def test_settings_worse_than_the_defaults_held_out_are_not_written_silently(tmp_path, capsys):
    def rule(settings, split):
        if split == 'tuned on':
            return (4 if settings['voxel_size'] == 0.008 else 2), 0, {}
        return (0 if settings['voxel_size'] == 0.008 else 3), 0, {}

    choice, trials = _choose(rule, 3, [({'voxel_size': 0.008}, _tuned(4, 0.1)),
                                       ({'voxel_size': 0.002}, _tuned(2, 0.5))])
    assert choice.best == {'voxel_size': 0.008}
    assert choice.written == trials.defaults()  # 5 of 7 over all pairs against 4 of 7
    assert 'beyond noise' in choice.guard and 'defaults' in choice.guard
    # Within noise (one held-out pair fewer), the best is written without a word.
    assert not tune_choice.worse_beyond_noise(tuning.Score(3, 2, 0, 0.1, {}),
                                              tuning.Score(3, 3, 0, 0.1, {}), 0)
    assert tune_choice.worse_beyond_noise(tuning.Score(3, 3, 1, 0.1, {}),
                                          tuning.Score(3, 3, 0, 0.1, {}), 0)  # a wrong pair
    # Through the tool: the file written is the defaults, and stdout and its header say why.
    setup = _setup(trials)
    setup.splits = {'tuned on': [None] * 4, 'held out': [None] * 3}
    for v in (0.008, 0.002):
        setup.study.enqueue_trial({'voxel_size': v})
    tune_search.run_trials(setup, tune.Options(bags=[], trials=2))
    outcome = tune._finish(setup, tune.Options(bags=[Path('bag')], output=tmp_path, quiet=True))
    header = outcome.paths['params'].read_text().split('register_node:')[0]
    assert 'WARNING' in header and 'beyond noise' in header
    assert 'voxel_size: 0.002' in outcome.paths['params'].read_text()
    assert 'warning' in capsys.readouterr().out


def test_a_study_lives_with_its_output_and_other_arguments_start_their_own(tmp_path):
    bag = tmp_path / 'bag'
    first = tune.Options(bags=[bag], output=tmp_path / 'a', voxel_size=0.03, seed=7)
    assert first.storage_url == f"sqlite:///{tmp_path / 'a' / 'study.db'}"
    assert (tmp_path / 'a').is_dir()
    same = tune.Options(bags=[bag], output=tmp_path / 'b', voxel_size=0.03, seed=7, trials=60,
                        quiet=True, jobs=2, resume=True)
    assert same.study_name == first.study_name  # a resume with more trials: the same study
    for other in ({'voxel_size': 0.003}, {'seed': 8}, {'holdout': 0.0}, {'max_wrong': 1},
                  {'ignore_ground_truth': True}, {'live': True}):
        arguments = {'voxel_size': 0.03, 'seed': 7, **other}
        changed = tune.Options(bags=[bag], output=tmp_path / 'a', **arguments)
        assert changed.study_name != first.study_name, other


@pytest.mark.slow
def test_a_moved_cloud_bag_from_a_coarse_start_reaches_the_fix_in_the_second_stage(
        data_dir, tmp_path):
    """At 2.4 cm nothing registers nor is refused for free space: stage 0 opens nothing."""
    from test_tune import moved_bunny_bag

    bag = moved_bunny_bag(data_dir, tmp_path / 'moved_bunny')
    opts = tune.Options(bags=[bag], trials=4, voxel_size=0.024, holdout=0.0,
                        output=tmp_path / 'out', quiet=True)
    outcome = tune.tune(opts)
    start = outcome.trials[0]
    assert start['voxel_size'] == pytest.approx(0.024, rel=0.1)  # the grid's nearest
    assert start['right'] == 0
    assert outcome.stages and all(s['trial'] != 0 for s in outcome.stages)  # not the start
    assert all(ORIENTATION in s['opened'] and s['refusals'].get('free_space')
               for s in outcome.stages)
    assert outcome.written[ORIENTATION] == 'centroid'
    assert outcome.scores['best', 'tuned on'].right == 4
    assert outcome.scores['best', 'tuned on'].wrong == 0
    assert outcome.scores['defaults', 'tuned on'].right < 4
