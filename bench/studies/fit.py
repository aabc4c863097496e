r"""
The numbers of :mod:`cgags_ros.fitted` as the trust study fits them from a record.

Run from the repository root (offline: it registers nothing)::

    .venv/bin/python -m bench.studies.fit [--record bench/studies/records/trust.jsonl.gz] [--check]
    .venv/bin/python -m bench.studies.fit --gates out/loso_trust/gates.jsonl \
        [--records RECORDS] [--root <shared data>/3dmatch_benchmark] [--write-record FILE]
    .venv/bin/python -m bench.studies.fit --benchmark out/no_overlap/benchmark.jsonl \
        [--write-refusals FILE]

It prints every number of :mod:`cgags_ros.fitted` as that module writes it, fit by the
studies' own code:

- the confidence, the twins and the gates' ``min_confidence`` and ``max_position_sigma``:
  :func:`.trust_shift.shipped` on gates-only records;
- the covariance: :func:`.loso_trust_study.shipped_covariance` and
  :func:`.loso_trust_study.shipped_doubt` on the same records (``--records``: others);
- the refused estimates' confidence: :func:`refused_right` on the refusals record
  (``--refusals``), the benchmark's pairs registered with the defaults
  (``bench.no_overlap benchmark``); ``--benchmark`` reads such a run instead and
  ``--write-refusals FILE`` writes its pairs of the trust record as a refusals record.

``--record`` (the default) reads the committed record: the gates-only records of every pair
whose truth is not in doubt, trimmed to what the fit reads. ``--gates`` reads a full
``measure --gates-only`` output instead, leaves out the pairs whose truth is in doubt
(:func:`.trust_shift.trusted`, which reads the benchmark's poses under ``--root``), and
``--write-record FILE`` writes what is left as a record. It measures nothing: a missing
file is named with the :mod:`.loso_trust` command that writes it.

A number matches its fit when the fit rounds to it at the significant digits the module
gives it (at least two); it is then printed as the module writes it, the fit's four digits
beside it, and otherwise the fit is printed beside it. ``--check`` exits 1 when a number
differs from its fit. No source file is rewritten.
"""

from __future__ import annotations

from decimal import Decimal
import gzip
import json
import math
from pathlib import Path

from bench.common import argument_parser
from bench.studies import loso_trust_study, trust_shift
from cgags_ros import fitted
from cgags_ros.io.shared_data import shared_data_dir
from cgags_ros.pipeline import confidence
import numpy as np

MEASURE = {
    'gates': 'OMP_NUM_THREADS=1 python -m bench.studies.loso_trust measure --gates-only '
             '--output {path}',
    'records': 'OMP_NUM_THREADS=1 python -m bench.studies.loso_trust measure --output {path}',
    'record': 'python -m bench.studies.fit --gates GATES --write-record {path}',
    'benchmark': 'OMP_NUM_THREADS=1 python -m bench.no_overlap benchmark --output {path}',
    'refusals': 'python -m bench.studies.fit --benchmark BENCHMARK --write-refusals {path}',
}
# Refusals the confidence decides, not the gates: never capped by a share.
DECIDED_BY_CONFIDENCE = ('low_confidence', 'uncertain')
# A kind of refusal has its own share with at least this many of the benchmark's pairs.
MIN_REFUSALS = 10


def literal(value) -> str:
    """Return ``value`` as the module writes it: four significant digits, ``math.pi``, a dict."""
    if isinstance(value, dict):
        return '{' + ', '.join(f'{k!r}: {literal(v)}' for k, v in value.items()) + '}'
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if math.isclose(value, math.pi, rel_tol=1e-9):
        return 'math.pi'
    return repr(float(f'{value:.4g}'))


def same(fit, shipped) -> bool:
    """Tell whether ``fit`` rounds to ``shipped`` at the significant digits the source gives it."""
    if isinstance(shipped, dict):
        return fit.keys() == shipped.keys() and all(same(fit[k], shipped[k]) for k in fit)
    if isinstance(shipped, (int, np.integer)):
        return fit == shipped
    digits = max(2, len(Decimal(repr(float(shipped))).normalize().as_tuple().digits))
    return float(f'{fit:.{digits}g}') == float(shipped)


def refused_right(rows: list[dict]) -> tuple[dict[str, float], float]:
    """
    Return the share of right estimates among each kind of the gates' refusals, and overall.

    ``rows``: the benchmark's pairs registered with the defaults (``refusal``, ``success``).
    Kinds with fewer than :data:`MIN_REFUSALS` pairs have no share of their own; the pooled
    share of every gate refusal stands for them.
    """
    refused = [r for r in rows if r['refusal'] and r['refusal'] not in DECIDED_BY_CONFIDENCE]
    kinds: dict[str, list[bool]] = {}
    for r in refused:
        kinds.setdefault(r['refusal'], []).append(bool(r['success']))
    shares = {k: float(np.mean(v)) for k, v in sorted(kinds.items(), key=lambda kv: -len(kv[1]))
              if len(v) >= MIN_REFUSALS}
    return shares, float(np.mean([bool(r['success']) for r in refused]))


