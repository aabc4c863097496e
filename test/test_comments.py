"""
Comments and docstrings of cgags_ros/ say why, not what happened on which machine when.

A measured timing ("costs ~0.2 ms", "1.5x faster"), a development pass ("fifth pass",
"pass 3"), an issue or pull-request number ("issue 14", "#14"), a commit hash or a date
goes stale with the next change or machine; it belongs in docs/ (benchmarks, design) or in
git history. One test per file, so a failure names the file; every hit is listed as
``line: text``.

What is not flagged, on purpose: a duration that is a setting or a property of the data
("at most every 30 s", "timeout in seconds", "stamps up to 50 ms apart"): a timing is
flagged only with a cue that it was measured (costs, takes, took, ~, about, per call,
here); an algorithm's own passes ("its first pass", "the FPFH pass"): ordinals up to
second are flagged only when named a development pass; sizes ("64 x 64 block").
"""

from __future__ import annotations

import ast
import io
from pathlib import Path
import re
import tokenize

import pytest

pytestmark = pytest.mark.source_only
REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / 'cgags_ros'

_DURATION = (r'\d[\d.,]*(?:\s*(?:-|–|to)\s*\d[\d.,]*)?\s*'
             r'(?:ns|us|µs|ms|s|secs?|seconds?|mins?|minutes?|hours?|h)\b')
_CUE_BEFORE = (r'(?:~|≈|\babout\s+|\baround\s+|\broughly\s+|\bapprox(?:imately|\.)?\s+'
               r'|\b(?:costs?|took|takes|spent|saves?|saved|measured|runs? in)\s+~?)')
_CUE_AFTER = (r'\s+(?:here\b|on (?:this|my|our|the \w+) (?:machine|laptop|cpu|host|box)'
              r'|per (?:call|pair|scan|frame|registration|iteration|cloud|run)\b'
              r'|a (?:call|pair|scan|frame|registration|cloud)\b)')
_ORDINALS = ('third|fourth|fifth|sixth|seventh|eighth|ninth|tenth|eleventh|twelfth'
             r'|\d+(?:st|nd|rd|th)')
_DEV_KINDS = (r'development|review|optimi[sz]ation|tuning|bench(?:mark)?|clean-?up'
              r'|refactor(?:ing)?|profiling|speed-?up')

PATTERNS = {
    'timing': re.compile(rf'{_CUE_BEFORE}{_DURATION}|{_DURATION}{_CUE_AFTER}', re.I),
    'speed ratio': re.compile(
        r'\d[\d.]*\s*(?:x|×|times)\s+(?:faster|slower|quicker|speed-?up|the (?:speed|time))\b'
        r'|\b(?:costs?|takes?|took)\s+~?\d[\d.]*\s*(?:x|×|times)\b'
        r'|\bspeed-?up of\s+~?\d', re.I),
    'machine': re.compile(r'\b(?:on|of|for) (?:this|my|our) (?:machine|laptop|workstation'
                          r'|box|host|cpu)\b'
                          r'|\bmeasured on (?:a |an )?\d+[- ]?(?:cores?|cpus?|threads?)\b',
                          re.I),
    'development pass': re.compile(
        rf'\bpass(?:es)?\s*#?\d+\b(?![.,]\d)|\b(?:{_ORDINALS})\s+pass\b'
        rf'|\b(?:first|second)\s+(?:{_DEV_KINDS})\s+pass\b'
        rf'|\b(?:{_DEV_KINDS}) pass\s+(?:one|two|three|four|five|\d)', re.I),
    'issue number': re.compile(
        r'\b(?:issues?|tickets?|pr|pull request|pull)\s*#?\d+\b|(?<![\w#&/])#\d+\b'
        r'|\bgh-\d+\b', re.I),
    # Case-sensitive: git prints lowercase hex; a digit and a letter, so no word or number.
    'commit hash': re.compile(r'\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*\d)[0-9a-f]{7,40}\b'
                              r'|\bcommit [0-9a-f]{5,40}\b'),
    # Not inside a name: a file name pattern may carry a date-like stamp.
    'date': re.compile(r'(?<![\w-])(?:19|20)\d\d-[01]\d-[0-3]\d(?![\w-])'),
}


def comment_blocks(source: str):
    """
    Yield (first line, text) of each comment block and docstring of a module.

    Consecutive full-line comments are one block (lines joined by newlines), so a phrase
    wrapped over two lines is seen whole; a comment after code is a block of its own. The
    leading ``#`` is dropped.
    """
    block, start, last = [], 0, -2
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type != tokenize.COMMENT:
            continue
        line = tok.start[0]
        own_line = not tok.line[:tok.start[1]].strip()
        if block and not (own_line and line == last + 1):
            yield start, '\n'.join(block)
            block = []
        if not block:
            start = line
        block.append(tok.string.lstrip('#').strip())
        last = line if own_line else -2
    if block:
        yield start, '\n'.join(block)
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            body = node.body
            if (body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant)
                    and isinstance(body[0].value.value, str)):
                yield body[0].lineno, body[0].value.value


