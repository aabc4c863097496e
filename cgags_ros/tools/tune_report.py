"""
What ``cgags-tune`` writes beside ``params.yaml``: the report, the plot, the hold-out warning.

The report names the settings written (:mod:`.tune_choice`), compares the best trial with
the defaults on the pairs tuned on and on the held-out ones, and lists every trial; the
plot shows every trial's recall against its median time, the Pareto front marked.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Sequence

TRIAL_SCORE_KEYS = ('right', 'wrong', 'pairs', 'median_s', 'judged_by', 'unconfirmed')
NOT_SETTINGS = ('number', 'refused', 'repeat_of') + TRIAL_SCORE_KEYS


def holdout_warning(tuned: Any, held: Any) -> str:
    """
    Return a warning when the held-out recall is below the tuned one by more than noise.

    Noise is two binomial standard errors of the held-out share (at least that of a
    recall of one half), so one pair missed of one or two held out never warns.
    """
    if tuned is None or held is None or not held.pairs:
        return ''
    p = tuned.recall
    noise = 2.0 * math.sqrt(max(p * (1 - p), 0.25 / held.pairs) / held.pairs)
    if held.recall + noise < p:
        return (f'the held-out pairs fare worse ({100 * held.recall:.0f} % right and valid '
                f'against {100 * p:.0f} %) than noise allows: the settings may fit only the '
                'pairs they were chosen on; record more varied pairs')
    return ''


def report_markdown(bags: Sequence[Any], choice: Any, scores: dict[tuple[str, str], Any],
                    trials: list[dict[str, Any]], notes: Sequence[str]) -> str:
    """Return the report: what was written, the best against the defaults, every trial."""
    judged = next(iter(scores.values())).judged_by if scores else 'ground truth'
    right = 'right and valid' if judged == 'ground truth' else 'valid and confirmed'
    wrong = 'valid but wrong' if judged == 'ground truth' else 'valid and contradicted'
    lines = [f'# cgags-tune: {", ".join(map(str, bags))}', '',
             f'written: `{choice.written}`; best trial: `{choice.best}`; defaults: '
             f'`{choice.defaults}`; judged by {judged}', '']
    lines += [f'- {note}' for note in notes] + ([''] if notes else [])
    lines += [f'| settings | pairs | {right} | {wrong} | median s a pair |',
              '|---|---|---|---|---|']
    for (name, split), s in scores.items():
        lines.append(f'| {name}, {split} | {s.pairs} | {s.right} ({100 * s.recall:.0f} %) | '
                     f'{s.wrong} | {s.median_s:.3f} |')
    lines += ['', '| trial | settings | right | wrong | median s |', '|---|---|---|---|---|']
    for row in trials:
        settings = {k: v for k, v in row.items() if k not in NOT_SETTINGS}
        if row.get('refused'):
            lines.append(f"| {row['number']} | `{settings}` | refused: {row['refused']} | | |")
            continue
        again = f" (as trial {row['repeat_of']})" if 'repeat_of' in row else ''
        lines.append(f"| {row['number']} | `{settings}` | {row['right']} of {row['pairs']}"
                     f"{again} | {row['wrong']} | {row['median_s']:.3f} |")
    return '\n'.join(lines) + '\n'


def plot_trials(rows: list[dict[str, Any]], path: Path) -> None:
    """Draw every scored trial's recall against its median time, the Pareto front marked."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    rows = [r for r in rows if not r.get('refused')]
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
