r"""
Where the valid flag's held-out misses come from.

The wrong poses it lets through, the operating points it could take instead, and the right
poses the ambiguity refuses.

Run by hand from the repository root, on the records of one gates-only run (seconds)::

    .venv/bin/python -m bench.studies.trust_limits out/loso_trust/gates.jsonl \
        [--output out/trust_shift/limits]    # writes <output>.md

Every figure is of the test scenes of :mod:`.trust_shift`'s splits, each fold's levers
chosen on its training scenes as that study chooses them; pairs whose truth is in doubt are
left out. It prints:

- each valid but wrong 3DLoMatch pose of the hard split, with what the flag saw of it (its
  errors, confidence, loosest sigma in voxels, inliers over the chance bound);
- the operating points a stricter flag would take, in both splits: a lower bound on the
  loosest sigma, or a higher confidence threshold, than the fold chose, and what each keeps
  and lets through;
- the right 3DLoMatch poses refused as ambiguous: how the best plausible candidate's overlap
  (its refined fitness) compares with the estimate's. Where a right pose's candidate overlaps
  as well or better, no rule on the overlap can keep it without keeping the wrong poses
  refused the same way.
"""

from __future__ import annotations

from bench.common import markdown_table
from bench.studies.trust_shift import Design, fold_flags, read_records, splits
from cgags_ros.config.gates import GatesConfig
import numpy as np

SIGMA_BOUNDS = (8.0, 10.0, 12.0, 15.0, 20.0)  # voxels, below the folds' 23-34
THRESHOLDS = (0.7, 0.8, 0.85, 0.9, 0.95)  # above the folds' 0.5
OVERLAP_RATIOS = (1.0, 1.1, 1.2, 1.3)
RATIO = GatesConfig().ambiguity_ratio  # the candidates the gate settles (settle_candidates)


def counts(d: Design, mask: np.ndarray, flag: np.ndarray) -> str:
    valid = mask & flag
    wrong = int((valid & ~d.right).sum())
    return (f'{100 * (valid & d.right).sum() / max((mask & d.right).sum(), 1):.1f} / '
            f'{wrong} of {int(valid.sum())} ({100 * wrong / max(valid.sum(), 1):.2f} %)')


def operating_points(records: list[dict], d: Design) -> str:
    """Return keeps / valid but wrong of each split at stricter sigma bounds and thresholds."""
    rows = []
    for split in ('loso', 'hard'):
        folds = [(train, test, fold_flags(records, d, train))
                 for s, _, train, test in splits(records) if s == split]

        def row(name: str, flag_of) -> tuple:
            cells = []
            for b in ('3DMatch', '3DLoMatch'):
                mask = np.zeros(len(records), dtype=bool)
                flag = np.zeros(len(records), dtype=bool)
                for _, test, f in folds:
                    m = test & (d.bench == b)
                    mask |= m
                    flag |= m & flag_of(f)
                cells.append(counts(d, mask, flag))
            return (split, name, *cells)

        rows.append(row('as chosen', lambda f: f['valid']))
        for bound in SIGMA_BOUNDS:
            rows.append(row(f'sigma <= {bound:g} voxels',
                            lambda f, b=bound: f['valid'] & (f['sigma'] <= b)))
        for t in THRESHOLDS:
            rows.append(row(f'confidence >= {t:g}', lambda f, t=t: f['valid'] & (f['p'] >= t)))
    return markdown_table(('split', 'flag', '3DMatch keeps / VW', '3DLoMatch keeps / VW'), rows)


def wrong_valid(records: list[dict], d: Design) -> str:
    """Return the valid but wrong 3DLoMatch poses of the hard split's test scenes."""
    rows = []
    for split, _, train, test in splits(records):
        if split != 'hard':
            continue
        f = fold_flags(records, d, train)
        for i in np.flatnonzero(test & f['valid'] & ~d.right & (d.bench == '3DLoMatch')):
            r = records[i]
            rows.append((r['scene'].split('-')[1], f"{r['target']}-{r['source']}",
                         f"{r['re_deg']:.1f}", f"{r['te_m']:.2f}", f"{f['p'][i]:.3f}",
                         f"{f['sigma'][i]:.1f}",
                         f"{r['num_inliers'] / max(r['chance_bound'], 1):.2f}"))
    return markdown_table(('scene', 'pair', 'RE deg', 'TE m', 'confidence', 'sigma voxels',
                           'inliers / chance bound'), rows)


def ambiguity(records: list[dict]) -> str:
    """Return the 3DLoMatch estimates refused as ambiguous, by their candidate's overlap."""
    ratios: dict[bool, list[float]] = {True: [], False: []}
    for r in records:
        if r['benchmark'] != '3DLoMatch' or r.get('refusal') != 'ambiguous':
            continue
        best, *others = r.get('candidates') or [None]
        close = [c for c in others if best and c.get('fitness')
                 and c['num_inliers'] * RATIO > best['num_inliers']]
        if close:
            top = max(c['fitness'] for c in close)
            ratios[bool(r['success'])].append(r['overlap'] / top)
    rows = [(f'>= {q:g}', sum(x >= q for x in ratios[True]), sum(x >= q for x in ratios[False]))
            for q in OVERLAP_RATIOS]
    return (f'refused as ambiguous with a refined candidate: {len(ratios[True])} right, '
            f'{len(ratios[False])} wrong\n\n'
            + markdown_table(("estimate's overlap / candidate's", 'right', 'wrong'), rows))


def main(argv: list[str] | None = None) -> int:
    args, records, excluded = read_records(__spec__.name, __doc__, 'out/trust_shift/limits',
                                           argv)
    d = Design.of(records)
    text = '\n\n'.join([
        f"Pairs in doubt, left out: {excluded['pairs']}",
        '### Valid but wrong, hard split, 3DLoMatch\n\n' + wrong_valid(records, d),
        '### Stricter operating points (keeps % / valid but wrong)\n\n'
        + operating_points(records, d),
        '### Refused as ambiguous, 3DLoMatch\n\n' + ambiguity(records)])
    print(text)
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.with_suffix('.md').write_text(text + '\n', encoding='utf-8')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
