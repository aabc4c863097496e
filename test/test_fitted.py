"""
The numbers of :mod:`cgags_ros.fitted` are what their committed record gives.

The trust study's fit (``python -m bench.studies.fit``) runs on the record the module names,
in a process of its own: a test imports no study (test_bench); it checks the product's
numbers against what the study gives, so a number that drifts from its record is seen.
"""

from __future__ import annotations

import ast
import gzip
import json
from pathlib import Path
import re
import subprocess
import sys

from cgags_ros import fitted
import pytest

REPO = Path(__file__).resolve().parents[1]
RECORD = REPO / 'bench' / 'studies' / 'records' / 'trust.jsonl.gz'

pytestmark = pytest.mark.subprocess


def fit(record: Path) -> dict:
    """Return ``{name: (fit, shipped or None)}`` as ``bench.studies.fit`` prints them."""
    run = subprocess.run([sys.executable, '-m', 'bench.studies.fit', '--record', str(record)],
                         cwd=REPO, capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stdout + run.stderr
    out = {}
    for line in run.stdout.splitlines():
        m = re.match(r'([A-Z_]+) = (.*?)(?:  # (fit|shipped): (.*))?$', line)
        if m:
            name, first, kind, second = m.groups()
            if kind == 'shipped':
                out[name] = (literal(first), literal(second))
            else:
                out[name] = (literal(second) if kind == 'fit' else literal(first), None)
    return out


def literal(text: str):
    return 3.141592653589793 if text == 'math.pi' else ast.literal_eval(text)


def test_every_fitted_number_is_what_its_record_gives():
    numbers = fit(RECORD)
    assert set(numbers) == {n for n in vars(fitted) if n.isupper()}
    differing = {n: f for n, (f, shipped) in numbers.items() if shipped is not None}
    assert differing == {}


def test_a_record_that_gives_other_numbers_is_seen(tmp_path):
    # Every second pair of the record: the confidence is fit on other pairs, its weights are
    # not what ships, and the fit says so.
    rows = [json.loads(line) for line in gzip.open(RECORD, 'rt', encoding='utf-8')][::2]
    changed = tmp_path / 'changed.jsonl.gz'
    with gzip.open(changed, 'wt', encoding='utf-8') as f:
        f.writelines(json.dumps(r) + '\n' for r in rows)
    weights, shipped = fit(changed)['CONFIDENCE_WEIGHTS']
    assert shipped == fitted.CONFIDENCE_WEIGHTS
    assert weights != fitted.CONFIDENCE_WEIGHTS
