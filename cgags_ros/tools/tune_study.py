"""
A ``cgags-tune`` study: its pairs and space, the objective, and the processes that run it.

:func:`prepare` loads the bags' pairs, splits off the held-out ones and opens the study in
its storage (choosing and storing the search space when the study is new); every process of
a study calls it. :func:`objective_of` is one trial: the sampler's settings replayed by the
study's trials (:class:`OfflineTrials` in this process, or
:class:`~.tune_live.LiveTrials` through a running node) and scored; settings tried before
are read back, not replayed. :func:`search` runs the trials still due, in ``--jobs``
processes on the study's storage.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable, Sequence

from . import tuning
from .replay_common import ReplayError
from .tuning import SettingRefused
from ..errors import InvalidConfigError

SQLITE = 'sqlite:///'  # the storage URLs of a local file
SQLITE_LOCK_WAIT_S = 60.0  # a --jobs process waits this long for the study file's lock


@dataclasses.dataclass
class Setup:
    """What every process of a study shares: the pairs, the grid, the space, the trials."""

    study: Any
    splits: dict[str, list]  # 'tuned on' / 'held out' -> tuning.TunePair
    criteria: Any
    grid: list[float]
    space: dict[str, tuple]
    reference: float
    trials: Any  # OfflineTrials or tune_live.LiveTrials
    notes: list[str]


class OfflineTrials:
    """Trials replayed in this process, through the path ``cgags-replay`` takes."""

    def __init__(self, splits: dict[str, list], criteria: Any, reference: float):
        self.splits, self.criteria, self.reference = splits, criteria, reference

    def defaults(self) -> dict[str, Any]:
        """Return the settings the user would run without tuning: the automatic voxel."""
        return {'voxel_size': self.reference}

    def score(self, settings: dict[str, Any], splits: Sequence[str]) -> dict[str, Any]:
        """Replay the pairs of ``splits`` with ``settings``; return each split's score."""
        return {name: tuning.replay(self.splits[name], settings, self.criteria)[0]
                for name in splits if self.splits[name]}

    def leave_on(self, best: dict[str, Any]) -> None:
        """Nothing runs on after an offline study."""

    def close(self) -> None:
        """Nothing to release offline."""

    lost = 0  # offline, every pair gets its result


def _open_study(opts: Any) -> Any:
    """Open (or create) the study of ``opts`` in its storage."""
    import optuna

    url = opts.storage_url
    storage: Any = url
    if url.startswith(SQLITE):  # several processes: wait for the file's lock, not fail
        storage = optuna.storages.RDBStorage(
            url, engine_kwargs={'connect_args': {'timeout': SQLITE_LOCK_WAIT_S}})
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    return optuna.create_study(study_name=opts.name, storage=storage, direction='maximize',
                               load_if_exists=True,
                               sampler=optuna.samplers.TPESampler(seed=opts.seed))


def prepare(opts: Any, first: bool = True) -> Setup:
    """
    Load the pairs and open the study (``first``: check it, choose and store its space).

    Every process of a study calls it; only the first (``first``) may create the study's
    space and enqueue its starting trials.
    """
    import optuna

    opts.check()
    pairs = tuning.load_pairs(opts.bags, opts.source_topic, opts.target_topic,
                              opts.ground_truth_topic, opts.ground_truth)
    if opts.ignore_ground_truth:
        pairs = [dataclasses.replace(p, truth=None) for p in pairs]
    tuned_on, held_out = tuning.holdout_split(pairs, opts.holdout, opts.seed)
    notes = []
    if opts.holdout > 0 and not held_out:
        notes.append(f'no pair held out: {len(pairs)} pairs would leave fewer than '
                     f'{tuning.MIN_HELD_OUT} to it, too few to show a difference beyond '
                     'noise; every pair is tuned on')
    if tuning.judged_by(pairs) == 'consistency':
        notes.append('no ground truth: pairs judged by consistency (each valid pair '
                     'registered again the other way round; docs/tuning.md)')
    reference = tuning.reference_voxel(pairs)
    start = opts.voxel_size or reference
    criteria = tuning.criteria_for(reference, opts.max_re_deg, opts.max_te)
    grid = tuning.voxel_grid(reference, start)
    start, automatic = (min(grid, key=lambda v: abs(math.log(v / x))) for x in (start, reference))
    try:
        study = _open_study(opts)
    except Exception as exc:  # an unreachable database or a bad URL: what the user can fix
        raise InvalidConfigError(f'cannot open the study storage {opts.storage_url}: '
                                 f'{exc}') from exc
    splits = {'tuned on': tuned_on, 'held out': held_out}
    if opts.live:
        from .tune_live import LiveTrials  # imports rclpy

        trials: Any = LiveTrials(opts, splits, criteria)
    else:
        trials = OfflineTrials(splits, criteria, reference)
    setup = Setup(study, splits, criteria, grid, {}, reference, trials, notes)
    if not first:
        setup.space = _stored_space(study)
        return setup
    done = [t for t in study.trials if t.state == optuna.trial.TrialState.COMPLETE]
    if study.trials and not opts.resume:
        trials.close()
        raise InvalidConfigError(
            f'a study {opts.name!r} exists in {opts.storage_url} ({len(done)} trials): '
            '--resume to continue it, or --storage for a new one')
    if 'space' in study.user_attrs:
        setup.space = _stored_space(study)
    else:
        baseline = trials.score({'voxel_size': start}, ('tuned on',))['tuned on']
        setup.space = tuning.search_space(baseline.refusals)
        study.set_user_attr('space', {k: list(v) for k, v in setup.space.items()})
        study.enqueue_trial({'voxel_size': start})
        if automatic != start:
            study.enqueue_trial({'voxel_size': automatic})
    return setup


