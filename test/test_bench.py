"""
bench/ as a package: each benchmark runs as ``python -m bench.<name>`` from the repository root.

Checked from the sources with ast: no module edits sys.path, imports cgags_ros.tools or a
private name of cgags_ros, and the bench modules import one another without a cycle. The
benchmark data readers live in bench/datasets/, not in the installed package, and every
``python -m bench.<name>`` and ``bench/<file>.py`` that README and docs/ name exists. The
one-off studies live in bench/studies/: no test and no other bench module imports one.
"""

from __future__ import annotations

import ast
import graphlib
import importlib
from pathlib import Path
import pkgutil
import re

import bench
import cgags_ros
import pytest

BENCH = Path(bench.__file__).resolve().parent
REPO = BENCH.parent
MODULES = ['bench', *sorted(info.name for info in pkgutil.walk_packages([str(BENCH)], 'bench.'))]
# The benchmark-only data readers, moved out of the package into bench/datasets/.
BENCH_ONLY = ('threedmatch.py', 'rigs.py', 'gt_pairs.py', 'synthetic.py')
STUDIES = 'bench.studies'


def _source(name: str) -> Path:
    path = BENCH.joinpath(*name.split('.')[1:])
    return path / '__init__.py' if path.is_dir() else path.with_suffix('.py')


def _tree(name: str) -> ast.Module:
    return ast.parse(_source(name).read_text(encoding='utf-8'))


def _imports(name: str) -> list[tuple[str, str, str]]:
    """
    Return (module, name or '', local name) of every import of a bench module.

    Function-level imports count too; relative ones are resolved.
    """
    package = name if _source(name).name == '__init__.py' else name.rpartition('.')[0]
    out = []
    for node in ast.walk(_tree(name)):
        if isinstance(node, ast.Import):
            out += [(a.name, '', a.asname or a.name.split('.')[0]) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ''
            if node.level:
                parts = package.split('.')
                base = '.'.join(parts[:len(parts) - node.level + 1] + ([base] if base else []))
            out += [(base, a.name, a.asname or a.name) for a in node.names]
    return out


def _bench_edges(name: str) -> set[str]:
    """Return the bench modules that a bench module imports."""
    edges = set()
    for module, attr, _ in _imports(name):
        if module.split('.')[0] == 'bench':
            edges.add(f'{module}.{attr}' if f'{module}.{attr}' in MODULES else module)
    edges.discard(name)
    return edges


def _is_study(name: str) -> bool:
    return name == STUDIES or name.startswith(f'{STUDIES}.')


@pytest.mark.source_only
def test_every_module_is_found():
    assert {'bench.common', 'bench.core', 'bench.ab_core', 'bench.pipeline',
            'bench.threedmatch', 'bench.datasets.threedmatch', 'bench.studies.fit',
            'bench.studies.trust_shift'} <= set(MODULES)
    assert all(_source(name).is_file() for name in MODULES)


@pytest.mark.parametrize('name', MODULES)
def test_module_imports_as_a_package_module_and_its_command_parses(name, capsys):
    module = importlib.import_module(name)
    assert Path(module.__file__).resolve() == _source(name)
    runnable = "if __name__ == '__main__':" in _source(name).read_text(encoding='utf-8')
    assert runnable == hasattr(module, 'main'), f'{name}: a main() and its __main__ guard'
    if runnable:
        with pytest.raises(SystemExit) as done:
            module.main(['--help'])
        assert done.value.code == 0
        assert capsys.readouterr().out.startswith(f'usage: python -m {name} ')


@pytest.mark.source_only
@pytest.mark.parametrize('name', MODULES)
def test_no_sys_path_edit(name):
    for node in ast.walk(_tree(name)):
        edit = (isinstance(node, ast.Attribute) and node.attr in ('path', 'addsitedir')
                and isinstance(node.value, ast.Name) and node.value.id in ('sys', 'site'))
        assert not edit, f'{name}:{node.lineno} edits sys.path: import as a package module'
    assert not [i for i in _imports(name) if i[:2] in (('sys', 'path'), ('site', 'addsitedir'))]


@pytest.mark.source_only
@pytest.mark.parametrize('name', MODULES)
def test_only_the_public_api_of_cgags_ros(name):
    bound = set()
    for module, attr, local in _imports(name):
        if module.split('.')[0] != 'cgags_ros':
            continue
        assert not module.startswith('cgags_ros.tools'), f'{name} imports {module}'
        private = [p for p in [*module.split('.'), attr] if p.startswith('_')
                   and not p.startswith('__')]
        assert not private, f'{name} imports the private {module} {attr}'
        bound.add(local)
    for node in ast.walk(_tree(name)):
        if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name)
                and node.value.id in bound):
            assert not node.attr.startswith('_') or node.attr.startswith('__'), (
                f'{name}:{node.lineno} reads {node.value.id}.{node.attr}')