def constants(gates: list[dict], records: list[dict], refusals: list[dict]) -> dict:
    """
    Return ``{block: [(name, fit, shipped)]}`` of every number in :mod:`cgags_ros.fitted`.

    ``gates``: gates-only records whose truth is not in doubt (:func:`.trust_shift.trusted`);
    ``records``: the covariance's (the same unless given); ``refusals``: the refusals
    record's rows (:func:`refused_right`).
    """
    chosen = trust_shift.shipped(gates)
    shares, other = refused_right(refusals)
    limit, rho, apart, promising = chosen['twins']
    valid = np.array([r['valid'] for r in records], dtype=bool)
    g, k, ft, fr = loso_trust_study.shipped_covariance(records, valid)
    wt, wr, gamma, _ = loso_trust_study.shipped_doubt(records, valid)
    weights = chosen['weights']
    unused = {n: w for n, w in weights.items() if n not in confidence.FEATURES and w != 0}
    return {
        'confidence': [
            ('CONFIDENCE_WEIGHTS', {n: weights[n] for n in confidence.FEATURES},
             fitted.CONFIDENCE_WEIGHTS),
            ('CONFIDENCE_INTERCEPT', chosen['intercept'], fitted.CONFIDENCE_INTERCEPT),
            ('MIN_CONFIDENCE', chosen['threshold'], fitted.MIN_CONFIDENCE),
            *[(f'# weight of {n}, not an input of the model', w, 0) for n, w in unused.items()]],
        'twins': [
            ('TWIN_PROMISING', promising, fitted.TWIN_PROMISING),
            ('TWIN_APART', apart, fitted.TWIN_APART),
            ('TWIN_OVERLAP_RATIO', rho, fitted.TWIN_OVERLAP_RATIO),
            ('TWIN_MAX_VIOLATION', limit, fitted.TWIN_MAX_VIOLATION)],
        'covariance': [
            ('COVARIANCE_CELL_FACTOR', int(g), fitted.COVARIANCE_CELL_FACTOR),
            ('COVARIANCE_SCALE', k, fitted.COVARIANCE_SCALE),
            ('COVARIANCE_FLOOR_POSITION', ft, fitted.COVARIANCE_FLOOR_POSITION),
            ('COVARIANCE_FLOOR_ROTATION', fr, fitted.COVARIANCE_FLOOR_ROTATION),
            ('WRONG_POSITION_VOXELS', wt / loso_trust_study.VOXEL, fitted.WRONG_POSITION_VOXELS),
            ('WRONG_ROTATION', wr, fitted.WRONG_ROTATION),
            ('DOUBT_EXPONENT', gamma, fitted.DOUBT_EXPONENT),
            ('MAX_POSITION_SIGMA', chosen['sigma_voxels'], fitted.MAX_POSITION_SIGMA)],
        'refusals': [
            ('REFUSED_RIGHT', shares, fitted.REFUSED_RIGHT),
            ('REFUSED_RIGHT_OTHER', other, fitted.REFUSED_RIGHT_OTHER)],
    }


RECORD = Path(__file__).parent / 'records' / 'trust.jsonl.gz'
REFUSALS = Path(__file__).parent / 'records' / 'refusals.jsonl.gz'
REFUSAL_FIELDS = ('benchmark', 'scene', 'source', 'target', 'success', 'refusal')
# What the fit reads of a record: the pair, its truth and flag, the gates' measures, the
# overlap's information, and the twins a grid value of the study could settle.
FIELDS = ('benchmark', 'scene', 'source', 'target', 'success', 'valid', 'confidence', 'error',
          'covariance', 'fitness', 'overlap', 'inlier_rmse', 'free_space_violation',
          'observability', 'runner_up_ratio', 'num_inliers', 'num_correspondences',
          'num_hypotheses', 'chance_inliers')
OVERLAP = ('axis_rms', 'cells', 'overlap_points', 'plane_info', 'plane_r2')
TWIN = ('fitness', 'free_space_violation', 'from_estimate_deg', 'from_estimate_m',
        'start_fitness')
DIGITS = 6


def _rounded(value):
    if isinstance(value, float):
        return float(f'{value:.{DIGITS}g}')
    if isinstance(value, list):
        return [_rounded(v) for v in value]
    if isinstance(value, dict):
        return {k: _rounded(v) for k, v in value.items()}
    return value


def trimmed(r: dict) -> dict:
    """Return what the fit reads of a record, floats at :data:`DIGITS` significant digits."""
    out = {k: r[k] for k in FIELDS}
    out['doubt'] = list(r.get('doubt', loso_trust_study.EARLIER_DOUBT))
    out['candidates'] = [{'fitness': c['fitness']} for c in r['candidates']]
    if r.get('overlap_info'):
        out['overlap_info'] = {k: r['overlap_info'][k] for k in OVERLAP
                               if k in r['overlap_info']}
    least = min(loso_trust_study.TWIN_GRID['promising']) * (r['fitness'] or 0.0)
    out['twins'] = [{k: x[k] for k in TWIN} for x in loso_trust_study.measured_twins(r)
                    if x['start_fitness'] >= least]
    return _rounded(out)


