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

History that a page needs behind it (numbered A/B rounds, superseded runs) lives in dated
notes, docs/notes/YYYY-MM-topic.md: they may hold dates anywhere and are otherwise held to
the same rule. Every page, note and README is also checked for its size (at most
``MAX_LINES``; the generated parameters.md is exempt), for the repository paths it names
(``cgags_ros/...``, ``bench/...``, ``test/...``, a package-relative ``pipeline/map.py``,
a dotted ``cgags_ros.x.y``: each must exist) and for its relative links (file and #anchor).
"""

from __future__ import annotations

from pathlib import Path
import re

import pytest
from test_comments import normalized, PATTERNS

pytestmark = pytest.mark.source_only
REPO = Path(__file__).resolve().parents[1]
PAGES = sorted((REPO / 'docs').glob('*.md'))
NOTES = sorted((REPO / 'docs' / 'notes').glob('*.md'))
README = REPO / 'README.md'
MAX_LINES = 400
GENERATED = {'parameters.md'}
NOTE_NAME = re.compile(r'20\d\d-[01]\d-[a-z0-9-]+\.md')
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


def page_hits(text: str, dated: bool = False) -> list[str]:
    """
    Return ``['line N (kind): ...matched text...']`` of one page's text.

    ``dated``: a note of docs/notes/, whose dates are its subject, not a diary.
    """
    out = []
    for start, paragraph in _paragraphs(text):
        exempt = paragraph.lstrip().startswith(MEASURED)
        flat, lines = normalized(paragraph)
        for kind, pattern in DIARY.items():
            if (exempt and kind in REPRODUCIBLE) or (dated and kind == 'date'):
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


@pytest.mark.parametrize('note', NOTES, ids=[p.name for p in NOTES])
def test_notes_are_dated_and_carry_no_other_diary(note):
    assert NOTE_NAME.fullmatch(note.name), f'docs/notes/{note.name}: name it YYYY-MM-topic.md'
    found = page_hits(note.read_text(encoding='utf-8'), dated=True)
    assert not found, (f'docs/notes/{note.name}: a note may hold dates; a revision goes in a '
                       f'"{MEASURED}" paragraph:\n' + '\n'.join(found))


def test_every_page_is_checked():
    names = {p.name for p in PAGES}
    assert {'benchmarks.md', 'design.md', 'bench_core.md', 'ablation.md'} <= names
    assert len(PAGES) > 15
    assert NOTES, 'docs/notes/ holds the dated history the pages link to'


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


def test_a_note_may_hold_dates_and_nothing_else_of_a_diary():
    text = 'Run 2026-12-02, two rounds at revision 41af97f.\n'
    assert page_hits(text, dated=True) == [
        'line 1 (commit hash): ...Run 2026-12-02, two rounds at revision 41af97f....']
    assert len(page_hits(text)) == 2


def test_the_exemption_is_one_paragraph_and_only_for_revisions():
    text = ('How this was measured: at revision 41af97f.\n'
            'still the same paragraph, 2026-12-03.\n'
            '\n'
            'A later paragraph at 41af97f.\n')
    assert page_hits(text) == ['line 4 (commit hash): ...A later paragraph at 41af97f....']


# Size, named paths and links: every page, note and README.

CHECKED = [README, *PAGES, *NOTES]
IDS = [str(p.relative_to(REPO)) for p in CHECKED]
PACKAGE = REPO / 'cgags_ros'
ROOTED = re.compile(r'(?<![\w./~$-])((?:cgags_ros|bench|test)/[\w./*-]*[\w*/])')
RELATIVE = re.compile(r'(?<![\w./~$-])((?:[a-z_0-9]+/)+[a-z_0-9]+\.py)\b')
DOTTED = re.compile(r'(?<![\w./-])(cgags_ros(?:\.\w+)+)')


def _is_module(parts: list[str]) -> bool:
    path = REPO.joinpath(*parts)
    return path.with_suffix('.py').is_file() or (path / '__init__.py').is_file()


def missing_paths(text: str) -> list[str]:
    """
    Return the repository paths that ``text`` names and the repository does not hold.

    ``cgags_ros/...``, ``bench/...`` and ``test/...`` are taken from the repository root (a
    ``*`` is globbed); ``pipeline/map.py``, whose first part is a package of cgags_ros (or
    ``compiled``), must end some file of the package; a dotted ``cgags_ros.a.b`` must be a
    module, or an attribute of one.
    """
    packages = {p.name for p in PACKAGE.iterdir() if p.is_dir()} | {'compiled'}
    out = []
    for m in ROOTED.finditer(text):
        path = m.group(1).rstrip('.')
        if not (list(REPO.glob(path)) if '*' in path else (REPO / path).exists()):
            out.append(path)
    for m in RELATIVE.finditer(text):
        path = m.group(1)
        if path.split('/')[0] in packages and not list(PACKAGE.rglob(path)):
            out.append(path)
    for m in DOTTED.finditer(text):
        parts = m.group(1).split('.')
        if not (_is_module(parts) or _is_module(parts[:-1])):
            out.append(m.group(1))
    return out


def anchor(heading: str) -> str:
    """Return the #anchor GitHub gives a markdown heading."""
    return re.sub(r'[^\w\- ]', '', heading.strip().lower()).replace(' ', '-')


def broken_links(page: Path) -> list[str]:
    """Return the relative links of ``page`` whose file or #anchor does not exist."""
    broken = []
    text = re.sub(r'^```.*?^```', '', page.read_text(encoding='utf-8'), flags=re.M | re.S)
    for target in re.findall(r'\]\(([^)\s]+)\)', text):
        if re.match(r'[a-z]+://', target):
            continue
        path, _, fragment = target.partition('#')
        linked = (page.parent / path).resolve() if path else page
        if not linked.exists():
            broken.append(target)
        elif fragment and linked.suffix == '.md':
            headings = re.findall(r'^#+\s+(.*)$', linked.read_text(encoding='utf-8'), flags=re.M)
            if fragment not in {anchor(h) for h in headings}:
                broken.append(target)
    return broken


@pytest.mark.parametrize('page', CHECKED, ids=IDS)
def test_page_is_at_most_max_lines(page):
    if page.parent.name == 'docs' and page.name in GENERATED:
        pytest.skip('generated from the config classes')
    lines = len(page.read_text(encoding='utf-8').splitlines())
    limit = 150 if page == README else MAX_LINES
    assert lines <= limit, (f'{page.relative_to(REPO)}: {lines} lines (at most {limit}); move '
                            f'history to a dated docs/notes/YYYY-MM-topic.md')


@pytest.mark.parametrize('page', CHECKED, ids=IDS)
def test_paths_a_page_names_exist(page):
    assert missing_paths(page.read_text(encoding='utf-8')) == []


@pytest.mark.parametrize('page', CHECKED, ids=IDS)
def test_links_resolve(page):
    assert broken_links(page) == []


def test_the_path_check_finds_stale_paths_and_leaves_others_alone():
    text = ('`cgags_ros/pipeline/backlog.py`, `pipeline/upstream.py`, `bench/nope.py`, '
            '`test/test_nope.py`, `cgags_ros.pipeline.nope.thing`; fine: '
            '`cgags_ros/engine/accounting.py`, `engine/pairing.py`, `compiled/bits.py`, '
            '`cgags_ros.pipeline.register.register_clouds`, `bench/studies/*.py`, '
            '`out/bench/soak.json`, `$(ros2 pkg prefix cgags_ros)/share/cgags_ros/config/x.xml`, '
            '`src/cgags_ros/requirements.txt`, `launch/register_node.launch.py`')
    assert missing_paths(text) == ['cgags_ros/pipeline/backlog.py', 'bench/nope.py',
                                   'test/test_nope.py', 'pipeline/upstream.py',
                                   'cgags_ros.pipeline.nope.thing']


def test_the_link_check_finds_a_missing_page_and_a_missing_anchor(tmp_path):
    (tmp_path / 'a.md').write_text('# A page\n\n## The map (`pipeline/map.py`)\n')
    page = tmp_path / 'b.md'
    page.write_text('[ok](a.md#the-map-pipelinemappy) [no](c.md) [gone](a.md#the-map)\n'
                    '[self](#b) [web](https://example.org/x.md)\n\n# B\n')
    assert broken_links(page) == ['c.md', 'a.md#the-map']