def _stored_space(study: Any) -> dict[str, tuple]:
    return {k: tuple(v) for k, v in study.user_attrs.get('space', {}).items()}


CATCH = (SettingRefused,)  # a trial that fails so is recorded, and the study goes on


def objective_of(setup: Setup, opts: Any) -> Callable[[Any], float]:
    """Return the study's objective: one trial's settings replayed and scored."""

    def objective(trial: Any) -> float:
        settings = {'voxel_size': trial.suggest_categorical('voxel_size', setup.grid)}
        for name, choices in setup.space.items():
            settings[name] = trial.suggest_categorical(name, list(choices))
        earlier = _earlier(setup.study, trial)
        if earlier is not None:  # the same settings: read back, not replayed (nor refused again)
            trial.set_user_attr('repeat_of', earlier.number)
            for key, value in earlier.user_attrs.items():
                if key != 'repeat_of':
                    trial.set_user_attr(key, value)
            if earlier.user_attrs.get('refused'):
                raise SettingRefused(earlier.user_attrs['refused'])
            return earlier.value
        try:
            score = setup.trials.score(settings, ('tuned on',))['tuned on']
        except SettingRefused as exc:
            trial.set_user_attr('refused', str(exc))
            raise
        for key, value in dataclasses.asdict(score).items():
            trial.set_user_attr(key, value)
        return score.value(opts.max_wrong)

    return objective


def _earlier(study: Any, trial: Any) -> Any:
    """Return a finished trial of ``study`` with the same settings as ``trial``, if any."""
    import optuna

    finished = (optuna.trial.TrialState.COMPLETE, optuna.trial.TrialState.FAIL)
    for other in study.get_trials(deepcopy=False, states=finished):
        scored = 'right' in other.user_attrs or other.user_attrs.get('refused')
        if scored and other.params == trial.params:
            return other
    return None


def _started(study: Any) -> int:
    """Return the trials of ``study`` that ran or run (not those enqueued, still waiting)."""
    import optuna

    return sum(t.state != optuna.trial.TrialState.WAITING for t in study.trials)


def _max_trials(n: int) -> Any:
    """Return the callback that stops a process once the study has ``n`` trials started."""
    import optuna

    state = optuna.trial.TrialState
    return optuna.study.MaxTrialsCallback(
        n, states=(state.COMPLETE, state.FAIL, state.PRUNED, state.RUNNING))


def search(setup: Setup, opts: Any) -> None:
    """Run the trials still to run, in ``opts.jobs`` processes."""
    from tqdm import tqdm

    study = setup.study
    remaining = opts.trials - _started(study)
    if remaining <= 0:
        return
    bar = tqdm(total=opts.trials, initial=_started(study), disable=opts.quiet or None,
               unit='trial', leave=False)

    def progress(study: Any, _trial: Any) -> None:
        bar.update(_started(study) - bar.n)

    workers = _start_workers(opts, opts.jobs - 1, remaining)
    try:
        study.optimize(objective_of(setup, opts), n_trials=remaining,
                       callbacks=[_max_trials(opts.trials), progress], catch=CATCH)
    finally:
        for worker in workers:
            worker.join()
        bar.close()
    failed = [w.exitcode for w in workers if w.exitcode]
    if failed:
        raise ReplayError(f'{len(failed)} of the --jobs processes failed (exit codes {failed})')


def _start_workers(opts: Any, n: int, remaining: int) -> list[Any]:
    """Start ``n`` processes that run trials of the same study beside this one."""
    import multiprocessing

    context = multiprocessing.get_context('spawn')  # no fork of a process with threads
    workers = [context.Process(target=_work, args=(opts, remaining), daemon=True)
               for _ in range(max(0, n))]
    for worker in workers:
        worker.start()
    return workers


def _work(opts: Any, remaining: int) -> None:
    """Run trials of ``opts``' study until it has ``opts.trials`` (a ``--jobs`` process)."""
    setup = prepare(dataclasses.replace(opts, quiet=True), first=False)
    setup.study.optimize(objective_of(setup, opts), n_trials=remaining,
                         callbacks=[_max_trials(opts.trials)], catch=CATCH)