def read_record(path: Path) -> list[dict]:
    """Return the rows of a record (gzipped JSON lines, as :func:`write_record` writes)."""
    with gzip.open(path, 'rt', encoding='utf-8') as f:
        return [json.loads(line) for line in f]


def write_record(records: list[dict], path: Path) -> None:
    """Write ``records`` trimmed (:func:`trimmed`) as a record."""
    write_rows([trimmed(r) for r in records], path)


def write_rows(rows: list[dict], path: Path) -> None:
    """Write ``rows`` as a record: gzipped JSON lines, as :func:`read_record` reads them."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with gzip.open(path, 'wt', encoding='utf-8', compresslevel=9) as f:
        for r in rows:
            f.write(json.dumps(r, separators=(',', ':')) + '\n')


def benchmark_refusals(run: list[dict], trusted: list[dict]) -> list[dict]:
    """
    Return the refusals record's rows of a ``bench.no_overlap benchmark`` run.

    Only its pairs the trust record holds (``trusted``): those whose benchmark pose is not
    in doubt.
    """
    keys = {(r['benchmark'], r['scene'], r['source'], r['target']) for r in trusted}
    rows = [{'benchmark': r['kind'], 'scene': r['source_scene'], 'source': r['source'],
             'target': r['target'], 'success': bool(r['success']), 'refusal': r['refusal']}
            for r in run]
    return [r for r in rows if (r['benchmark'], r['scene'], r['source'], r['target']) in keys]


def main(argv: list[str] | None = None) -> int:
    p = argument_parser(__spec__.name, __doc__)
    p.add_argument('--record', type=Path, default=RECORD,
                   help='a committed record (default: %(default)s)')
    p.add_argument('--gates', type=Path, default=None,
                   help='a measure --gates-only output instead of --record')
    p.add_argument('--records', type=Path, default=None,
                   help="records for the covariance (default: the fit's own)")
    p.add_argument('--root', type=Path, default=shared_data_dir() / '3dmatch_benchmark',
                   help="the 3DMatch benchmark: its fragments' poses (default: %(default)s)")
    p.add_argument('--write-record', type=Path, default=None,
                   help="write --gates's trusted pairs as a record to this file")
    p.add_argument('--refusals', type=Path, default=REFUSALS,
                   help='the refusals record (default: %(default)s)')
    p.add_argument('--benchmark', type=Path, default=None,
                   help='a bench.no_overlap benchmark run instead of --refusals')
    p.add_argument('--write-refusals', type=Path, default=None,
                   help="write --benchmark's trusted pairs as a refusals record to this file")
    p.add_argument('--check', action='store_true',
                   help='exit 1 when a number differs from its fit')
    args = p.parse_args(argv)
    for path, kind in ((args.gates, 'gates'), (args.records, 'records'),
                       (None if args.gates else args.record, 'record'),
                       (args.benchmark, 'benchmark'),
                       (None if args.benchmark else args.refusals, 'refusals')):
        if path is not None and not path.is_file():
            print(f'missing {path}; it is written by\n    {MEASURE[kind].format(path=path)}')
            return 2
    if args.gates:
        gates = trust_shift.trusted(loso_trust_study.load(args.gates), args.root)[0]
        source = args.gates
    else:
        gates, source = read_record(args.record), args.record
    if args.write_record:
        write_record(gates, args.write_record)
        print(f'# wrote {args.write_record}: {len(gates)} pairs')
    records = loso_trust_study.load(args.records) if args.records else gates
    if args.benchmark:
        run = [json.loads(line) for line in args.benchmark.read_text().splitlines() if line]
        refusals = benchmark_refusals(run, gates)
        if args.write_refusals:
            write_rows(refusals, args.write_refusals)
            print(f'# wrote {args.write_refusals}: {len(refusals)} pairs')
    else:
        refusals = read_record(args.refusals)
    scenes = loso_trust_study.scenes(gates)
    print(f'# read {source}: {len(gates)} pairs whose truth is not in doubt, {len(scenes)} '
          f"scenes ({', '.join(map(loso_trust_study.short, scenes))})")
    differ = []
    for block, numbers in constants(gates, records, refusals).items():
        print(f'\n# {block}')
        for name, fit, shipped in numbers:
            # As the module would hold it: its literal when the fit rounds to it.
            if same(fit, shipped):
                text = literal(shipped) + ('' if literal(fit) == literal(shipped)
                                           else f'  # fit: {literal(fit)}')
            else:
                text = f'{literal(fit)}  # shipped: {literal(shipped)}'
                differ.append(name)
            print(f'{name} = {text}')
    print('\nevery number matches its fit' if not differ else
          '\ndiffering from the fit: ' + ', '.join(differ))
    return 1 if args.check and differ else 0


if __name__ == '__main__':
    raise SystemExit(main())
