r"""
Trust under shift: the valid flag chosen on some scenes and reported on harder unseen ones.

Run by hand from the repository root, after the records (one gates-only run, ~10 min)::

    OMP_NUM_THREADS=1 .venv/bin/python -m bench.studies.loso_trust measure --gates-only \
        --output out/loso_trust/gates.jsonl
    .venv/bin/python -m bench.studies.trust_shift out/loso_trust/gates.jsonl \
        [--output out/trust_shift/study]

Two splits of the four shared 3DMatch scenes, every setting chosen on the training scenes
only and every figure reported on the test scenes:

- ``loso``: each scene held out in turn, chosen on the other three;
- ``hard``: chosen on the two easiest scenes (the highest recall: redkitchen, hotel_uc),
  reported on the two hardest (home_at, mit_lab_hj): a shift like that to an unseen
  building.

Pairs with a fragment whose benchmark pose is in doubt (:mod:`bench.truth_check`) are left
out of every choice and every figure, and counted (``--evidence``: the truths settled by
:mod:`bench.truth_settle` checked too; ``--keep-doubtful``: none left out).

The levers, in the pipeline's order, on top of the gates (the records' ``valid``):

``twins``
    The twins (:mod:`cgags_ros.pipeline.twins`): a valid pose is refused when
    a twin distinct from it fits about as well without stacking surfaces in free space.
    Chosen as in :mod:`.loso_trust_study` (the most wrong poses refused, at most 1 % of the
    right valid ones lost), once with the half turns and slides alone (``twins (flips,
    slides)``) and once with every start (``twins (all)``: quarter turns about the
    normals' axes and the correspondences' other candidates too).
``sigma``
    Valid means usable: the reported covariance's loosest position sigma (the overlap's
    opened by the doubt, :func:`cgags_ros.pipeline.covariance.with_confidence`) at most a
    bound in voxels, the 99th percentile of the right valid poses' on the training scenes.
``confidence``
    P(right) from four monotone inputs (:data:`MONOTONE`), fit on the training scenes'
    estimates; a weight whose sign contradicts its input's meaning is dropped and the rest
    refit. Its threshold is the smallest meeting the valid-but-wrong targets (1 % / 3 %) on
    the training scenes.

Outputs ``--output`` + ``.md`` / ``.json``; the levers chosen on every scene (what ships)
come last, and ``python -m bench.studies.fit`` prints them as the source holds them.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any

from bench.common import argument_parser, markdown_table
from bench.studies.loso_trust_study import (as_result, CHI2_95, CHI2_999, fit_logistic,
                                            fit_twins, flag_counts, load, measured_twins,
                                            MIN_ROTATION_DEG, overlap_covariance, predict,
                                            reliability, short, SIGNIFICANCE, threshold_for,
                                            twin_refuses, VOXEL)
from bench.truth_check import doubtful_fragments, in_doubt, read_records as truth_records
from cgags_ros import validity
from cgags_ros.io.shared_data import shared_data_dir
from cgags_ros.pipeline import confidence, covariance, twins
import numpy as np

EASY = ('7-scenes-redkitchen', 'sun3d-hotel_uc-scan3')
HARD_SPLIT = 'hard'
# Each input with the sign its weight must have: the pipeline's (more margin over chance is
# more trust, a looser overlap and more free-space violation are less) and a better-fitting
# alternative (less), which the fits leave out when its sign contradicts that.
MONOTONE = {**confidence.SIGNS, 'alternative_fit': -1.0}
FLIPS_SLIDES = ('flip', 'slide')
TODAY_TWINS = (0.1, 1.5, 4.0, 0.45)  # (L, rho, apart, promising) as shipped before
FLOOR = 0.5
SHARP = 0.99  # the share of right valid training poses the sigma bound keeps


def splits(records: list[dict]) -> list[tuple[str, str, np.ndarray, np.ndarray]]:
    """Return (split, test name, train mask, test mask) of every fold of both splits."""
    scene = np.array([r['scene'] for r in records])
    out = [('loso', short(s), scene != s, scene == s) for s in sorted(set(scene))]
    easy = np.isin(scene, EASY)
    out.append((HARD_SPLIT, '+'.join(short(s) for s in sorted(set(scene[~easy]))), easy,
                ~easy))
    return out


def alternative_fit(r: dict) -> float:
    """
    Return the best fit of a distinct alternative over the estimate's fit (0: none).

    The correspondences' other candidates, and the twins the pipeline settles (a start at
    least ``fitted.TWIN_PROMISING`` times the estimate's fit) that settle away from the estimate.
    """
    fitness = r['fitness'] or 0.0
    fits = [c['fitness'] for c in r['candidates'][1:] if c['fitness'] is not None]
    fits += [x['fitness'] for x in measured_twins(r)
             if twins.worth_refining(x['start_fitness'], fitness)
             and validity.settled_apart(x['from_estimate_deg'], x['from_estimate_m'], VOXEL,
                                        MIN_ROTATION_DEG)]
    return max(fits, default=0.0) / max(fitness, 1e-3)


def inputs(r: dict) -> dict[str, float] | None:
    """Return the candidate confidence inputs of a record (None without an estimate)."""
    values = confidence.features(as_result(r), SIGNIFICANCE)
    return None if values is None else {**values, 'alternative_fit': alternative_fit(r)}


def fit_monotone(X: np.ndarray, y: np.ndarray, names: list[str]) -> dict:
    """Return a logistic fit whose weights all have :data:`MONOTONE`'s signs (others 0)."""
    use = list(range(len(names)))
    while True:
        model = fit_logistic(X[:, use], y)
        bad = [i for i, w in zip(use, model['weights']) if w * MONOTONE[names[i]] < 0]
        if not bad:
            weights = np.zeros(len(names))
            weights[use] = model['weights']
            return {'weights': weights.tolist(), 'intercept': model['intercept']}
        use = [i for i in use if i not in bad]


