"""
Which settings ``cgags-tune`` writes: the best trial, ties broken on every pair, guarded.

The search scores the tuned-on pairs only. Among the trials at the best tuned-on score
(often several voxels that all register the same pairs), the held-out pairs break the tie:
the most pairs right over all pairs (a wrong pair past ``max_wrong`` weighing as in the
objective), and only then the fastest median pair. Time alone once chose a voxel that
missed the held-out pairs the defaults kept.

Then the guard: when the chosen settings fare worse on the held-out pairs than the
defaults beyond noise (more wrong pairs past the allowance, or a recall lower by more than
two binomial standard errors, as :func:`.tune_report.holdout_warning` counts noise), the
better of the two over all pairs is written (the defaults on a tie), and a warning says so
on stdout and in ``params.yaml``'s header.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Sequence

from . import tuning


@dataclasses.dataclass
class Choice:
    """The best trial's settings, those written, each one's score on both splits, the guard."""

    best: dict[str, Any]
    written: dict[str, Any]
    defaults: dict[str, Any]
    scores: dict[tuple[str, str], tuning.Score]  # ('best' | 'defaults', split) -> score
    guard: str = ''


def combined(tuned: tuning.Score, held: tuning.Score | None) -> tuning.Score:
    """Return the score over all pairs (the tuned-on median time: the tie-break's)."""
    if held is None:
        return tuned
    refusals = dict(tuned.refusals)
    for code, n in held.refusals.items():
        refusals[code] = refusals.get(code, 0) + n
    return tuning.Score(tuned.pairs + held.pairs, tuned.right + held.right,
                        tuned.wrong + held.wrong, tuned.median_s, refusals, tuned.judged_by,
                        tuned.unconfirmed + held.unconfirmed)


def worse_beyond_noise(held: tuning.Score, reference: tuning.Score, max_wrong: int) -> bool:
    """Return whether ``held`` is worse than ``reference`` (same pairs) beyond noise."""
    if max(0, held.wrong - max_wrong) > max(0, reference.wrong - max_wrong):
        return True
    if not held.pairs:
        return False
    p = reference.recall
    noise = 2.0 * math.sqrt(max(p * (1 - p), 0.25 / held.pairs) / held.pairs)
    return held.recall + noise < p


def score_of(attrs: dict[str, Any]) -> tuning.Score:
    """Return the score a trial stored in its user attributes."""
    return tuning.Score(**{f.name: attrs[f.name] for f in dataclasses.fields(tuning.Score)
                           if f.name in attrs})


def choose(trials: Any, scored: Sequence[tuple[dict[str, Any], tuning.Score]],
           has_held_out: bool, max_wrong: int) -> Choice:
    """
    Return the settings to write from the ``scored`` trials' (settings, tuned-on score).

    ``trials`` replays settings (offline or through the node): the tied trials and the
    defaults on the held-out pairs, the defaults on the tuned-on ones.
    """
    top = max(s.value(max_wrong) for _, s in scored)
    tied = [(params, s) for params, s in scored if s.value(max_wrong) == top]
    split = ('held out',)
    held = [trials.score(params, split)['held out'] if has_held_out else None
            for params, _ in tied]
    order = sorted(range(len(tied)), key=lambda i: (
        -combined(tied[i][1], held[i]).value(max_wrong), tied[i][1].median_s, i))
    best, best_tuned = tied[order[0]]
    defaults = trials.defaults()
    scores = {('best', 'tuned on'): best_tuned}
    if has_held_out:
        scores['best', 'held out'] = held[order[0]]
    for name, score in trials.score(defaults, ('tuned on', 'held out')).items():
        scores['defaults', name] = score
    choice = Choice(dict(best), dict(best), dict(defaults), scores)
    if not has_held_out or not worse_beyond_noise(scores['best', 'held out'],
                                                  scores['defaults', 'held out'], max_wrong):
        return choice
    overall = {name: combined(scores[name, 'tuned on'], scores[name, 'held out'])
               for name in ('best', 'defaults')}
    keep_best = overall['best'].value(max_wrong) > overall['defaults'].value(max_wrong)
    choice.written = dict(best if keep_best else defaults)
    b, d = scores['best', 'held out'], scores['defaults', 'held out']
    choice.guard = (
        f'the best trial ({_settings(best)}) fares worse on the {b.pairs} held-out pairs than '
        f'the defaults ({_settings(defaults)}) beyond noise: {b.right} right and valid, '
        f'{b.wrong} valid but wrong, against {d.right} and {d.wrong}. Written: the '
        f"{'best trial' if keep_best else 'defaults'}, better over all pairs "
        f"({overall['best'].right} right for the best trial, {overall['defaults'].right} for "
        f"the defaults, of {overall['best'].pairs})")
    return choice


def _settings(settings: dict[str, Any]) -> str:
    return ', '.join(f'{k} {v:g}' if isinstance(v, float) else f'{k} {v}'
                     for k, v in sorted(settings.items()))
