r"""
Regenerate the shipped constants the trust studies fit, from their measurement records.

Run from the repository root (offline: it registers nothing)::

    .venv/bin/python -m bench.studies.fit [--gates out/loso_trust/gates.jsonl] \
        [--records RECORDS] [--root <shared data>/3dmatch_benchmark] [--check]

It prints each block of constants as the source holds it, fit by the studies' own code:

- ``cgags_ros/pipeline/confidence.py`` (``WEIGHTS``, ``INTERCEPT``),
  ``cgags_ros/pipeline/twins.py`` (``PROMISING``) and ``cgags_ros/validity/__init__.py``
  (``TWIN_APART``, ``TWIN_MAX_VIOLATION``, ``TWIN_OVERLAP_RATIO``):
  :func:`.trust_shift.shipped` on ``--gates``, the gates-only records, the pairs whose
  truth is in doubt left out (:func:`.trust_shift.trusted`, which reads the benchmark's
  poses under ``--root``);
- ``cgags_ros/pipeline/covariance.py`` (``CELL_FACTOR``, ``SCALE``, ``FLOOR_POSITION``,
  ``FLOOR_ROTATION``, ``WRONG_POSITION``, ``WRONG_ROTATION``, ``DOUBT_EXPONENT``):
  :func:`.loso_trust_study.shipped_covariance` and :func:`.loso_trust_study.shipped_doubt`
  on ``--records``: the ``--gates`` records unless given (records of the defaults,
  ``measure`` without ``--gates-only``, are that study's own).

The gates' options the same fit chooses (``gates.max_position_sigma``,
``gates.min_confidence``) are printed beside their defaults, unchecked. It measures
nothing: a missing record file is named with the :mod:`.loso_trust` command that writes it.
A shipped value matches its fit when the fit rounds to it at the significant digits the
source gives it (at least two); it is then printed as the source holds it, the fit's four
digits beside it, and otherwise the fit is printed beside it. ``--check`` exits 1 when a
shipped constant differs from its fit. No source file is rewritten.
"""

from __future__ import annotations

from decimal import Decimal
import math
from pathlib import Path

from bench.common import argument_parser
from bench.studies import loso_trust_study, trust_shift
from cgags_ros import validity
from cgags_ros.config import GatesConfig
from cgags_ros.io.shared_data import shared_data_dir
from cgags_ros.pipeline import confidence, covariance, twins
import numpy as np

MEASURE = {
    'gates': 'OMP_NUM_THREADS=1 python -m bench.studies.loso_trust measure --gates-only '
             '--output {path}',
    'records': 'OMP_NUM_THREADS=1 python -m bench.studies.loso_trust measure --output {path}',
}


def literal(value) -> str:
    """Return ``value`` as the source writes it: four significant digits, ``np.pi``, a dict."""
    if isinstance(value, dict):
        return '{' + ', '.join(f'{k!r}: {literal(v)}' for k, v in value.items()) + '}'
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if math.isclose(value, math.pi, rel_tol=1e-9):
        return 'np.pi'
    return repr(float(f'{value:.4g}'))


def same(fit, shipped) -> bool:
    """Tell whether ``fit`` rounds to ``shipped`` at the significant digits the source gives it."""
    if isinstance(shipped, dict):
        return fit.keys() == shipped.keys() and all(same(fit[k], shipped[k]) for k in fit)
    if isinstance(shipped, (int, np.integer)):
        return fit == shipped
    digits = max(2, len(Decimal(repr(float(shipped))).normalize().as_tuple().digits))
    return float(f'{fit:.{digits}g}') == float(shipped)