def reported_sigma(r: dict, p: float) -> float:
    """Return the loosest position sigma of the covariance reported at confidence ``p``."""
    return covariance.loosest_sigma(covariance.with_confidence(overlap_covariance(r), p, VOXEL))


def covariance_figures(records: list[dict], p: np.ndarray, valid: np.ndarray) -> dict:
    """Return the reported covariance's NEES of the valid poses, right and wrong, and sigmas."""
    out = {'nees_right': [], 'nees_wrong': [], 'sigma_voxels': []}
    for r, q, v in zip(records, p, valid):
        if not v:
            continue
        S = covariance.with_confidence(overlap_covariance(r), q, VOXEL)
        e = np.asarray(r['error'])
        out['nees_right' if r['success'] else 'nees_wrong'].append(
            float(e @ np.linalg.solve(S, e)))
        out['sigma_voxels'].append(float(np.sqrt(np.trace(S[:3, :3]))) / VOXEL)
    return out


def fit_confidence(X: np.ndarray, has: np.ndarray, right: np.ndarray, scene: np.ndarray,
                   train: np.ndarray, names: list[str]) -> tuple[dict, np.ndarray]:
    """
    Return the confidence fit on ``train`` and each training scene's held-out probabilities.

    The monotone model (:func:`fit_monotone`) on every training estimate; then its logits
    rescaled (``a z + b``, one logistic fit) to the probabilities each training scene gets
    from a model fit on the other ones: how sure it may be on a scene it has not seen, not
    on the scenes it was fit on. The held-out probabilities (rescaled alike) are what the
    sigma bound and the threshold are chosen on.
    """
    model = fit_monotone(X[train & has], right[train & has].astype(float), names)
    z = np.zeros(len(X))
    for held in sorted(set(scene[train])):
        fit = train & has & (scene != held)
        inner = fit_monotone(X[fit], right[fit].astype(float), names)
        m = has & (scene == held)
        z[m] = X[m] @ np.asarray(inner['weights']) + inner['intercept']
    sel = train & has
    scale = fit_logistic(z[sel][:, None], right[sel].astype(float), c=1e6)
    a, b = scale['weights'][0], scale['intercept']
    calibrated = {'weights': (a * np.asarray(model['weights'])).tolist(),
                  'intercept': a * model['intercept'] + b}
    return calibrated, np.where(has, 1.0 / (1.0 + np.exp(-(a * z + b))), 0.0)


def sigmas(records: list[dict], p: np.ndarray, has: np.ndarray) -> np.ndarray:
    """Return each record's reported loosest sigma at confidence ``p``, in voxels."""
    return np.array([reported_sigma(r, q) if h else math.inf
                     for r, q, h in zip(records, p, has)]) / VOXEL


@dataclasses.dataclass
class Design:
    """Every record's candidate confidence inputs, its truth, the gates' verdict, list, scene."""

    X: np.ndarray
    has: np.ndarray
    right: np.ndarray
    gates: np.ndarray
    bench: np.ndarray
    scene: np.ndarray

    @classmethod
    def of(cls, records: list[dict]) -> 'Design':
        rows = [inputs(r) for r in records]
        return cls(np.array([[x[n] for n in MONOTONE] if x else [0.0] * len(MONOTONE)
                             for x in rows]),
                   np.array([x is not None for x in rows]),
                   np.array([r['success'] for r in records], dtype=bool),
                   np.array([r['valid'] for r in records], dtype=bool),
                   np.array([r['benchmark'] for r in records]),
                   np.array([r['scene'] for r in records]))


