"""
``cgags-tune``: the settings that register your own recorded bags best, as a ROS parameters file.

::

    cgags-tune BAG [BAG ...] [--voxel-size V0] [--trials N] [--seed S] [--holdout 0.3]
               [--max-wrong 0] [--output DIR] [--storage URL] [--resume]
               [--ground-truth FILE] [--source-topic T] [--target-topic T]
               [--ground-truth-topic T]

Replays every pair of the bags (paired as the node pairs them, the topics as in
``cgags-replay``) once a trial with Optuna's seeded TPE sampler choosing the settings
(:mod:`.tuning` says which and why), scores them against the bags' ground truth
(``/ground_truth`` PoseStamped, or ``--ground-truth`` lines ``STAMP_NS x y z qx qy qz
qw``) and writes to DIR (default ``out/tune/<first bag>``):

- ``params.yaml``: the best settings as a ROS 2 parameters file (``register_node:
  ros__parameters:``), for ``--ros-args --params-file``, ``ros2 param load`` and
  ``cgags-replay --config``; every searched setting is a ROS parameter of the node;
- ``report.md``: the best trial against the defaults on the pairs tuned on and on the
  held-out ones (pairs right and valid, valid but wrong, median seconds a pair), a warning
  when the held-out pairs fare worse than noise allows, and every trial;
- ``trials.png``: every trial's recall against its median time, the Pareto front marked;
- ``summary.json``: the same for programs (best settings, each split's score, every trial).

The study is stored in ``out/tune/<first bag>.db`` (SQLite) unless ``--storage`` names
another Optuna storage URL (a shared database lets several machines work on one study);
``--resume`` continues a stopped study up to ``--trials`` trials, without repeating one.
Without ground truth it stops with an error: an objective that needs none is not built yet.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
from pathlib import Path
import sys
from typing import Any, Sequence

from .cli import Parser, run_cli
from .replay_common import DEFAULT_GT_TOPIC, ReplayError
from ..errors import InvalidConfigError

PROG = 'cgags-tune'
SQLITE = 'sqlite:///'


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
    p.add_argument('--trials', type=int, default=30, help='trials in all (default: 30)')
    p.add_argument('--seed', type=int, default=0, help='sampler and hold-out seed')
    p.add_argument('--holdout', type=float, default=0.3,
                   help='share of the pairs held out of the search (default: 0.3)')
    p.add_argument('--max-wrong', type=int, default=0,
                   help='valid but wrong pairs a setting may have (default: 0)')
    p.add_argument('--output', type=Path, default=None, help='default: out/tune/<first bag>')
    p.add_argument('--storage', default=None, help='Optuna storage URL (default: SQLite in '
                   'out/tune/<first bag>.db)')
    p.add_argument('--resume', action='store_true', help='continue a stopped study')
    p.add_argument('--ground-truth', type=Path, default=None, metavar='FILE',
                   help='STAMP_NS x y z qx qy qz qw lines (source -> target) instead of the '
                   "bag's ground-truth topic")
    p.add_argument('--source-topic', default='/source_cloud')
    p.add_argument('--target-topic', default='/target_cloud')
    p.add_argument('--ground-truth-topic', default=DEFAULT_GT_TOPIC)
    p.add_argument('--max-re-deg', type=float, default=None,
                   help='success: rotation error at most this (degrees; default as '
                   'cgags-replay)')
    p.add_argument('--max-te', type=float, default=None, help='success: translation error '
                   'at most this (metres; default 3 reference voxel sizes)')
    p.add_argument('--quiet', action='store_true', help='no progress bar, no tables')
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
    ground_truth_topic: str = DEFAULT_GT_TOPIC
    max_re_deg: float | None = None
    max_te: float | None = None
    quiet: bool = False

    def check(self) -> None:
        """Raise InvalidConfigError for options out of range."""
        if self.trials < 1:
            raise InvalidConfigError(f'--trials must be >= 1, got {self.trials}')
        if not 0.0 <= self.holdout < 1.0:
            raise InvalidConfigError(f'--holdout must be in [0, 1), got {self.holdout}')
        if self.voxel_size is not None and not self.voxel_size > 0:
            raise InvalidConfigError(f'--voxel-size must be > 0, got {self.voxel_size}')
        if self.max_wrong < 0:
            raise InvalidConfigError(f'--max-wrong must be >= 0, got {self.max_wrong}')

    @property
    def name(self) -> str:
        """Return the study's name: the first bag's."""
        bag = self.bags[0]
        return bag.stem if bag.suffix == '.mcap' else bag.resolve().name

    @property
    def out_dir(self) -> Path:
        """Return the output folder."""
        return self.output or Path('out') / 'tune' / self.name

    @property
    def storage_url(self) -> str:
        """Return the Optuna storage URL (a local SQLite file unless given), its folder made."""
        url = self.storage or f"sqlite:///{Path('out') / 'tune' / f'{self.name}.db'}"
        if url.startswith(SQLITE):
            Path(url[len(SQLITE):]).parent.mkdir(parents=True, exist_ok=True)
        return url


@dataclasses.dataclass
class Outcome:
    """A finished tuning: the best settings, and the comparison on both splits."""

    best: dict[str, Any]
    defaults: dict[str, Any]
    scores: dict[str, Any]  # (settings name, split) -> tuning.Score
    trials: list[dict[str, Any]]
    warning: str
    paths: dict[str, Path]


def tune(opts: Options) -> Outcome:
    """Run (or resume) the study of ``opts`` and write its outputs; return the outcome."""
    import optuna

    from . import tuning

    opts.check()
    pairs = tuning.load_pairs(opts.bags, opts.source_topic, opts.target_topic,
                              opts.ground_truth_topic, opts.ground_truth)
    tuned_on, held_out = tuning.holdout_split(pairs, opts.holdout, opts.seed)
    reference = tuning.reference_voxel(pairs)
    start = opts.voxel_size or reference
    criteria = tuning.criteria_for(reference, opts.max_re_deg, opts.max_te)
    grid = tuning.voxel_grid(reference, start)
    start, automatic = (min(grid, key=lambda v: abs(math.log(v / x))) for x in (start, reference))
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    try:
        study = optuna.create_study(study_name=opts.name, storage=opts.storage_url,
                                    direction='maximize', load_if_exists=True,
                                    sampler=optuna.samplers.TPESampler(seed=opts.seed))
    except Exception as exc:  # an unreachable database or a bad URL: what the user can fix
        raise InvalidConfigError(f'cannot open the study storage {opts.storage_url}: '
                                 f'{exc}') from exc
    done = [t for t in study.trials if t.state == optuna.trial.TrialState.COMPLETE]
    if study.trials and not opts.resume:
        raise InvalidConfigError(
            f'a study {opts.name!r} exists in {opts.storage_url} ({len(done)} trials): '
            '--resume to continue it, or --storage for a new one')
    if 'space' in study.user_attrs:
        space = {k: tuple(v) for k, v in study.user_attrs['space'].items()}
    else:
        baseline, _ = tuning.replay(tuned_on, {'voxel_size': start}, criteria)
        space = tuning.search_space(baseline.refusals)
        study.set_user_attr('space', {k: list(v) for k, v in space.items()})
        study.enqueue_trial({'voxel_size': start})
        if automatic != start:
            study.enqueue_trial({'voxel_size': automatic})

    def objective(trial: Any) -> float:
        settings = {'voxel_size': trial.suggest_categorical('voxel_size', grid)}
        for name, choices in space.items():
            settings[name] = trial.suggest_categorical(name, list(choices))
        score, _ = tuning.replay(tuned_on, settings, criteria)
        for key, value in dataclasses.asdict(score).items():
            trial.set_user_attr(key, value)
        return score.value(opts.max_wrong)

    remaining = opts.trials - len(done)
    if remaining > 0:
        from tqdm import tqdm

        bar = tqdm(total=remaining, disable=opts.quiet or None, unit='trial', leave=False)
        study.optimize(objective, n_trials=remaining, callbacks=[lambda *_: bar.update()])
        bar.close()
    return _finish(study, opts, tuned_on, held_out, criteria, reference)


def _finish(study: Any, opts: Options, tuned_on: list, held_out: list, criteria: Any,
            reference: float) -> Outcome:
    """Pick the best trial, replay it and the defaults on both splits, write the outputs."""
    import optuna

    from . import tuning

    trials = [t for t in study.trials if t.state == optuna.trial.TrialState.COMPLETE]
    if not trials:
        raise ReplayError('no trial completed')
    best = max(trials, key=lambda t: (t.value, -t.user_attrs['median_s'])).params
    defaults = {'voxel_size': reference}
    scores = {}
    for name, settings in (('best', best), ('defaults', defaults)):
        for split, pairs in (('tuned on', tuned_on), ('held out', held_out)):
            if pairs:
                scores[name, split] = tuning.replay(pairs, settings, criteria)[0]
    warning = _holdout_warning(scores.get(('best', 'tuned on')), scores.get(('best', 'held out')))
    rows = [{'number': t.number, **t.params, **{k: t.user_attrs[k] for k in
                                                ('right', 'wrong', 'pairs', 'median_s')}}
            for t in trials]
    out = opts.out_dir
    out.mkdir(parents=True, exist_ok=True)
    comment = (f'cgags-tune {" ".join(map(str, opts.bags))}: {len(trials)} trials, seed '
               f'{opts.seed}; report.md beside this file')
    paths = {'params': out / 'params.yaml', 'report': out / 'report.md',
             'plot': out / 'trials.png', 'summary': out / 'summary.json'}
    paths['params'].write_text(tuning.params_yaml(best, comment), encoding='utf-8')
    outcome = Outcome(best, defaults, scores, rows, warning, paths)
    paths['report'].write_text(report_markdown(outcome, opts), encoding='utf-8')
    paths['summary'].write_text(json.dumps({
        'best': best, 'defaults': defaults, 'warning': warning, 'trials': rows,
        'scores': [{'settings': name, 'split': split, **dataclasses.asdict(score)}
                   for (name, split), score in scores.items()]}, indent=1), encoding='utf-8')
    plot_trials(rows, paths['plot'])
    if not opts.quiet:
        print(report_markdown(outcome, opts))
    return outcome


def _holdout_warning(tuned: Any, held: Any) -> str:
    """Return a warning when the held-out recall is below the tuned one by more than noise."""
    if tuned is None or held is None or not held.pairs:
        return ''
    p = tuned.recall
    noise = 2.0 * math.sqrt(max(p * (1 - p), 0.25 / held.pairs) / held.pairs)
    if held.recall + noise < p:
        return (f'the held-out pairs fare worse ({100 * held.recall:.0f} % right and valid '
                f'against {100 * p:.0f} %) than noise allows: the settings may fit only the '
                'pairs they were chosen on; record more varied pairs')
    return ''


def report_markdown(outcome: Outcome, opts: Options) -> str:
    """Return the report: the best settings against the defaults on both splits, every trial."""
    lines = [f'# cgags-tune: {", ".join(map(str, opts.bags))}', '',
             f'best: `{outcome.best}`; defaults: `{outcome.defaults}`', '',
             '| settings | pairs | right and valid | valid but wrong | median s a pair |',
             '|---|---|---|---|---|']
    for (name, split), s in outcome.scores.items():
        lines.append(f'| {name}, {split} | {s.pairs} | {s.right} ({100 * s.recall:.0f} %) | '
                     f'{s.wrong} | {s.median_s:.3f} |')
    if outcome.warning:
        lines += ['', f'**Warning**: {outcome.warning}.']
    lines += ['', '| trial | settings | right | wrong | median s |', '|---|---|---|---|---|']
    for row in outcome.trials:
        settings = {k: v for k, v in row.items()
                    if k not in ('number', 'right', 'wrong', 'pairs', 'median_s')}
        lines.append(f"| {row['number']} | `{settings}` | {row['right']} of {row['pairs']} | "
                     f"{row['wrong']} | {row['median_s']:.3f} |")
    return '\n'.join(lines) + '\n'


def plot_trials(rows: list[dict[str, Any]], path: Path) -> None:
    """Draw every trial's recall against its median time, the Pareto front marked."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    recall = [r['right'] / max(r['pairs'], 1) for r in rows]
    times = [r['median_s'] for r in rows]
    front = [i for i in range(len(rows))
             if not any(recall[j] >= recall[i] and times[j] <= times[i]
                        and (recall[j], times[j]) != (recall[i], times[i])
                        for j in range(len(rows)))]
    fig, ax = plt.subplots(figsize=(5, 4))
    ax.scatter(times, recall, color='grey', s=18, label='trials')
    ax.scatter([times[i] for i in front], [recall[i] for i in front], color='C3', s=30,
               label='Pareto front')
    ax.set_xlabel('median seconds a pair')
    ax.set_ylabel('share right and valid')
    ax.set_ylim(-0.02, 1.02)
    ax.legend(loc='lower right', fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``cgags-tune``."""
    args = build_parser().parse_args(argv)
    opts = Options(**vars(args))
    return run_cli(PROG, lambda: (tune(opts), 0)[1])


if __name__ == '__main__':
    sys.exit(main())
