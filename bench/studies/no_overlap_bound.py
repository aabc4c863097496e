r"""
The shared-surface bound, chosen on some scenes and reported on the others.

Run by hand on the records of :mod:`bench.no_overlap` (cross-scene pairs and the benchmark's
pairs, the shared-surface gate off)::

    .venv/bin/python -m bench.studies.no_overlap_bound out/no_overlap/cross.jsonl \
        out/no_overlap/benchmark.jsonl [--measure shared_points] [--keep 0.99]

The bound is a quantile of the measure over the right, valid poses of the training scenes'
3DLoMatch pairs (those of low overlap, which a shared-surface bound threatens): the value
below which ``1 - --keep`` of them lie, so that it costs about that share of them (and
fewer on 3DMatch) and needs no cross-scene pair to be chosen.
Two splits: leave one scene out (each scene's pairs, and every cross-scene pair with one
fragment of it, judged by the bound of the other three), and the hard split (chosen on the
two easiest scenes, redkitchen and hotel_uc; judged on the two hardest, home_at and mit_lab,
and on every cross-scene pair with a fragment of either). Printed: each bound, and on the
held-out pairs the accepted cross-scene pairs and, per list, recall, valid but wrong and
keeps before and after the gate; then the bound on every scene (the one that ships).
"""

from __future__ import annotations

from bench.common import argument_parser
from bench.no_overlap import read_records
import numpy as np

EASY = ('7-scenes-redkitchen', 'sun3d-hotel_uc-scan3')


def value(rec: dict, measure: str) -> float:
    """Return ``rec``'s measure, negated for ``NAME:max`` (NaN when not measured: passes)."""
    name, _, side = measure.partition(':')
    x = rec.get(name)
    x = float('nan') if x is None else float(x)
    return -x if side == 'max' else x


def choose(benchmark: list[dict], measures: list[str], keep: float) -> list[float]:
    """Return, per measure, the ``1 - keep`` quantile over the right valid 3DLoMatch poses."""
    out = []
    for m in measures:
        xs = [value(r, m) for r in benchmark
              if r['kind'] == '3DLoMatch' and r['valid'] and r['success']]
        xs = [x for x in xs if np.isfinite(x)]
        out.append(float(np.quantile(xs, 1.0 - keep)) if xs else float('nan'))
    return out


def refused(rec: dict, measure: list[str], bound: list[float]) -> bool:
    """Tell whether the gate refuses ``rec``'s estimate (any measure below its bound)."""
    return any(value(rec, m) < b for m, b in zip(measure, bound))


def said(measures: list[str], bounds: list[float]) -> str:
    """Return the gate as text: ``NAME >= bound`` (``NAME <= bound`` for ``NAME:max``)."""
    return ' and '.join(f'{m[:-4]} <= {-b:.4g}' if m.endswith(':max') else f'{m} >= {b:.4g}'
                        for m, b in zip(measures, bounds))


def report(cross: list[dict], benchmark: list[dict], measure: list[str],
           bound: list[float]) -> str:
    """Return the held-out pairs' numbers before and after a gate at ``bound``."""
    accepted = [r for r in cross if r['valid']]
    after = [r for r in accepted if not refused(r, measure, bound)]
    parts = [f'cross-scene accepted {len(accepted)} -> {len(after)} of {len(cross)}']
    for kind in ('3DMatch', '3DLoMatch'):
        recs = [r for r in benchmark if r['kind'] == kind]
        if not recs:
            continue
        right = sum(r['success'] for r in recs)
        rows = []
        for gate in (False, True):
            valid = [r for r in recs if r['valid']
                     and not (gate and refused(r, measure, bound))]
            wrong = sum(not r['success'] for r in valid)
            kept = sum(r['success'] for r in valid)
            rows.append(f'valid but wrong {wrong} of {len(valid)}, keeps '
                        f'{100 * kept / max(right, 1):.1f} %')
        parts.append(f'{kind} ({len(recs)} pairs, recall {100 * right / len(recs):.1f} %): '
                     + ' -> '.join(rows))
    return '; '.join(parts)


def main(argv: list[str] | None = None) -> None:
    parser = argument_parser('bench.studies.no_overlap_bound', __doc__)
    parser.add_argument('cross')
    parser.add_argument('benchmark')
    parser.add_argument('--measure', action='append', default=None,
                        help='repeatable (refused when any is out of bounds); NAME:max '
                        'bounds it from above (default shared_points)')
    parser.add_argument('--keep', type=float, default=0.99)
    args = parser.parse_args(argv)
    args.measure = args.measure or ['shared_points']
    cross = read_records([args.cross])
    bench = read_records([args.benchmark])
    scenes = sorted({r['source_scene'] for r in bench})
    splits = [(f'leave out {s}', [t for t in scenes if t != s], [s]) for s in scenes]
    splits.append(('hard split', list(EASY), [s for s in scenes if s not in EASY]))
    for name, train, test in splits:
        bound = choose([r for r in bench if r['source_scene'] in train], args.measure,
                       args.keep)
        held_cross = [r for r in cross
                      if r['source_scene'] in test or r['target_scene'] in test]
        held = [r for r in bench if r['source_scene'] in test]
        print(f'{name}: {said(args.measure, bound)}: '
              + report(held_cross, held, args.measure, bound))
    bound = choose(bench, args.measure, args.keep)
    print(f'every scene: {said(args.measure, bound)}: '
          + report(cross, bench, args.measure, bound))


if __name__ == '__main__':
    main()
