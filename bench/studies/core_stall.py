r"""
When the core's best consensus is found, and what a stop on a stalled search would keep.

Run by hand from the repository root (about ten minutes for every pair of both lists)::

    .venv/bin/python -m bench.studies.core_stall [--pairs K] [--seed 0] \
        [--output out/bench/core_stall.jsonl]

On a pair whose best consensus does not stand out from chance, the core draws to its cap
(``core.max_iterations``): most of a refused 3DLoMatch pair's time. A cap cuts the late
successes (a right consensus found after many draws); a stop on a stalled search (no
better consensus in the last S draws) would keep a search going while it still improves.
This study runs the pipeline on every pair (or ``--pairs K`` a scene and list) with its
defaults, records every improvement of the core's best consensus (the draw it came at, its
inliers, whether its pose is within the benchmark's 15 deg / 30 cm of the truth) and the
pair's outcome, then replays both rules on the records: for a cap C and a stall S, the
search would have ended at draw ``min(C, ...)`` or at the first draw S after an
improvement with none since. A pair is *unchanged* when the rule ends the search after its
last improvement (the core's result, and so the pipeline's, is the same); otherwise the
best consensus at the stop is what the core would have returned, right or not (what the
stages after it make of it is not replayed: ``bench.threedmatch --variant`` measures that).
The draws saved are the share of all the core's draws.
"""

from __future__ import annotations

import json
from pathlib import Path

from bench.common import argument_parser, markdown_table
from bench.datasets import threedmatch as tdm
from bench.threedmatch import select_pairs
from cgags_ros.config import PipelineConfig
from cgags_ros.io.shared_data import shared_data_dir
from cgags_ros.pipeline import clear_feature_cache, register_clouds
from cgags_ros.registration import search
import numpy as np

CAPS = (10_000, 20_000, 40_000)
STALLS = (5_000, 10_000, 20_000, 40_000)


class _Recorder:
    """Patch :class:`search.Search` to note each improvement of a call's first search."""

    def __init__(self):
        self.history: list[tuple[int, int, np.ndarray]] = []
        self.searches = 0
        self._init, self._evaluate = search.Search.__init__, search.Search.evaluate

    def __enter__(self):
        recorder, init, evaluate = self, self._init, self._evaluate

        def counted(s, *args, **kwargs):
            init(s, *args, **kwargs)
            recorder.searches += 1
            s.noted = recorder.searches == 1  # the estimate's search, not the candidates'

        def noted(s, subsets, support=None):
            improved = evaluate(s, subsets, support)
            if improved and s.noted:
                recorder.history.append((s.num_drawn, len(s.best_inliers), s.best_T.copy()))
            return improved

        search.Search.__init__, search.Search.evaluate = counted, noted
        return self

    def __exit__(self, *exc):
        search.Search.__init__, search.Search.evaluate = self._init, self._evaluate


def measure_pair(src: np.ndarray, tgt: np.ndarray, truth: np.ndarray,
                 cfg: PipelineConfig) -> dict:
    """Return one pair's outcome and its core's improvements (draw, inliers, right)."""
    with _Recorder() as rec:
        clear_feature_cache()
        result = register_clouds(src, tgt, config=cfg)
    return {'valid': result.valid, 'right': tdm.registered(result.transform, truth),
            'draws': int(result.stats.get('compatible_samples', 0)
                         + result.stats.get('guided_samples', 0)),
            'core_s': result.timings.get('core_total', 0.0),
            'seconds': result.timings['total'],
            'improvements': [(d, n, tdm.registered(T, truth)) for d, n, T in rec.history]}


def stop_at(row: dict, cap: int | None = None, stall: int | None = None) -> int:
    """Return the draw at which the rule would have ended the row's search."""
    end = row['draws'] if cap is None else min(row['draws'], cap)
    if stall is not None:
        last = 0
        for d, _, _ in row['improvements']:
            if d - last >= stall and last + stall < end:
                return last + stall
            last = d
        end = min(end, last + stall)
    return end


def replay(rows: list[dict], cap: int | None = None, stall: int | None = None) -> dict:
    """Return what a rule changes on the rows (see the module doc)."""
    changed = right_lost = right_kept = 0
    saved = 0
    for r in rows:
        stop = stop_at(r, cap, stall)
        saved += r['draws'] - stop
        before = [s for s in r['improvements'] if s[0] <= stop]
        if len(before) == len(r['improvements']):
            continue
        changed += 1
        coarse_right = bool(before) and before[-1][2]
        if r['right']:
            right_kept += coarse_right
            right_lost += not coarse_right
    return {'changed': changed, 'right_changed_kept': right_kept,
            'right_changed_lost': right_lost,
            'draws_saved': saved / max(sum(r['draws'] for r in rows), 1)}


def summary(rows: list[dict]) -> str:
    parts = []
    for benchmark in dict.fromkeys(r['benchmark'] for r in rows):
        mine = [r for r in rows if r['benchmark'] == benchmark]
        right = sum(r['right'] for r in mine)
        table = []
        for label, kw in ([(f'cap {c}', {'cap': c}) for c in CAPS]
                          + [(f'stall {s}', {'stall': s}) for s in STALLS]):
            o = replay(mine, **kw)
            table.append((label, o['changed'], o['right_changed_kept'],
                          o['right_changed_lost'], f"{100 * o['draws_saved']:.0f} %"))
        parts.append(f'### {benchmark}: {len(mine)} pairs, {right} right\n\n' + markdown_table(
            ('rule', 'searches changed', 'right pairs changed, coarse pose still right',
             'right pairs changed, coarse pose wrong', "the core's draws saved"), table))
    return '\n\n'.join(parts)


def main(argv: list[str] | None = None) -> int:
    parser = argument_parser(__spec__.name, __doc__)
    parser.add_argument('--root', type=Path, default=shared_data_dir() / '3dmatch_benchmark')
    parser.add_argument('--pairs', type=int, default=None, help='pairs a scene and list')
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--output', type=Path, default=Path('out/bench/core_stall.jsonl'))
    args = parser.parse_args(argv)
    cfg = PipelineConfig()
    args.output.parent.mkdir(parents=True, exist_ok=True)
    rows = []
    with open(args.output, 'w', encoding='utf-8') as out:
        for benchmark, scene, fragments, pairs in tdm.benchmark_scenes(args.root):
            for p in select_pairs(pairs, args.pairs, args.seed):
                row = measure_pair(fragments[p.source], fragments[p.target],
                                   tdm.nearest_rigid(p.transform), cfg)
                row.update(benchmark=benchmark, scene=scene, key=p.key)
                out.write(json.dumps(row) + '\n')
                out.flush()
                rows.append(row)
    print(summary(rows))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
