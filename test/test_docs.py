"""
docs/ states the present: what is true now and why, not a diary of the runs that got there.

Every docs/*.md, hand-written or written by a bench script, is checked for what dates a page
to the run that produced it: a development pass ("fifth pass", "pass 3"), an issue or
pull-request number, a commit hash, a date, and the run-diary phrases of ``DIARY``. Which
pass, issue or commit produced a number stays in git history; a re-run replaces the numbers
it measures again. One exception, for a result that cannot be reproduced without it (e.g.
an ablation of variants the code no longer has): a paragraph that starts with
``How this was measured:`` may name the revision and the date. The rule is stated in
docs/design.md; the same patterns keep code comments clean (test_comments.py). One test per
page, so a failure names the page; every hit is listed as ``line N (kind): text``.
"""

from __future__ import annotations

from pathlib import Path
import re

import pytest
from test_comments import normalized, PATTERNS

REPO = Path(__file__).resolve().parents[1]
PAGES = sorted((REPO / 'docs').glob('*.md'))
MEASURED = 'How this was measured:'
REPRODUCIBLE = ('commit hash', 'date')
DIARY = {kind: PATTERNS[kind] for kind in ('development pass', 'issue number') + REPRODUCIBLE}
DIARY['run diary'] = re.compile(
    r'\bbefore \((?:main|master|HEAD)\b|\brun on commit\b|\b(?:earlier|previous) runs?:'
    r'|\bbefore (?:this|the) pass\b|\bas before the (?:pass|change)\b', re.I)


def _paragraphs(text: str):
    """Yield (first line index, paragraph text) of ``text``, paragraphs split at blank lines."""
    start, block = 0, []
    for number, line in enumerate(text.splitlines() + ['']):
        if line.strip():
            if not block:
                start = number
            block.append(line)
        elif block:
            yield start, '\n'.join(block)
            block = []


def page_hits(text: str) -> list[str]:
    """Return ``['line N (kind): ...matched text...']`` of one page's text."""
    out = []
    for start, paragraph in _paragraphs(text):
        exempt = paragraph.lstrip().startswith(MEASURED)
        flat, lines = normalized(paragraph)
        for kind, pattern in DIARY.items():
            if exempt and kind in REPRODUCIBLE:
                continue
            for m in pattern.finditer(flat):
                out.append(f'line {start + lines[m.start()] + 1} ({kind}): '
                           f'...{flat[max(0, m.start() - 50):m.end() + 20]}...')
    return out


@pytest.mark.parametrize('page', PAGES, ids=[p.name for p in PAGES])
def test_docs_carry_no_run_diary(page):
    found = page_hits(page.read_text(encoding='utf-8'))
    assert not found, (f'docs/{page.name}: run-by-run history (state what is true now; the '
                       f'revision a result needs goes in a "{MEASURED}" paragraph):\n'
                       + '\n'.join(found))


def test_every_page_is_checked():
    names = {p.name for p in PAGES}
    assert {'benchmarks.md', 'design.md', 'bench_core.md', 'ablation.md'} <= names
    assert len(PAGES) > 15


@pytest.mark.parametrize('text, kind', [
    ('Run 2026-12-02, fifth pass (issue 11: preference merges streamed)', 'development pass'),
    ('Run 2026-12-02, fifth pass (issue 11: preference merges streamed)', 'issue number'),
    ('Run 2026-12-02, fifth pass (issue 11: preference merges streamed)', 'date'),
    ('| before (main at e5a4038) | 91.4 | 91.7 |', 'run diary'),
    ('| before (main at e5a4038) | 91.4 | 91.7 |', 'commit hash'),
    ('Run on commit d60e90f plus the guided_count option', 'run diary'),
    ('kiss_matcher 1.0.2, git a2bc591, registration/*.py', 'commit hash'),
    ('the same successes in each run as before the pass', 'run diary'),
    ('Earlier runs:\n\nRun 2026-12-01, compiled kernels', 'run diary'),
    ('## The valid flag on 3DMatch (issue 30)', 'issue number'),
    ('Targets of the fourth\npass, wrapped over two lines', 'development pass'),
    ('How this was measured: the fifth pass at revision 41af97f', 'development pass'),
])
def test_patterns_catch_run_diaries(text, kind):
    assert kind in [h.split('(', 1)[1].split(')', 1)[0] for h in page_hits(text)], \
        page_hits(text)


@pytest.mark.parametrize('text', [
    'How this was measured: `git worktree add /tmp/ablation 41af97f`, then in it\n'
    '`bench/ablation_core.py --trials 8` (the last revision with every variant, 2026-12-03).',
    'the FPFH pass reads every SPFH once; one compiled pass over the pairs j > i',
    'SPFH pass 13.0 → 5.1 ms (LiDAR 0.3 m, 5k points)',
    'N = 1000 at 99 % outliers: 9.7 ms against 6.3 ms, 0.67-0.77x of its time',
    'map points 77966 median, sun3d-mit_lab_hj-lab_hj_tea_nov_2_2012_scan1_erika',
    'Linux-6.18.44-fc-v1098-x86_64-with-glibc2.36, one pair at a time',
    '[ablation.md](ablation.md#4-dof-chance-level), a 4x4 transform',
    'before the lists exist a draw costs ~3.2 µs; the previous commit, run from its directory',
])
def test_patterns_leave_current_facts_alone(text):
    assert not page_hits(text)


def test_the_exemption_is_one_paragraph_and_only_for_revisions():
    text = ('How this was measured: at revision 41af97f.\n'
            'still the same paragraph, 2026-12-03.\n'
            '\n'
            'A later paragraph at 41af97f.\n')
    assert page_hits(text) == ['line 4 (commit hash): ...A later paragraph at 41af97f....']