def choose(records: list[dict], d: Design, train: np.ndarray) -> dict:
    """Return every lever chosen on the ``train`` records, in the pipeline's order."""
    limits = fit_twins([r for r, t in zip(records, train) if t], d.gates[train])
    refused = np.array([g and twin_refuses(r, *limits) for r, g in zip(records, d.gates)],
                       dtype=bool)
    model, p_inner = fit_confidence(d.X, d.has, d.right, d.scene, train, list(MONOTONE))
    inner_sigma = sigmas(records, p_inner, d.has)
    after = d.gates & ~refused
    kept = inner_sigma[train & after & d.right]
    bound = float(np.quantile(kept, SHARP)) if len(kept) else math.inf
    threshold = threshold_for(p_inner[train], (after & (inner_sigma <= bound))[train],
                              d.right[train], d.bench[train])
    return {'twins': limits, 'refused': refused, 'model': model, 'sigma_voxels': bound,
            'threshold': max(threshold, FLOOR)}


def fold_flags(records: list[dict], d: Design, train: np.ndarray) -> dict:
    """
    Return the levers chosen on ``train`` and every record's flag after each of them.

    ``p`` the fold's confidence, ``sigma`` the reported loosest sigma in voxels at it;
    ``after_twins``, ``usable`` (within the sigma bound too) and ``valid`` (the threshold
    too: the flag as the fold chose it).
    """
    chosen = choose(records, d, train)
    p = np.where(d.has, predict(chosen['model'], d.X), 0.0)
    sigma = sigmas(records, p, d.has)
    after_twins = d.gates & ~chosen['refused']
    usable = after_twins & (sigma <= chosen['sigma_voxels'])
    return {'chosen': chosen, 'p': p, 'sigma': sigma, 'after_twins': after_twins,
            'usable': usable, 'valid': usable & (p >= chosen['threshold'])}


def study(records: list[dict]) -> dict:
    """Choose every lever on each fold's training scenes; return the test figures."""
    d = Design.of(records)
    flips = [{**r, 'twins': [x for x in measured_twins(r)
                             if x['name'].startswith(FLIPS_SLIDES)]} for r in records]
    # Today's flag as it shipped: half turns and slides at their settings, its confidence
    # (fit on all four scenes, the test scenes too) at 0.5, as the records measured it.
    today = d.gates & np.array([not twin_refuses(r, *TODAY_TWINS) and r['confidence'] >= 0.5
                                for r in flips])
    out = {}
    for split, name, train, test in splits(records):
        fold = out.setdefault(split, {}).setdefault(name, {})
        f = fold_flags(records, d, train)
        chosen, p = f['chosen'], f['p']
        twin_flips = fit_twins([r for r, t in zip(flips, train) if t], d.gates[train])
        refuse_flips = np.array([g and twin_refuses(r, *twin_flips)
                                 for r, g in zip(flips, d.gates)], dtype=bool)
        flags = {'today (shipped before)': today, 'gates': d.gates,
                 'twins (flips, slides)': d.gates & ~refuse_flips,
                 'twins (all)': f['after_twins'], '+ sigma': f['usable'],
                 '+ confidence': f['valid']}
        fold['settings'] = {**{k: v for k, v in chosen.items() if k != 'refused'},
                            'twins_flips': twin_flips}
        for b in ('3DMatch', '3DLoMatch'):
            m = test & (d.bench == b)
            t = [r for r, x in zip(records, m) if x]
            fold[b] = {k: flag_counts(t, v[m]) for k, v in flags.items()}
            fold[b]['covariance'] = covariance_figures(t, p[m], flags['+ confidence'][m])
        fold['p'] = p[test & d.has].tolist()
        fold['right'] = d.right[test & d.has].tolist()
    return out


def totals(folds: dict, lever: str, b: str) -> dict:
    keys = ('right', 'valid', 'right_valid', 'wrong_valid')
    return {k: sum(f[b][lever][k] for f in folds.values()) for k in keys}


