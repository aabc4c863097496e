"""
package.xml declares what the installed package and its tests import.

rosdep installs what package.xml names, so an import without its key works in this venv but
fails on a machine set up with ``rosdep install``. Every import of the installed code
(``cgags_ros/`` and the installed ``launch/`` files), module level or inside a function, must
have an exec_depend; every import of ``test/`` an exec_depend or a test_depend.
"""

import ast
import functools
import gzip
from pathlib import Path
import re
import sys
import xml.etree.ElementTree as ET

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
PACKAGE = 'cgags_ros'
# ros/rosdistro's rosdep database and Jazzy distribution file, committed so that the key check
# runs from a bare clone; ../shared/rosdep holds the same snapshot uncompressed.
ROSDEP_SNAPSHOT = REPO / 'test' / 'fixtures' / 'rosdep'
SHARED_ROSDEP = REPO.parent / 'shared' / 'rosdep'
ROSDEP_FILES = ('base', 'python', 'jazzy-distribution')
# Jazzy's Ubuntu release: the one rosdep resolves for on a Jazzy robot.
UBUNTU_RELEASE = 'noble'
# rosdep reads a dict under an OS first as installer -> packages, else as release -> rule.
INSTALLERS = ('apt', 'pip', 'gem', 'npm', 'source')

# Top-level module -> rosdep key. A third-party import not listed here fails the test on
# purpose: whoever adds it decides its key (and adds that key to package.xml).
ROSDEP_KEYS = {
    # ROS 2 packages: the key is the package name.
    'ament_index_python': 'ament_index_python',
    'bondpy': 'bondpy',
    'builtin_interfaces': 'builtin_interfaces',
    'diagnostic_msgs': 'diagnostic_msgs',
    'geometry_msgs': 'geometry_msgs',
    'launch': 'launch',
    'launch_ros': 'launch_ros',
    'lifecycle_msgs': 'lifecycle_msgs',
    'nav_msgs': 'nav_msgs',
    'rcl_interfaces': 'rcl_interfaces',
    'rclpy': 'rclpy',
    'sensor_msgs': 'sensor_msgs',
    'std_msgs': 'std_msgs',
    'std_srvs': 'std_srvs',
    'tf2_msgs': 'tf2_msgs',
    'tf2_ros': 'tf2_ros',
    'visualization_msgs': 'visualization_msgs',
    'ament_flake8': 'ament_flake8',
    'ament_pep257': 'ament_pep257',
    # Python packages the distributions ship.
    'hypothesis': 'python3-hypothesis',
    'matplotlib': 'python3-matplotlib',
    'numba': 'python3-numba',
    'numpy': 'python3-numpy',
    'pytest': 'python3-pytest',
    'scipy': 'python3-scipy',
    'tqdm': 'python3-tqdm',
    'yaml': 'python3-yaml',
    # Python packages only pip has, with a rosdep key that installs them with pip.
    'mcap_ros2': 'mcap-ros2-support',
    'open3d': 'python3-open3d-pip',
    'rosbags': 'python3-rosbags-pip',
}
# Top-level module -> pip distribution, for what the rosdep database has no key for on
# Ubuntu noble: package.xml cannot key them (rosdep install would stop), so a package.xml
# comment names them for `pip install` instead. Only optional imports belong here.
PIP_ONLY = {
    'mcap': 'mcap',
    'optuna': 'optuna',
    'small_gicp': 'small_gicp',
    'threadpoolctl': 'threadpoolctl',
}
# format 3: <depend> is build + exec + test; run_depend is format 1's exec_depend.
EXEC_TAGS = ('depend', 'exec_depend', 'run_depend')
TEST_TAGS = EXEC_TAGS + ('test_depend',)
# Calls that import the module named by their first (constant) argument.
DYNAMIC_IMPORTS = {'import_module', '__import__', 'importorskip'}


def package_xml():
    return ET.parse(REPO / 'package.xml').getroot()


def dependencies(tags):
    return {el.text.strip() for el in package_xml() if el.tag in tags and el.text}


def imported_modules(path: Path):
    """Yield (line, top-level module) of every absolute import in ``path``, at any depth."""
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield node.lineno, alias.name.partition('.')[0]
        elif isinstance(node, ast.ImportFrom):
            if node.level == 0:  # relative imports are the package's own
                yield node.lineno, node.module.partition('.')[0]
        elif isinstance(node, ast.Call) and node.args:
            func = node.func
            name = func.attr if isinstance(func, ast.Attribute) else getattr(func, 'id', None)
            arg = node.args[0]
            if (name in DYNAMIC_IMPORTS and isinstance(arg, ast.Constant)
                    and isinstance(arg.value, str) and not arg.value.startswith('.')):
                yield node.lineno, arg.value.partition('.')[0]


def third_party_imports(paths):
    """Map each module that is neither stdlib nor the package to ['file:line', ...]."""
    found = {}
    for path in paths:
        for line, module in imported_modules(path):
            if module in sys.stdlib_module_names or module == PACKAGE:
                continue
            found.setdefault(module, []).append(f'{path.relative_to(REPO)}:{line}')
    return found


