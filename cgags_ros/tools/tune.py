"""
``cgags-tune``: the settings that register your own recorded bags best, as a ROS parameters file.

::

    cgags-tune BAG [BAG ...] [--voxel-size V0] [--config FILE] [--set KEY=VALUE ...]
               [--trials N] [--seed S] [--holdout 0.3] [--max-wrong 0] [--output DIR]
               [--storage URL] [--resume] [--jobs N] [--ground-truth FILE]
               [--source-topic T] [--target-topic T] [--ground-truth-topic T]
               [--live [--node /register_node]]

Replays every pair of the bags (paired as the node pairs them, the topics as in
``cgags-replay``) once a trial with Optuna's seeded TPE sampler choosing the settings
(:mod:`.tuning` says which and why, :mod:`.tune_search` how the space follows the
refusals), scores them against the bags' ground truth
(``/ground_truth`` PoseStamped, or ``--ground-truth`` lines ``STAMP_NS x y z qx qy qz
qw``), or by their consistency when the bags have none, and writes to DIR (default
``out/tune/<first bag>``):

- ``params.yaml``: the chosen settings as a ROS 2 parameters file (``register_node:
  ros__parameters:``), for ``--ros-args --params-file``, ``ros2 param load`` and
  ``cgags-replay --config``; every searched setting is a ROS parameter of the node. Ties
  are broken on every pair, and settings worse than the defaults on the held-out pairs are
  not written without a warning (:mod:`.tune_choice`). The settings fixed with
  ``--config``/``--set`` are written too; those that are no ROS parameters (the sensors'
  positions) in ``config.yaml``, which ``params.yaml`` names as ``config_file``;
- ``report.md``: the best trial against the defaults on the pairs tuned on and on the
  held-out ones (pairs right and valid, valid but wrong, median seconds a pair), a warning
  when the held-out pairs fare worse than noise allows, and every trial;
- ``trials.png``: every trial's recall against its median time, the Pareto front marked;
- ``summary.json``: the same for programs (best settings, each split's score, every trial).

The study is stored in DIR's ``study.db`` (SQLite) unless ``--storage`` names another
Optuna storage URL (a shared database lets several machines work on one study), named
after the arguments that define it, so a run with other arguments starts its own;
``--resume`` continues a stopped study up to ``--trials`` trials, without repeating one.
``--jobs N`` runs the trials in N processes on that storage (then the trials' order, and so
the proposals, depend on timing: a seed no longer replays them).

``--config FILE`` (read as ``cgags-replay --config`` reads it) and ``--set KEY=VALUE``
fix settings: every trial runs with them, the start included, and none is searched
(:mod:`.tune_fixed`); e.g. ``frontend.source_sensor`` and ``frontend.target_sensor`` for
clouds not in their sensor's frame, which no tuner can guess (docs/frames.md).

``--live`` tunes a running ``register_node`` instead (:mod:`.tune_live`): each trial sets
the node's parameters through its parameter services and replays the bags through it; the
node is left on the best settings.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
from pathlib import Path
import sys
from typing import Any, Sequence

from . import tune_fixed
from .cli import Parser, run_cli
from .replay_common import DEFAULT_GT_TOPIC, ReplayError, user_parameters
from .tune_study import prepare, search, SQLITE
from ..config.node import ros_value
from ..errors import InvalidConfigError

PROG = 'cgags-tune'


def build_parser() -> argparse.ArgumentParser:
    """Return the argument parser of ``cgags-tune``."""
    summary = __doc__.strip().split('\n\n')[0].replace('``', '')
    p = Parser(prog=PROG, description=summary,
               formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('bags', type=Path, nargs='+', metavar='BAG',
                   help='rosbag2 directories or .mcap files with ground truth')
    p.add_argument('--voxel-size', type=float, default=None,
                   help='metres: where the search starts (default: chosen from the first '
                   'target cloud, as cgags-replay chooses it)')
    p.add_argument('--config', default=None, metavar='FILE',
                   help='settings fixed in every trial and never searched: YAML of node/'
                   'pipeline keys, as cgags-replay --config reads it (ROS format or a plain '
                   "mapping), e.g. the sensors' positions of clouds not in their sensor frame")
    p.add_argument('--set', action='append', default=[], metavar='KEY=VALUE',
                   help='fix one setting (repeatable, over --config), e.g. --set '
                   "'frontend.source_sensor=[0.1, 0, 0.3]'")
    p.add_argument('--trials', type=int, default=30, help='distinct settings scored, the '
                   'start included (default: 30)')
    p.add_argument('--seed', type=int, default=0, help='sampler and hold-out seed')
    p.add_argument('--holdout', type=float, default=0.3,
                   help='share of the pairs held out of the search (default: 0.3)')
    p.add_argument('--max-wrong', type=int, default=0,
                   help='valid but wrong pairs a setting may have (default: 0)')
    p.add_argument('--output', type=Path, default=None, help='default: out/tune/<first bag>')
    p.add_argument('--storage', default=None, help='Optuna storage URL (default: SQLite in '
                   'the output, study.db)')
    p.add_argument('--resume', action='store_true', help='continue a stopped study')
    p.add_argument('--jobs', type=int, default=1,
                   help='processes running trials at once (default: 1)')
    p.add_argument('--ground-truth', type=Path, default=None, metavar='FILE',
                   help='STAMP_NS x y z qx qy qz qw lines (source -> target) instead of the '
                   "bag's ground-truth topic")
    p.add_argument('--source-topic', default='/source_cloud')
    p.add_argument('--target-topic', default='/target_cloud')
    p.add_argument('--ground-truth-topic', default=None,
                   help=f'PoseStamped source -> target (default: {DEFAULT_GT_TOPIC} when the '
                   'bags have it; without ground truth the pairs are judged by consistency)')
    p.add_argument('--ignore-ground-truth', action='store_true',
                   help='judge by consistency even where the bags have ground truth (to see '
                   'what tuning without it would choose)')
    p.add_argument('--max-re-deg', type=float, default=None,
                   help='success: rotation error at most this (degrees; default as '
                   'cgags-replay)')
    p.add_argument('--max-te', type=float, default=None, help='success: translation error '
                   'at most this (metres; default 3 reference voxel sizes)')
    p.add_argument('--quiet', action='store_true', help='no progress bar, no tables')
    live = p.add_argument_group('tuning a running register_node through its parameters')
    live.add_argument('--live', action='store_true',
                      help="set a running node's parameters each trial and replay the bags "
                      'through it (over DDS)')
    live.add_argument('--node', default='/register_node', help='the node (default: '
                      '/register_node)')
    live.add_argument('--timeout', type=float, default=60.0,
                      help='seconds without an answer from the node before a pair counts '
                      'as lost (default: 60)')
    return p


@dataclasses.dataclass
class Options:
    """What ``cgags-tune`` was asked (see the module doc)."""

    bags: list[Path]
    voxel_size: float | None = None
    trials: int = 30
    seed: int = 0
    holdout: float = 0.3
    max_wrong: int = 0
    output: Path | None = None
    storage: str | None = None
    resume: bool = False
    ground_truth: Path | None = None
    source_topic: str = '/source_cloud'
    target_topic: str = '/target_cloud'
    ground_truth_topic: str | None = None
    ignore_ground_truth: bool = False
    max_re_deg: float | None = None
    max_te: float | None = None
    quiet: bool = False
    jobs: int = 1
    live: bool = False
    node: str = '/register_node'
    timeout: float = 60.0
    fixed: dict[str, Any] = dataclasses.field(default_factory=dict)  # --config, --set

    def check(self) -> None:
        """Raise InvalidConfigError for options out of range, or fixed settings (tune_fixed)."""
        if self.trials < 1:
            raise InvalidConfigError(f'--trials must be >= 1, got {self.trials}')
        if not 0.0 <= self.holdout < 1.0:
            raise InvalidConfigError(f'--holdout must be in [0, 1), got {self.holdout}')
        if self.voxel_size is not None and not self.voxel_size > 0:
            raise InvalidConfigError(f'--voxel-size must be > 0, got {self.voxel_size}')
        if self.max_wrong < 0:
            raise InvalidConfigError(f'--max-wrong must be >= 0, got {self.max_wrong}')
        if self.jobs < 1:
            raise InvalidConfigError(f'--jobs must be >= 1, got {self.jobs}')
        if self.live and self.jobs > 1:
            raise InvalidConfigError('--live tunes one node: its trials run one at a time '
                                     '(--jobs 1)')
        if not self.timeout > 0:
            raise InvalidConfigError(f'--timeout must be > 0, got {self.timeout}')
        tune_fixed.check(self.fixed, self.live, self.voxel_size)

    @property
    def name(self) -> str:
        """Return the first bag's name."""
        bag = self.bags[0]
        return bag.stem if bag.suffix == '.mcap' else bag.resolve().name

    @property
    def study_name(self) -> str:
        """Return the study's name: the first bag's, and a digest of what defines the study."""
        defining = [[str(Path(b).resolve()) for b in self.bags], self.voxel_size, self.seed,
                    self.holdout, self.max_wrong,
                    str(self.ground_truth.resolve()) if self.ground_truth else None,
                    self.source_topic, self.target_topic, self.ground_truth_topic,
                    self.ignore_ground_truth, self.max_re_deg, self.max_te, self.live,
                    self.node if self.live else None]
        if self.fixed:  # only then: the studies of earlier runs keep their names
            defining.append(sorted(self.fixed.items()))
        digest = hashlib.sha1(json.dumps(defining).encode()).hexdigest()[:10]
        return f'{self.name}-{digest}'

    @property
    def out_dir(self) -> Path:
        """Return the output folder."""
        return self.output or Path('out') / 'tune' / self.name

    @property
    def storage_url(self) -> str:
        """Return the Optuna storage URL (``study.db`` in the output unless given)."""
        url = self.storage or f"{SQLITE}{self.out_dir / 'study.db'}"
        if url.startswith(SQLITE):
            Path(url[len(SQLITE):]).parent.mkdir(parents=True, exist_ok=True)
        return url


