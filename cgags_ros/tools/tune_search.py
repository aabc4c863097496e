"""
How a ``cgags-tune`` study runs its trials: a space that follows the refusals, no repeats.

**Stages.** The space starts as ``voxel_size`` alone (nothing when the user fixed it).
After every scored trial (trial 0, the start, first), the refusals of the best trials so
far (every trial at the best tuned-on score) are read: a setting that docs/refusals.md
names as their fix (:data:`.tuning.FIXES`), that the user did not fix, and that is not
searched yet is opened, and its other choices are tried next on the fastest best trial
that was refused so. Each such step is a stage, and the study records it (its user
attribute ``stages``: the trial, its refusals, what it opened). A bag whose start
registers nothing, so refuses nothing for free space, still reaches
``frontend.normal_orientation`` once a better voxel shows free-space refusals.

**Repeats.** On a grid the sampler often proposes settings tried before. Such a proposal
is recorded (its score read back, ``repeat_of``) but not replayed, and it does not count
against ``--trials``: the untried settings nearest to it are tried next instead. A study
ends when ``--trials`` distinct settings are scored, or when none is left untried.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from typing import Any, Callable

from . import tuning
from .tuning import SettingRefused


def stored_space(study: Any) -> dict[str, tuple]:
    """Return the settings searched beside ``voxel_size`` so far."""
    return {k: tuple(v) for k, v in study.user_attrs.get('space', {}).items()}


def distributions(grid: list[float], space: dict[str, tuple]) -> dict[str, Any]:
    """Return the Optuna distributions of the voxel grid (none when empty) and ``space``."""
    from optuna.distributions import CategoricalDistribution

    return {**({'voxel_size': CategoricalDistribution(grid)} if grid else {}),
            **{name: CategoricalDistribution(list(c)) for name, c in space.items()}}


def filled(trials: Any, params: dict[str, Any]) -> dict[str, Any]:
    """Return ``params`` with every fixable setting they leave out at what a trial runs."""
    base = {name: choices[0] for name, choices in tuning.FIXES.values()}
    base.update({k: v for k, v in trials.defaults().items() if k != 'voxel_size'})
    return {**base, **params}


def _scored(study: Any) -> list[Any]:
    """Return the trials replayed and scored (no repeat, no refused settings)."""
    import optuna

    return [t for t in study.get_trials(deepcopy=False,
                                        states=(optuna.trial.TrialState.COMPLETE,))
            if 'right' in t.user_attrs and 'repeat_of' not in t.user_attrs]


def counted(study: Any) -> int:
    """Return the trials that count against ``--trials``: started, and not repeats."""
    import optuna

    return sum(t.state != optuna.trial.TrialState.WAITING and 'repeat_of' not in t.user_attrs
               for t in study.get_trials(deepcopy=False))


def earlier(trials: Any, study: Any, params: dict[str, Any]) -> Any:
    """Return a finished trial run with the same settings as ``params``, if any."""
    import optuna

    states = (optuna.trial.TrialState.COMPLETE, optuna.trial.TrialState.FAIL)
    want = filled(trials, params)
    for other in study.get_trials(deepcopy=False, states=states):
        ran = 'right' in other.user_attrs or other.user_attrs.get('refused')
        if ran and 'repeat_of' not in other.user_attrs and filled(trials, other.params) == want:
            return other
    return None


def nearest_untried(setup: Any, study: Any, params: dict[str, Any]) -> dict[str, Any] | None:
    """Return the untried settings of the space nearest ``params`` (None: all tried)."""
    import optuna

    space = stored_space(study)
    states = (optuna.trial.TrialState.COMPLETE, optuna.trial.TrialState.FAIL,
              optuna.trial.TrialState.RUNNING, optuna.trial.TrialState.WAITING)
    tried = [filled(setup.trials, t.params if t.params else t.system_attrs.get(
        'fixed_params', {})) for t in study.get_trials(deepcopy=False, states=states)]
    want = filled(setup.trials, params)
    best, best_key = None, None
    names = list(space)
    axes = {**({'voxel_size': setup.grid} if setup.grid else {}), **space}
    for values in itertools.product(*axes.values()):
        candidate = dict(zip(axes, values))
        full = filled(setup.trials, candidate)
        if full in tried:
            continue
        key = (sum(full[n] != want[n] for n in names),
               abs(math.log(candidate['voxel_size'] / want['voxel_size'])) if setup.grid
               else 0.0)
        if best_key is None or key < best_key:
            best, best_key = candidate, key
    return best


def open_stages(setup: Any, study: Any) -> list[dict[str, Any]]:
    """Open the settings the best trials' refusals name and queue them; return new stages."""
    scored = _scored(study)
    if not scored:
        return []
    top = max(t.value for t in scored)
    best = sorted((t for t in scored if t.value == top),
                  key=lambda t: (t.user_attrs['median_s'], t.number))
    space = stored_space(study)
    opened: dict[int, list[str]] = {}
    anchors = {}
    for trial in best:
        for name, choices in tuning.search_space(trial.user_attrs['refusals'],
                                                 setup.fixed).items():
            if name not in space:
                space[name] = choices
                opened.setdefault(trial.number, []).append(name)
                anchors[trial.number] = trial
    if not opened:
        return []
    study.set_user_attr('space', {k: list(v) for k, v in space.items()})
    stages = list(study.user_attrs.get('stages', []))
    new = []
    for number, names in opened.items():
        at = anchors[number]
        new.append({'stage': len(stages) + len(new) + 1, 'trial': number, 'settings': at.params,
                    'refusals': at.user_attrs['refusals'], 'opened': names})
        base = {name: choices[0] for name, choices in space.items()}
        base.update(at.params)
        for name in names:
            for choice in space[name]:
                if choice != filled(setup.trials, at.params)[name]:
                    study.enqueue_trial({**base, name: choice})
    study.set_user_attr('stages', stages + new)
    return new


def record_score(trial: Any, score: tuning.Score) -> None:
    """Store ``score`` in ``trial``'s user attributes (what the report and the stages read)."""
    for key, value in dataclasses.asdict(score).items():
        trial.set_user_attr(key, value)


def run_trials(setup: Any, opts: Any, on_trial: Callable[[Any], None] | None = None) -> None:
    """Ask, replay and tell trials until ``opts.trials`` count or nothing is left untried."""
    import optuna

    study = setup.study
    while counted(study) < opts.trials:
        trial = study.ask(distributions(setup.grid, stored_space(study)))
        params = dict(trial.params)
        before = earlier(setup.trials, study, params)
        if before is not None:  # read back, not replayed (nor refused again), not counted
            trial.set_user_attr('repeat_of', before.number)
            for key, value in before.user_attrs.items():
                trial.set_user_attr(key, value)
            if before.user_attrs.get('refused'):
                study.tell(trial, state=optuna.trial.TrialState.FAIL)
            else:
                study.tell(trial, before.value)
            untried = nearest_untried(setup, study, params)
            if untried is None:
                return
            study.enqueue_trial(untried)
            continue
        try:
            score = setup.trials.score(params, ('tuned on',))['tuned on']
        except SettingRefused as exc:
            trial.set_user_attr('refused', str(exc))
            study.tell(trial, state=optuna.trial.TrialState.FAIL)
        else:
            record_score(trial, score)
            study.tell(trial, score.value(opts.max_wrong))
            open_stages(setup, study)
        if on_trial is not None:
            on_trial(study)