def package_xml_comments():
    return ' '.join(re.findall(r'<!--(.*?)-->', (REPO / 'package.xml').read_text(), re.S))


def undeclared(paths, declared, tag):
    problems = []
    comments = package_xml_comments()
    for module, where in sorted(third_party_imports(paths).items()):
        key = ROSDEP_KEYS.get(module)
        if module in PIP_ONLY:
            named = rf'(?<![\w-]){re.escape(PIP_ONLY[module])}(?![\w-])'
            if not re.search(named, comments):
                problems.append(f'{module!r} (imported at {", ".join(where)}) is pip-only: '
                                f'name {PIP_ONLY[module]!r} in the pip-only comment of '
                                'package.xml')
        elif key is None:
            problems.append(f'{module!r} (imported at {", ".join(where)}) has no rosdep key: '
                            f'add it to ROSDEP_KEYS in {Path(__file__).name} and to '
                            f'package.xml')
        elif key not in declared:
            problems.append(f'{module!r} (imported at {", ".join(where)}) needs '
                            f'<{tag}>{key}</{tag}> in package.xml')
    return problems


def installed_sources():
    return sorted((REPO / PACKAGE).rglob('*.py')) + sorted((REPO / 'launch').glob('*.py'))


def test_installed_code_imports_are_exec_depends():
    paths = installed_sources()
    assert len(paths) > 10 and REPO / PACKAGE / '__init__.py' in paths
    problems = undeclared(paths, dependencies(EXEC_TAGS), 'exec_depend')
    assert not problems, '\n'.join(problems)


def test_test_imports_are_declared():
    paths = sorted((REPO / 'test').glob('*.py'))
    # The tests' own helper modules (waiting.py) and the repository's bench package (its data
    # readers; not installed, on pytest's path through setup.cfg) are no dependencies.
    helpers = {p.stem for p in paths} | {'bench'}
    problems = [p for p in undeclared(paths, dependencies(TEST_TAGS), 'test_depend')
                if p.split("'")[1] not in helpers]
    assert not problems, '\n'.join(problems)


def test_scanner_sees_function_level_and_dynamic_imports(tmp_path):
    source = tmp_path / 'sample.py'
    source.write_text('import os.path\n'
                      'from . import sibling\n'
                      'def f():\n'
                      '    from scipy.spatial import cKDTree\n'
                      '    import importlib\n'
                      "    return importlib.import_module('tqdm.auto')\n")
    assert list(imported_modules(source)) == [(1, 'os'), (4, 'scipy'), (5, 'importlib'),
                                              (6, 'tqdm')]


def setup_keyword(name):
    for node in ast.walk(ast.parse((REPO / 'setup.py').read_text())):
        if isinstance(node, ast.Call) and getattr(node.func, 'id', None) == 'setup':
            for keyword in node.keywords:
                if keyword.arg == name:
                    return ast.literal_eval(keyword.value)
    raise AssertionError(f'setup.py: no setup({name}=...)')


def test_package_xml_is_consistent():
    root = package_xml()
    assert root.tag == 'package' and root.get('format') == '3'
    assert root.findtext('name') == PACKAGE
    assert root.findtext('export/build_type') == 'ament_python'
    assert (REPO / 'resource' / PACKAGE).is_file()  # the ament index marker setup.py installs
    # colcon reports package.xml's version, setuptools installs setup.py's: keep them equal.
    assert setup_keyword('version') == root.findtext('version')
    entries = [(el.tag, el.text.strip()) for el in root if el.tag.endswith('depend')]
    duplicates = sorted({entry for entry in entries if entries.count(entry) > 1})
    assert not duplicates, f'declared more than once: {duplicates}'
    assert not set(ROSDEP_KEYS) & sys.stdlib_module_names
    assert not set(ROSDEP_KEYS) & set(PIP_ONLY)


# --- every key resolves on Jazzy / Ubuntu noble ------------------------------------------------


@functools.cache
def snapshot(name):
    """Return one file of the committed rosdep snapshot, parsed."""
    with gzip.open(ROSDEP_SNAPSHOT / f'{name}.yaml.gz', 'rt', encoding='utf-8') as f:
        return yaml.load(f, Loader=getattr(yaml, 'CSafeLoader', yaml.SafeLoader))


@functools.cache
def jazzy_packages():
    """Return the ROS packages Jazzy releases (rosdep resolves them to ros-jazzy-* debs)."""
    names = set()
    for repository, entry in snapshot('jazzy-distribution')['repositories'].items():
        release = entry.get('release') or {}
        if 'version' in release:  # a release section without a version is not released
            # REP 143: without a package list the repository holds one package of its name.
            names.update(release.get('packages', [repository]))
    return frozenset(names)


