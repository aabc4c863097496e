"""
A ``cgags-tune`` study: its pairs, its storage, and its first trial.

:func:`prepare` loads the bags' pairs (each bag read once, live too), splits off the
held-out ones and opens the study in its storage; every process of a study calls it. The
first process of a new study replays the start once, records it as trial 0, queues the
automatic choice, and opens the space the start's refusals call for. The settings the user
fixed (:mod:`.tune_fixed`) apply to every trial and are never searched; a fixed
``voxel_size`` leaves the voxel out of the space (an empty grid). :func:`search` runs
the rest (:mod:`.tune_search`), in ``--jobs`` processes on the study's storage. Trials run
in this process (:class:`OfflineTrials`) or through a running node
(:class:`~.tune_live.LiveTrials`).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Sequence

from . import tuning
from .replay_common import ReplayError
from .tune_search import counted, distributions, open_stages, run_trials, stored_space
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
    fixed: dict[str, Any] = dataclasses.field(default_factory=dict)  # by the user, never searched


class OfflineTrials:
    """Trials replayed in this process, through the path ``cgags-replay`` takes."""

    def __init__(self, splits: dict[str, list], criteria: Any, reference: float,
                 fixed: dict[str, Any] | None = None):
        self.splits, self.criteria, self.reference = splits, criteria, reference
        self.fixed = dict(fixed or {})

    def defaults(self) -> dict[str, Any]:
        """Return the searched settings the user would run without tuning: the automatic voxel."""
        return {} if 'voxel_size' in self.fixed else {'voxel_size': self.reference}

    def score(self, settings: dict[str, Any], splits: Sequence[str]) -> dict[str, Any]:
        """
        Replay the pairs of ``splits`` with ``settings``; return each split's score.

        The fixed settings apply too (and win: the search never proposes one).

        :raises SettingRefused: a setting out of its range, as the node would refuse it.
        """
        settings = {**settings, **self.fixed}
        try:
            return {name: tuning.replay(self.splits[name], settings, self.criteria)[0]
                    for name in splits if self.splits[name]}
        except SettingRefused:
            raise
        except InvalidConfigError as exc:
            raise SettingRefused(str(exc)) from exc

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
    return optuna.create_study(study_name=opts.study_name, storage=storage, direction='maximize',
                               load_if_exists=True,
                               sampler=optuna.samplers.TPESampler(seed=opts.seed))


def prepare(opts: Any, first: bool = True) -> Setup:
    """
    Load the pairs and open the study (``first``: check it, and start it when new).

    Every process of a study calls it; only the first (``first``) may replay the start as
    trial 0, open the first stage and enqueue the automatic choice.
    """
    import optuna

    opts.check()
    pairs, contents = tuning.load_bags(opts.bags, opts.source_topic, opts.target_topic,
                                       opts.ground_truth_topic, opts.ground_truth, opts.fixed)
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
    grid = [] if 'voxel_size' in opts.fixed else tuning.voxel_grid(reference, start)
    start, automatic = (min(grid, key=lambda v: abs(math.log(v / x))) if grid else None
                        for x in (start, reference))
    try:
        study = _open_study(opts)
    except Exception as exc:  # an unreachable database or a bad URL: what the user can fix
        raise InvalidConfigError(f'cannot open the study storage {opts.storage_url}: '
                                 f'{exc}') from exc
    splits = {'tuned on': tuned_on, 'held out': held_out}
    if opts.live:
        from .tune_live import LiveTrials  # imports rclpy

        trials: Any = LiveTrials(opts, splits, criteria, contents)
    else:
        trials = OfflineTrials(splits, criteria, reference, opts.fixed)
    setup = Setup(study, splits, criteria, grid, {}, reference, trials, notes, dict(opts.fixed))
    if not first:
        setup.space = stored_space(study)
        return setup
    done = [t for t in study.trials if t.state == optuna.trial.TrialState.COMPLETE]
    if study.trials and not opts.resume:
        trials.close()
        raise InvalidConfigError(
            f'a study of these arguments ({opts.study_name}) exists in {opts.storage_url} '
            f'({len(done)} trials): --resume to continue it, or another --output')
    if not study.trials:
        _start(setup, opts, start, automatic)
    setup.space = stored_space(study)
    return setup


def _start(setup: Setup, opts: Any, start: float | None, automatic: float | None) -> None:
    """Replay the start once as trial 0, queue the automatic choice, open stage 0."""
    import optuna

    study = setup.study
    params = {} if start is None else {'voxel_size': start}  # None: voxel_size fixed
    try:
        score = setup.trials.score(params, ('tuned on',))['tuned on']
    except SettingRefused as exc:
        result: dict[str, Any] = {'state': optuna.trial.TrialState.FAIL,
                                  'user_attrs': {'refused': str(exc)}}
    else:
        result = {'value': score.value(opts.max_wrong), 'user_attrs': dataclasses.asdict(score)}
    study.set_user_attr('space', {})
    study.set_user_attr('stages', [])
    trial = optuna.trial.create_trial(params=params, distributions=distributions(setup.grid, {}),
                                      **result)
    study.add_trial(trial)
    if automatic != start:
        study.enqueue_trial({'voxel_size': automatic})
    open_stages(setup, study)


def search(setup: Any, opts: Any) -> None:
    """Run the trials still to run, in ``opts.jobs`` processes."""
    from tqdm import tqdm

    study = setup.study
    if counted(study) >= opts.trials:
        return
    bar = tqdm(total=opts.trials, initial=counted(study), disable=opts.quiet or None,
               unit='trial', leave=False)
    workers = _start_workers(opts, opts.jobs - 1)
    try:
        run_trials(setup, opts, lambda s: bar.update(counted(s) - bar.n))
    finally:
        for worker in workers:
            worker.join()
        bar.close()
    failed = [w.exitcode for w in workers if w.exitcode]
    if failed:
        raise ReplayError(f'{len(failed)} of the --jobs processes failed (exit codes {failed})')


def _start_workers(opts: Any, n: int) -> list[Any]:
    """Start ``n`` processes that run trials of the same study beside this one."""
    import multiprocessing

    context = multiprocessing.get_context('spawn')  # no fork of a process with threads
    workers = [context.Process(target=_work, args=(opts,), daemon=True)
               for _ in range(max(0, n))]
    for worker in workers:
        worker.start()
    return workers


def _work(opts: Any) -> None:
    """Run trials of ``opts``' study until it has ``opts.trials`` (a ``--jobs`` process)."""
    setup = prepare(dataclasses.replace(opts, quiet=True), first=False)
    try:
        run_trials(setup, opts)
    finally:
        setup.trials.close()