def constants(gates: list[dict], records: list[dict], root: Path) -> dict:
    """Return ``{source file: [(name, fit, shipped)]}`` of every constant the studies fit."""
    chosen = trust_shift.shipped(trust_shift.trusted(gates, root)[0])
    limit, rho, apart, promising = chosen['twins']
    valid = np.array([r['valid'] for r in records], dtype=bool)
    g, k, ft, fr = loso_trust_study.shipped_covariance(records, valid)
    wt, wr, gamma, _ = loso_trust_study.shipped_doubt(records, valid)
    weights = chosen['weights']
    unused = {n: w for n, w in weights.items() if n not in confidence.FEATURES and w != 0}
    gates_defaults = GatesConfig()
    return {
        'cgags_ros/pipeline/confidence.py': [
            ('WEIGHTS', {n: weights[n] for n in confidence.FEATURES}, confidence.WEIGHTS),
            ('INTERCEPT', chosen['intercept'], confidence.INTERCEPT),
            *[(f'# weight of {n}, not an input of the model', w, 0) for n, w in unused.items()]],
        'cgags_ros/pipeline/twins.py': [('PROMISING', promising, twins.PROMISING)],
        'cgags_ros/validity/__init__.py': [
            ('TWIN_APART', apart, validity.TWIN_APART),
            ('TWIN_MAX_VIOLATION', limit, validity.TWIN_MAX_VIOLATION),
            ('TWIN_OVERLAP_RATIO', rho, validity.TWIN_OVERLAP_RATIO)],
        'cgags_ros/pipeline/covariance.py': [
            ('CELL_FACTOR', int(g), covariance.CELL_FACTOR), ('SCALE', k, covariance.SCALE),
            ('FLOOR_POSITION', ft, covariance.FLOOR_POSITION),
            ('FLOOR_ROTATION', fr, covariance.FLOOR_ROTATION),
            ('WRONG_POSITION', wt, covariance.WRONG_POSITION),
            ('WRONG_ROTATION', wr, covariance.WRONG_ROTATION),
            ('DOUBT_EXPONENT', gamma, covariance.DOUBT_EXPONENT)],
        'cgags_ros/config/gates.py (defaults, not checked)': [
            ('max_position_sigma', chosen['sigma_voxels'], gates_defaults.max_position_sigma),
            ('min_confidence', chosen['threshold'], gates_defaults.min_confidence)],
    }


def main(argv: list[str] | None = None) -> int:
    p = argument_parser(__spec__.name, __doc__)
    p.add_argument('--gates', type=Path, default=Path('out/loso_trust/gates.jsonl'),
                   help='gates-only records: the confidence and the twins (default: %(default)s)')
    p.add_argument('--records', type=Path, default=None,
                   help='records for the covariance (default: the --gates records)')
    p.add_argument('--root', type=Path, default=shared_data_dir() / '3dmatch_benchmark',
                   help="the 3DMatch benchmark: its fragments' poses (default: %(default)s)")
    p.add_argument('--check', action='store_true',
                   help='exit 1 when a shipped constant differs from its fit')
    args = p.parse_args(argv)
    args.records = args.records or args.gates
    loaded = {}
    for kind in ('gates', 'records'):
        path = getattr(args, kind)
        if not path.is_file():
            print(f'missing {path}; it is written by\n    {MEASURE[kind].format(path=path)}')
            return 2
        loaded[kind] = loaded['gates'] if path == args.gates and kind == 'records' \
            else loso_trust_study.load(path)
        scenes = loso_trust_study.scenes(loaded[kind])
        print(f'# read {path}: {len(loaded[kind])} pairs, {len(scenes)} scenes '
              f"({', '.join(map(loso_trust_study.short, scenes))})")
    differ = []
    for source, block in constants(loaded['gates'], loaded['records'], args.root).items():
        print(f'\n# {source}')
        for name, fit, shipped in block:
            # As the source would hold it: the shipped literal when the fit rounds to it.
            if same(fit, shipped):
                text = literal(shipped) + ('' if literal(fit) == literal(shipped)
                                           else f'  # fit: {literal(fit)}')
            else:
                text = f'{literal(fit)}  # shipped: {literal(shipped)}'
                differ += [] if 'not checked' in source else [f'{source} {name}']
            print(f"{name}{' = ' if name.isupper() else ': '}{text}")
    print('\nevery shipped constant matches its fit' if not differ else
          '\ndiffering from the fit: ' + ', '.join(differ))
    return 1 if args.check and differ else 0


if __name__ == '__main__':
    raise SystemExit(main())
