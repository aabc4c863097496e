r"""
Replay the valid flag over ``bench.threedmatch`` records with extra gates, without re-running.

Run by hand::

    .venv/bin/python -m bench.studies.gate_study out/bench/threedmatch_run/records.jsonl \
        [--gate 'free_space_violation <= 0.25'] [--gate 'overlap >= 0.1'] [--method cgags]

Each ``--gate FIELD OP VALUE`` (OP one of ``<= < >= >``; FIELD a number the records hold for
our method: ``overlap``, ``fitness``, ``inlier_rmse``, ``observability``, ``chance_inliers``,
``num_inliers``, ``runner_up_ratio``, ``free_space_violation``, ...) must hold, on top of
the recorded flag, for an estimate to count as valid; a record without the field fails the
gate. Prints, per list, before and after: RR (unchanged: the estimates are the recorded
ones), valid, valid but wrong (count and share of valid) and valid keeps (right and valid /
right), overall and per scene. Gates that would change the estimate (a different candidate
chosen) need a new run of ``python -m bench.threedmatch``.
"""

from __future__ import annotations

import argparse
import json
import operator
from pathlib import Path

from bench.common import argument_parser, markdown_table

OPS = {'<=': operator.le, '<': operator.lt, '>=': operator.ge, '>': operator.gt}


def parse_gate(text: str):
    """Return (field, op, value) of ``'FIELD OP VALUE'``."""
    for op in ('<=', '>=', '<', '>'):
        if op in text:
            field, value = text.split(op, 1)
            return field.strip(), OPS[op], float(value)
    raise argparse.ArgumentTypeError(f'not FIELD OP VALUE with OP in {list(OPS)}: {text!r}')


def passes(record: dict, gates: list) -> bool:
    """Tell whether ``record`` is recorded valid and passes every extra gate."""
    if not record['valid']:
        return False
    for field, op, value in gates:
        x = record.get(field)
        if x is None or not op(float(x), value):
            return False
    return True


def flag_summary(records: list[dict], gates: list) -> dict:
    """Return pairs, RR, valid, valid but wrong and valid keeps of ``records``."""
    right = sum(r['success'] for r in records)
    valid = [r for r in records if passes(r, gates)]
    wrong = sum(not r['success'] for r in valid)
    return {'pairs': len(records), 'rr': right / len(records) if records else None,
            'valid': len(valid), 'valid_wrong': wrong,
            'valid_wrong_share': wrong / len(valid) if valid else None,
            'valid_keeps': (len(valid) - wrong) / right if right else None}


def main(argv: list[str] | None = None) -> int:
    p = argument_parser(__spec__.name, __doc__)
    p.add_argument('records', type=Path, help='records.jsonl of python -m bench.threedmatch')
    p.add_argument('--gate', action='append', type=parse_gate, default=[],
                   metavar="'FIELD OP VALUE'")
    p.add_argument('--method', default='cgags')
    args = p.parse_args(argv)
    records = [r for r in map(json.loads, args.records.read_text().splitlines())
               if r['method'] == args.method]
    rows = []
    for benchmark in dict.fromkeys(r['benchmark'] for r in records):
        recs = [r for r in records if r['benchmark'] == benchmark]
        for scene in [*dict.fromkeys(r['scene'] for r in recs), 'all']:
            sub = recs if scene == 'all' else [r for r in recs if r['scene'] == scene]
            for label, gates in (('recorded', []), ('with gates', args.gate)):
                s = flag_summary(sub, gates)
                rows.append((benchmark, scene[:24], label, s['pairs'], 100 * s['rr'],
                             s['valid'], s['valid_wrong'],
                             None if s['valid_wrong_share'] is None
                             else 100 * s['valid_wrong_share'],
                             None if s['valid_keeps'] is None else 100 * s['valid_keeps']))
    print(markdown_table(('list', 'scene', 'flag', 'pairs', 'RR [%]', 'valid',
                          'valid but wrong', 'of valid [%]', 'valid keeps [%]'), rows))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
