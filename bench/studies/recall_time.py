r"""
Recall against time: settings of ours run side by side with KISS-Matcher, one chosen held out.

Run by hand from the repository root, after one interleaved run (about 40 minutes)::

    flock /tmp/cgags-bench.lock .venv/bin/python -m bench.threedmatch \
        --methods cgags kiss_matcher \
        --variant j10:regenerate.judged=10 [--variant NAME:KEY=VALUE,... ...] \
        --output out/curve/full --records out/curve/full
    .venv/bin/python -m bench.studies.recall_time out/curve/full/records.jsonl \
        [--output out/curve/recall_time]

Every method of the run is a point: its registration recall over every pair of a list
against its median seconds a pair, as a ratio to KISS-Matcher's median in the same run
(the methods alternate pair by pair, so the ratio holds under the machine's drift).

Two settings are then chosen on the two easiest scenes only (:data:`EASY`, the highest
recall) and reported on the two hardest, as the trust studies do:

- ``recall``: the fastest (the sum of both lists' median times on the easy scenes) among
  those with at least :data:`KEEP` of the most right pairs there (both lists summed);
- ``speed``: the highest recall among those whose 3DLoMatch median time on the easy scenes
  is at most KISS-Matcher's there.

Outputs ``--output`` + ``.md`` / ``.png``.
"""

from __future__ import annotations

import json
from pathlib import Path

from bench.common import argument_parser, markdown_table, pyplot, save_figure, write_text
import numpy as np

EASY = ('7-scenes-redkitchen', 'sun3d-hotel_uc-scan3')
BASELINE = 'kiss_matcher'
KEEP = 0.99  # a faster setting may lose one right pair in a hundred


def load(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text(encoding='utf-8').splitlines() if line]


def point(records: list[dict]) -> dict:
    """Return recall, median seconds and the valid flag's counts of one method's records."""
    times = [r['time_s'] for r in records if r['time_s'] == r['time_s']]
    valid = [r for r in records if r['valid']]
    return {'pairs': len(records), 'right': sum(r['success'] for r in records),
            'rr': sum(r['success'] for r in records) / len(records) if records else float('nan'),
            'median_s': float(np.median(times)) if times else float('nan'),
            'valid': len(valid), 'valid_wrong': sum(not r['success'] for r in valid)}


def points(records: list[dict], benchmark: str, scenes=None) -> dict[str, dict]:
    """Return {method: point} over one list (and the given scenes), ratios to the baseline's."""
    chosen = [r for r in records if r['benchmark'] == benchmark
              and (scenes is None or r['scene'] in scenes)]
    out = {m: point([r for r in chosen if r['method'] == m])
           for m in dict.fromkeys(r['method'] for r in chosen)}
    base = out.get(BASELINE, {}).get('median_s', float('nan'))
    for p in out.values():
        p['ratio'] = p['median_s'] / base
    return out


def choose(records: list[dict]) -> dict[str, str]:
    """Return the ``recall`` and ``speed`` settings, chosen on the easy scenes (module doc)."""
    ours = [m for m in dict.fromkeys(r['method'] for r in records) if m != BASELINE]
    lists = sorted({r['benchmark'] for r in records})
    easy = {b: points(records, b, EASY) for b in lists}
    right = {m: sum(easy[b][m]['right'] for b in lists) for m in ours}
    seconds = {m: sum(easy[b][m]['median_s'] for b in lists) for m in ours}
    most = max(right.values())
    recall = min((m for m in ours if right[m] >= KEEP * most), key=lambda m: seconds[m])
    fast = [m for m in ours if easy.get('3DLoMatch', easy[lists[0]])[m]['ratio'] <= 1.0]
    speed = max(fast, key=lambda m: (right[m], -seconds[m])) if fast else ''
    return {'recall': recall, 'speed': speed}


def report(records: list[dict]) -> str:
    lists = list(dict.fromkeys(r['benchmark'] for r in records))
    hard = sorted({r['scene'] for r in records} - set(EASY))
    rows = []
    for b in lists:
        every, on_hard = points(records, b), points(records, b, hard)
        for m, p in every.items():
            h = on_hard[m]
            rows.append((b, m, 100 * p['rr'], p['median_s'], p['ratio'],
                         f"{p['valid_wrong']} of {p['valid']}", 100 * h['rr'], h['ratio']))
    text = ['### Every setting, every pair\n', markdown_table(
        ('list', 'method', 'RR [%]', 'median [s]', 'x KISS', 'valid but wrong',
         'RR hard scenes [%]', 'x KISS hard'), rows)]
    chosen = choose(records)
    text.append(f'\n### Chosen on {", ".join(EASY)}; reported on {", ".join(hard)}\n')
    rows = []
    for role, m in chosen.items():
        for b in lists:
            if not m:
                rows.append((role, '(none at KISS time)', b, '', '', '', ''))
                continue
            e, h = points(records, b, EASY)[m], points(records, b, hard)[m]
            rows.append((role, m, b, 100 * e['rr'], e['ratio'], 100 * h['rr'], h['ratio']))
    text.append(markdown_table(('setting', 'method', 'list', 'RR easy [%]', 'x KISS easy',
                                'RR hard [%]', 'x KISS hard'), rows))
    return '\n'.join(text)


def plot(records: list[dict], path: Path) -> None:
    plt = pyplot()
    lists = list(dict.fromkeys(r['benchmark'] for r in records))
    fig, axes = plt.subplots(1, len(lists), figsize=(6 * len(lists), 4.5))
    for ax, b in zip(np.atleast_1d(axes), lists):
        for m, p in points(records, b).items():
            ax.scatter(p['ratio'], 100 * p['rr'], marker='s' if m == BASELINE else 'o')
            ax.annotate(m, (p['ratio'], 100 * p['rr']), fontsize=7, xytext=(4, 2),
                        textcoords='offset points')
        ax.axvline(1.0, color='grey', lw=0.5)
        ax.set_xlabel("median seconds a pair / KISS-Matcher's (same run)")
        ax.set_ylabel('registration recall [%]')
        ax.set_title(b)
    fig.tight_layout()
    save_figure(fig, path)


def main(argv: list[str] | None = None) -> int:
    parser = argument_parser(__spec__.name, __doc__)
    parser.add_argument('records', type=Path, help='records.jsonl of bench.threedmatch')
    parser.add_argument('--output', type=Path, default=Path('out/curve/recall_time'))
    args = parser.parse_args(argv)
    records = load(args.records)
    if not any(r['method'] == BASELINE for r in records):
        parser.error(f'the records hold no {BASELINE} run to compare times with')
    text = report(records)
    print(text)
    write_text(args.output.with_suffix('.md'), text + '\n')
    plot(records, args.output.with_suffix('.png'))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