def ubuntu_rule(rule, release=UBUNTU_RELEASE):
    """
    Return (installer, packages) that rosdep installs for one key's rule on Ubuntu ``release``.

    ``rule`` is the key's entry of base.yaml / python.yaml ({os: spec}). Returns None where
    rosdep stops with a ResolutionError: no ubuntu entry, a per-release dict naming neither
    the release nor '*', or a null for it. Follows rosdep's RosdepDefinition
    .get_rule_for_platform: a dict is read as installer -> packages first, else as
    release -> rule (which may again be installer -> packages).
    """
    if not isinstance(rule, dict) or 'ubuntu' not in rule:
        return None
    spec, installer = rule['ubuntu'], 'apt'
    for level in ('os', 'release'):
        if not isinstance(spec, dict):
            break
        found = next((key for key in INSTALLERS if key in spec), None)
        if found:
            spec, installer = spec[found], found
            break
        if level == 'release':
            return None  # a dict inside a release must name an installer
        if release in spec:
            spec = spec[release]  # may be null: not available on this release
        elif '*' in spec:
            spec = spec['*']
        else:
            return None
    if isinstance(spec, dict):  # {packages: [...]} of an installer
        spec = spec.get('packages')
    if isinstance(spec, str):
        spec = spec.split()
    if not isinstance(spec, list):
        return None
    # An empty apt list is "nothing to install" (rosdep succeeds); pip needs a package.
    return (installer, spec) if spec or installer == 'apt' else None


def resolve(key):
    """Return how ``key`` resolves on Jazzy / noble, or None where rosdep stops on it."""
    if key in jazzy_packages():
        return ('ros', [f'ros-jazzy-{key.replace("_", "-")}'])
    for name in ('base', 'python'):
        if key in snapshot(name):
            return ubuntu_rule(snapshot(name)[key])
    return None


def test_every_package_xml_key_resolves_on_jazzy_noble():
    """Check each key the way `rosdep install --from-paths src` on a Jazzy robot would."""
    keys = sorted(dependencies(TEST_TAGS) | set(ROSDEP_KEYS.values()))
    assert 'rclpy' in keys and 'python3-numpy' in keys
    unresolved = [key for key in keys if resolve(key) is None]
    assert not unresolved, (
        f'no rule for Ubuntu {UBUNTU_RELEASE} in the rosdep snapshot ({ROSDEP_SNAPSHOT}): '
        f'{unresolved}; drop the key and name its pip package in the pip-only comment of '
        f'package.xml (PIP_ONLY), or pick a key that resolves')
    for module, pip_name in PIP_ONLY.items():
        assert resolve(f'python3-{pip_name}') is None, f'{module} now has a key: use it'
        assert resolve(f'python3-{pip_name.replace("_", "-")}-pip') is None, module


@pytest.mark.parametrize('rule, expected', [
    ({'ubuntu': ['python3-numba']}, ('apt', ['python3-numba'])),
    ({'ubuntu': {'pip': {'packages': ['open3d']}}}, ('pip', ['open3d'])),
    ({'ubuntu': {'*': ['python3-tqdm']}}, ('apt', ['python3-tqdm'])),
    ({'ubuntu': {'*': ['a'], 'focal': None}}, ('apt', ['a'])),
    ({'ubuntu': {'*': ['a'], 'noble': None}}, None),
    ({'ubuntu': {'*': None, 'focal': ['a']}}, None),
    ({'ubuntu': {'jammy': ['a']}}, None),
    ({'ubuntu': {'noble': ['b'], 'jammy': ['a']}}, ('apt', ['b'])),
    ({'ubuntu': {'*': ['a'], 'noble': {'pip': ['faiss-cpu']}}}, ('pip', ['faiss-cpu'])),
    ({'ubuntu': {'*': {'pip': {'packages': ['x']}}}}, ('pip', ['x'])),
    ({'ubuntu': {'noble': []}}, ('apt', [])),
    ({'ubuntu': {'pip': {'packages': []}}}, None),
    ({'debian': ['python3-threadpoolctl']}, None),
    (None, None),
])
def test_ubuntu_rule_reads_rosdep_entries_like_rosdep(rule, expected):
    assert ubuntu_rule(rule) == expected


def test_snapshot_resolves_known_keys_and_refuses_missing_ones():
    """The snapshot as read here: real keys of each shape, and the two that stopped rosdep."""
    assert resolve('tf2_ros')[0] == 'ros' and resolve('ros2launch')[0] == 'ros'
    assert resolve('python3-open3d-pip') == ('pip', ['open3d'])
    assert resolve('python3-tqdm') == ('apt', ['python3-tqdm'])  # per release: '*'
    assert resolve('libopen3d-dev') is None  # noble: null
    assert resolve('python3-threadpoolctl') is None and resolve('python3-small-gicp-pip') is None
    assert resolve('small_gicp_vendor')[0] == 'ros'  # C++ only: not the small_gicp module


def test_committed_rosdep_snapshot_equals_shared_snapshot(require_shared):
    """The committed copy is the snapshot of ../shared/rosdep (see its README), unchanged."""
    shared = require_shared(SHARED_ROSDEP, 'rosdep snapshot')
    for name in ROSDEP_FILES:
        with gzip.open(ROSDEP_SNAPSHOT / f'{name}.yaml.gz', 'rb') as f:
            committed = f.read()
        assert committed == (shared / f'{name}.yaml').read_bytes(), (
            f'{name}.yaml.gz differs from {shared}: refresh it (test/fixtures/rosdep/README.md)')