def normalized(text: str):
    """Return ``text`` with each run of whitespace one space, and each word's line offset."""
    words = [(m.group(0), text.count('\n', 0, m.start())) for m in re.finditer(r'\S+', text)]
    out, lines = [], []
    for word, line in words:
        lines += [line] * (len(word) + 1)
        out.append(word)
    return ' '.join(out), lines


def hits(text: str):
    """Return [(kind, match)] of ``text`` (whitespace runs read as one space)."""
    flat, _ = normalized(text)
    return [(kind, m) for kind, pattern in PATTERNS.items() for m in pattern.finditer(flat)]


def file_hits(path: Path):
    """Return ``['line N (kind): ...matched text...']`` of one source file."""
    out = []
    for start, text in comment_blocks(path.read_text()):
        flat, lines = normalized(text)
        for kind, m in hits(text):
            out.append(f'line {start + lines[m.start()]} ({kind}): '
                       f'...{flat[max(0, m.start() - 50):m.end() + 20]}...')
    return out


SOURCES = sorted(PACKAGE.rglob('*.py'))


@pytest.mark.parametrize('path', SOURCES, ids=[str(p.relative_to(REPO)) for p in SOURCES])
def test_comments_carry_no_timings_passes_issues_or_hashes(path):
    found = file_hits(path)
    assert not found, (f'{path.relative_to(REPO)}: comments/docstrings with numbers that '
                       'go stale (move them to docs/, say why instead):\n' + '\n'.join(found))


def test_every_package_module_is_checked():
    assert len(SOURCES) > 50
    assert PACKAGE / 'registration' / 'cgags.py' in SOURCES


@pytest.mark.parametrize('text, kind', [
    ('the split costs 0.1-0.2 ms here, more than it saves', 'timing'),
    ("numpy's version costs ~60 us.", 'timing'),
    ('a merge costs ~0.2 ms at N = 1000', 'timing'),
    ('registration takes 3 s on this machine', 'timing'),
    ('about 12 ms per pair', 'timing'),
    ('warm-up: 40 s here', 'timing'),
    ('8x slower, docs/implementation.md', 'speed ratio'),
    ('on the redkitchen features 1.5x faster than _REACH = 1', 'speed ratio'),
    ('selects instead: it vectorizes, ~2.5x faster than pair by pair', 'speed ratio'),
    ('one flat pass; the per-row mask costs ~30x more', 'speed ratio'),
    ('3 times slower without the cache', 'speed ratio'),
    ('the slowest step on my laptop', 'machine'),
    ('at most four (measured on 2 cores)', 'machine'),
    ('added in pass 3', 'development pass'),
    ('since the fifth pass the graph is bit-packed', 'development pass'),
    ('kept from the second review pass', 'development pass'),
    ('the 4th pass moved this', 'development pass'),
    ('see issue 14', 'issue number'),
    ('fixes #14', 'issue number'),
    ('(PR 7)', 'issue number'),
    ('reverted in 3f2a9c1', 'commit hash'),
    ('as of commit 41af97fe', 'commit hash'),
    ('measured on 2026-11-30', 'date'),
])
def test_patterns_catch_stale_numbers(text, kind):
    assert kind in [k for k, _ in hits(text)], [m.group(0) for _, m in hits(text)]


@pytest.mark.parametrize('text', [
    'Log a counted rejection, once per cause and then at most every 30 s.',
    'synchronized mode: largest |source stamp - target stamp|, seconds.',
    'Seconds one registration may take; 0 runs it with no limit.',
    'Stamps up to 50 ms apart.',
    'sampled every 0.1 s for a spawned node',
    'timeout: 30 s by default',
    'Fill rows a..b-1 of the upper triangle (its first pass).',
    'blocks whose lists are searched again for the second pass, so memory stays bounded',
    'every SPFH is computed once, before the FPFH pass reads it',
    'Transpose a 64 x 64 bit block in place.',
    'sees 80 x 40 degrees up to 15 m',
    "bin units: 450x the approximation's error",
    'atan(a) ~ a P(a^2) on [0, 1], max error 1.3e-9 rad',
    'float64 (N, 3) points; 12-byte points',
    'Remote Sensing 2024, 16, 2789',
    'p_target = R p_source + t, metres',
    'the decade 0xdeadbeef mask',
    'a 4x4 transform',
    'degenerate: fewer than 3 points',
    'only the members that pass get their distances computed',
])
def test_patterns_leave_reasons_and_settings_alone(text):
    assert not hits(text), [m.group(0) for _, m in hits(text)]


def test_blocks_join_wrapped_comments_and_read_docstrings(tmp_path):
    source = ('"""Module."""\n'
              'x = 1  # one\n'
              '# a merge costs\n'
              '# ~0.2 ms\n'
              'def f():\n'
              '    """Doc of f."""\n')
    assert list(comment_blocks(source)) == [(2, 'one'), (3, 'a merge costs\n~0.2 ms'),
                                            (1, 'Module.'), (6, 'Doc of f.')]
    path = tmp_path / 'sample.py'
    path.write_text(source)
    assert file_hits(path) == ['line 3 (timing): ...a merge costs ~0.2 ms...']