@dataclasses.dataclass
class Outcome:
    """A finished tuning: the best and written settings, and the comparison on both splits."""

    best: dict[str, Any]
    defaults: dict[str, Any]
    scores: dict[Any, Any]  # (settings name, split) -> tuning.Score
    trials: list[dict[str, Any]]
    warning: str
    paths: dict[str, Path]
    notes: list[str] = dataclasses.field(default_factory=list)
    written: dict[str, Any] = dataclasses.field(default_factory=dict)
    guard: str = ''  # why the written settings are not the best trial's, or ''
    stages: list[dict[str, Any]] = dataclasses.field(default_factory=list)
    fixed: dict[str, Any] = dataclasses.field(default_factory=dict)  # by the user: every trial


def tune(opts: Options) -> Outcome:
    """Run (or resume) the study of ``opts`` and write its outputs; return the outcome."""
    setup = prepare(opts)
    try:
        search(setup, opts)
        return _finish(setup, opts)
    finally:
        setup.trials.close()


def _finish(setup: Any, opts: Options) -> Outcome:
    """Choose the settings to write (:mod:`.tune_choice`) and write the outputs."""
    import optuna

    from .tune_choice import choose, score_of
    from .tune_report import holdout_warning, plot_trials, report_markdown

    trials = sorted(setup.study.trials, key=lambda t: t.number)
    scored = [t for t in trials if t.state == optuna.trial.TrialState.COMPLETE
              and 'repeat_of' not in t.user_attrs]
    if not scored:
        raise ReplayError('no trial completed' + ''.join(
            f'; trial {t.number}: {t.user_attrs["refused"]}' for t in trials
            if t.user_attrs.get('refused')))
    choice = choose(setup.trials, [(t.params, score_of(t.user_attrs)) for t in scored],
                    bool(setup.splits['held out']), opts.max_wrong)
    setup.trials.leave_on(choice.written)
    scores = choice.scores
    warning = holdout_warning(scores.get(('best', 'tuned on')), scores.get(('best', 'held out')))
    rows = [_trial_row(t) for t in trials
            if t.state == optuna.trial.TrialState.COMPLETE or t.user_attrs.get('refused')]
    stages = list(setup.study.user_attrs.get('stages', []))
    notes = setup.notes + [_stage_note(stage) for stage in stages]
    notes += [f'warning: {text}' for text in (warning, choice.guard) if text]
    if setup.trials.lost:
        notes.append(f'{setup.trials.lost} pair(s) got no result from the node (lost by DDS '
                     'or later than --timeout) and counted as not right: while tuning, start '
                     'the node with pairing.source_qos:=reliable (docs/tuning.md)')
    if opts.fixed:
        notes.insert(0, tune_fixed.note(opts.fixed))
    out = opts.out_dir
    out.mkdir(parents=True, exist_ok=True)
    comment = (f'cgags-tune {" ".join(map(str, opts.bags))}: {len(scored)} trials, seed '
               f'{opts.seed}; report.md beside this file')
    if opts.fixed:
        comment += f"\nfixed by the user: {', '.join(sorted(opts.fixed))}"
    if choice.guard:
        comment += f'\nWARNING: {choice.guard}'
    paths = tune_fixed.write_params(out, choice.written, opts.fixed, comment)
    paths.update({'report': out / 'report.md', 'plot': out / 'trials.png',
                  'summary': out / 'summary.json'})
    outcome = Outcome(choice.best, choice.defaults, scores, rows, warning, paths, notes,
                      choice.written, choice.guard, stages, dict(opts.fixed))
    report = report_markdown(opts.bags, choice, scores, rows, notes)
    paths['report'].write_text(report, encoding='utf-8')
    paths['summary'].write_text(json.dumps({
        'best': choice.best, 'written': choice.written, 'defaults': choice.defaults,
        'fixed': {k: ros_value(v) for k, v in opts.fixed.items()},
        'warning': warning, 'guard': choice.guard, 'notes': notes, 'stages': stages,
        'trials': rows,
        'scores': [{'settings': name, 'split': split, **dataclasses.asdict(score)}
                   for (name, split), score in scores.items()]}, indent=1), encoding='utf-8')
    plot_trials(rows, paths['plot'])
    if not opts.quiet:
        print(report)
    if choice.guard:  # even --quiet: the file written is not the best trial's
        print(f'{PROG}: warning: {choice.guard}')
    return outcome


def _stage_note(stage: dict[str, Any]) -> str:
    """Return a stage of the space as a line of the report."""
    return (f"stage {stage['stage']}: trial {stage['trial']}'s refusals {stage['refusals']} "
            f"opened {', '.join(stage['opened'])}")


def _trial_row(trial: Any) -> dict[str, Any]:
    """Return a trial's settings and score (or why the node refused its settings)."""
    from .tune_report import TRIAL_SCORE_KEYS

    row = {'number': trial.number, **trial.params}
    if trial.user_attrs.get('refused'):
        return {**row, 'refused': trial.user_attrs['refused']}
    row.update({k: trial.user_attrs[k] for k in TRIAL_SCORE_KEYS if k in trial.user_attrs})
    if 'repeat_of' in trial.user_attrs:
        row['repeat_of'] = trial.user_attrs['repeat_of']
    return row


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``cgags-tune``."""
    args = vars(build_parser().parse_args(argv))
    config, sets = args.pop('config'), args.pop('set')

    def body() -> int:
        tune(Options(**args, fixed=user_parameters(config, sets, None, None)))
        return 0

    return run_cli(PROG, body)


if __name__ == '__main__':
    sys.exit(main())
