"""
package.xml declares what the installed package and its tests import.

rosdep installs what package.xml names, so an import without its key works in this venv but
fails on a machine set up with ``rosdep install``. Every import of the installed code
(``cgags_ros/`` and the installed ``launch/`` files), module level or inside a function, must
have an exec_depend; every import of ``test/`` an exec_depend or a test_depend.
"""

import ast
from pathlib import Path
import sys
import xml.etree.ElementTree as ET

REPO = Path(__file__).resolve().parents[1]
PACKAGE = 'cgags_ros'

# Top-level module -> rosdep key. A third-party import not listed here fails the test on
# purpose: whoever adds it decides its key (and adds that key to package.xml).
ROSDEP_KEYS = {
    # ROS 2 packages: the key is the package name.
    'ament_index_python': 'ament_index_python',
    'builtin_interfaces': 'builtin_interfaces',
    'diagnostic_msgs': 'diagnostic_msgs',
    'geometry_msgs': 'geometry_msgs',
    'launch': 'launch',
    'launch_ros': 'launch_ros',
    'nav_msgs': 'nav_msgs',
    'rcl_interfaces': 'rcl_interfaces',
    'rclpy': 'rclpy',
    'sensor_msgs': 'sensor_msgs',
    'std_msgs': 'std_msgs',
    'std_srvs': 'std_srvs',
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
    'threadpoolctl': 'python3-threadpoolctl',
    'tqdm': 'python3-tqdm',
    'yaml': 'python3-yaml',
    # Python packages only pip has: rosdep's '-pip' keys.
    'mcap': 'python3-mcap-pip',
    'mcap_ros2': 'python3-mcap-ros2-support-pip',
    'open3d': 'python3-open3d-pip',
    'rosbags': 'python3-rosbags-pip',
    'small_gicp': 'python3-small-gicp-pip',
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


def undeclared(paths, declared, tag):
    problems = []
    for module, where in sorted(third_party_imports(paths).items()):
        key = ROSDEP_KEYS.get(module)
        if key is None:
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
    helpers = {p.stem for p in paths}  # the tests' own helper modules (waiting.py)
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