def report(out: dict, excluded: dict) -> str:
    parts = [f"Pairs in doubt, left out (either list): {excluded['pairs']} "
             f"({', '.join(f'{k}: {v}' for k, v in excluded['fragments'].items()) or 'none'})"]
    for split, folds in out.items():
        rows = []
        levers = list(next(iter(folds.values()))['3DMatch'])
        levers.remove('covariance')
        for lever in levers:
            for b in ('3DMatch', '3DLoMatch'):
                cells = [f"{100 * f[b][lever]['keeps']:.1f} / {f[b][lever]['wrong_valid']} of "
                         f"{f[b][lever]['valid']}" for f in folds.values()]
                t = totals(folds, lever, b)
                cells.append(f"{100 * t['right_valid'] / max(t['right'], 1):.1f} / "
                             f"{t['wrong_valid']} of {t['valid']} "
                             f"({100 * t['wrong_valid'] / max(t['valid'], 1):.2f} %)")
                rows.append((lever, b, *cells))
        parts.append(f'### {split}: keeps [%] / valid but wrong (test scenes)\n\n'
                     + markdown_table(('flag', 'list', *folds, 'all'), rows))
        for b in ('3DMatch', '3DLoMatch'):
            c = {k: sum((f[b]['covariance'][k] for f in folds.values()), [])
                 for k in ('nees_right', 'nees_wrong', 'sigma_voxels')}
            right_nees = np.asarray(c['nees_right'])
            parts.append(
                f'{b} covariance of the valid poses: {100 * np.mean(right_nees <= CHI2_95):.1f} %'
                f' of the right ones inside their 95 % ellipsoid (median NEES '
                f'{np.median(right_nees):.2f}); confidently wrong (valid, wrong, NEES > 22.5) '
                f"{sum(d > CHI2_999 for d in c['nees_wrong'])} of {len(c['sigma_voxels'])}; "
                f"median position sigma {np.median(c['sigma_voxels']):.2f} voxels")
        p = np.concatenate([f['p'] for f in folds.values()])
        right = np.concatenate([f['right'] for f in folds.values()]).astype(bool)
        top = p >= 0.9
        parts.append(f'confidence >= 0.9: {int(top.sum())} estimates, '
                     f'{100 * right[top].mean():.1f} % right' if top.any() else
                     'confidence >= 0.9: none')
        parts.append(markdown_table(('bin', 'estimates', 'mean P', 'right share'),
                                    reliability(p, right)))
        parts.append('settings: ' + json.dumps(
            {k: {s: v for s, v in f['settings'].items() if s != 'model'}
             for k, f in folds.items()}))
    return '\n\n'.join(parts)


def shipped(records: list[dict]) -> dict:
    """Return every lever chosen on all scenes as the folds choose them (what ships)."""
    chosen = choose(records, Design.of(records), np.ones(len(records), dtype=bool))
    model = chosen.pop('model')
    del chosen['refused']
    return {'weights': dict(zip(MONOTONE, model['weights'])), 'intercept': model['intercept'],
            **chosen}


def trusted(records: list[dict], root: Path,
            evidence: list[dict] | None = None) -> tuple[list[dict], dict]:
    """
    Return the records whose truth is not in doubt, and what was left out.

    ``evidence``: more records for the truth check (:mod:`bench.truth_settle`'s).
    """
    doubtful = doubtful_fragments(records, root, evidence or ())
    kept = [r for r in records if not in_doubt(r, doubtful)]
    return kept, {'pairs': len(records) - len(kept),
                  'fragments': {short(s): [f.fragment for f in fs]
                                for s, fs in doubtful.items() if fs}}


def read_records(name: str, doc: str | None, output: str,
                 argv: list[str] | None) -> tuple[Any, list[dict], dict]:
    """Parse a study's command line (records, --root, --output); return its trusted records."""
    parser = argument_parser(name, doc)
    parser.add_argument('records', type=Path, nargs='?',
                        default=Path('out/loso_trust/gates.jsonl'))
    parser.add_argument('--root', type=Path, default=shared_data_dir() / '3dmatch_benchmark')
    parser.add_argument('--output', type=Path, default=Path(output))
    parser.add_argument('--evidence', type=Path, nargs='*', default=[],
                        help="more evidence for the truth check (bench.truth_settle's records)")
    parser.add_argument('--keep-doubtful', action='store_true',
                        help='leave no pair out: every figure with the pairs in doubt too')
    args = parser.parse_args(argv)
    records = load(args.records)
    if args.keep_doubtful:
        return args, records, {'pairs': 0, 'fragments': {}}
    return (args, *trusted(records, args.root, truth_records(args.evidence)))


def main(argv: list[str] | None = None) -> int:
    args, kept, excluded = read_records(__spec__.name, __doc__, 'out/trust_shift/study', argv)
    out = study(kept)
    text = report(out, excluded) + '\n\n### Fit on all scenes (ships)\n\n' + json.dumps(
        shipped(kept), indent=1)
    print(text)
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.with_suffix('.md').write_text(text + '\n', encoding='utf-8')
    summary = {split: {name: {k: v for k, v in fold.items() if k not in ('p', 'right')}
                       for name, fold in folds.items()} for split, folds in out.items()}
    args.output.with_suffix('.json').write_text(json.dumps(
        {'excluded': excluded, 'splits': summary}, indent=1, default=str), encoding='utf-8')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