@pytest.mark.source_only
def test_no_import_cycle_among_bench_modules():
    graph = {name: _bench_edges(name) for name in MODULES}
    # The checker sees real edges, function-level ones included.
    assert {'bench.common', 'bench.baselines'} <= graph['bench.pipeline']
    assert 'bench.revision' in graph['bench.core']
    assert 'bench.datasets.threedmatch' in graph['bench.threedmatch']
    try:
        tuple(graphlib.TopologicalSorter(graph).static_order())
    except graphlib.CycleError as exc:
        pytest.fail(f'import cycle in bench/: {" -> ".join(exc.args[1])}')


@pytest.mark.source_only
def test_the_package_ships_no_benchmark_data():
    package = Path(cgags_ros.__file__).resolve().parent
    for name in BENCH_ONLY:
        assert not list(package.rglob(name)), f'{name} belongs in bench/datasets/'
        assert (BENCH / 'datasets' / name).is_file()


@pytest.mark.source_only
def test_commands_and_paths_of_readme_and_docs_exist():
    texts = {path: path.read_text(encoding='utf-8')
             for path in [REPO / 'README.md', *sorted((REPO / 'docs').glob('*.md'))]}
    named = 0
    for path, text in texts.items():
        for module in re.findall(r'-m (bench(?:\.\w+)+)', text):
            named += 1
            assert module in MODULES, f'{path.name} runs {module}, which does not exist'
        for file in re.findall(r'\bbench/[\w/]+\.py\b', text):
            assert (REPO / file).is_file(), f'{path.name} names {file}, which does not exist'
    assert named, 'no `python -m bench.<name>` command found in README.md or docs/'


def test_the_studies_package_lists_every_study():
    listed = importlib.import_module(STUDIES).__doc__
    for name in MODULES:
        if _is_study(name) and name != STUDIES:
            assert f':mod:`.{name.rpartition(".")[2]}`' in listed, f'{STUDIES} omits {name}'


@pytest.mark.source_only
def test_no_other_bench_module_imports_a_study():
    """The tools stay whole without the lab notebook; a study may import a tool."""
    for name in MODULES:
        if not _is_study(name):
            assert not [m for m in _bench_edges(name) if _is_study(m)], f'{name} imports a study'


@pytest.mark.source_only
def test_no_test_imports_a_study():
    """A test checks what ships, in the package; a study's code is not what ships."""
    for path in sorted((REPO / 'test').rglob('*.py')):
        for node in ast.walk(ast.parse(path.read_text(encoding='utf-8'))):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and not node.level:
                names = [node.module or '', *(f'{node.module}.{a.name}' for a in node.names)]
            elif (isinstance(node, ast.Call) and node.args
                    and isinstance(node.args[0], ast.Constant)
                    and isinstance(node.args[0].value, str)
                    and getattr(node.func, 'attr', getattr(node.func, 'id', None))
                    in ('import_module', '__import__')):
                names = [node.args[0].value]
            assert not [n for n in names if _is_study(n)], \
                f'{path.relative_to(REPO)}:{node.lineno} imports a study'


def test_a_threedmatch_variant_is_ours_with_its_changes_on_top_of_set():
    from bench import threedmatch
    from cgags_ros.config import PipelineConfig

    base = PipelineConfig(voxel_size=0.05)
    found = threedmatch.variants(['fast:regenerate.enabled=false,core.time_budget=0.01'], base)
    assert list(found) == ['cgags[fast]'] and threedmatch._ours('cgags[fast]')
    fast = found['cgags[fast]']
    assert not fast.regenerate.enabled and fast.core.time_budget == 0.01
    assert fast.voxel_size == 0.05 and base.regenerate.enabled  # the base is not changed
    for bad in (['fast'], [':core.time_budget=1'], ['a:core.p1=0.5', 'a:core.p1=0.6']):
        with pytest.raises(SystemExit):
            threedmatch.variants(bad, base)
    with pytest.raises(Exception, match='no_such'):
        threedmatch.variants(['x:core.no_such=1'], base)
