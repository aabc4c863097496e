"""
The package's architecture, checked from its sources with ast.

Layers import one way: tools -> ros -> engine -> runtime -> calibration, tracking,
relocalization -> pipeline -> frontend / registration -> validity -> geometry, config, io (and
errors, timing, and the refusal codes below them all). Only ros/ (and the live replay's DDS
client) imports rclpy and message packages, and ros/ is wiring only: every module of it imports
them, and the whole stays small enough to read in one sitting. The core (registration/) imports
neither ROS nor Open3D; the rest takes Open3D from open3d_import only. No import cycle. No module
over 400 lines: past that, a module usually holds two ideas.
"""

from __future__ import annotations

import ast
import os
from pathlib import Path
import subprocess
import sys

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / 'cgags_ros'
LAYERS = {  # top-level part of the module name -> layer (higher imports lower)
    'refusal': -1,  # the refusal codes, which every error and result carries
    'errors': 0, 'timing': 0, 'parallel': 0, 'compiled_types': 0,
    'fitted': 0,  # the numbers a study fitted, with their record
    'open3d_import': 0,  # Open3D as the front end, io and pipeline import it (without open3d.ml)
    'geometry': 1, 'config': 1,  # the bottom: typed config, geometry, then files and data
    'io': 2, 'validity': 2,  # validity: the core and the pipeline ask it for their verdicts
    'coordinates': 2,  # far coordinates worked on near a local origin (geometry's bounds)
    'frontend': 3, 'registration': 3,  # siblings: neither imports the other
    'pipeline': 4,  # one pair
    'calibration': 5,  # several frames, each through the pipeline
    'tracking': 5,  # a stream's scans, from their predicted pose or through the pipeline
    'relocalization': 5,  # several scans with odometry in a map
    'runtime': 6,  # the registration processes: typed jobs, their state, supervision
    'engine': 7,  # what the node decides, without ROS
    'ros': 8,
    'register_node': 9, 'tools': 9,  # entry points
}
ROS_MODULES = {'rclpy', 'tf2_ros', 'bondpy'}  # and every *_msgs, *_srvs, *_interfaces
# Tools that talk to a running node over DDS: clients of ros/, not part of the node.
ROS_CLIENTS = {'cgags_ros.tools.replay_player'}
CORE_THIRD_PARTY = {'numba', 'numpy', 'scipy', 'threadpoolctl'}
ROS_MAX_LINES = 1000  # all of ros/: the node, its outputs and their messages, TF, QoS, parameters
MODULE_MAX_LINES = 400


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix('').parts
    return '.'.join(parts[:-1] if parts[-1] == '__init__' else parts)


def modules() -> dict[str, Path]:
    return {module_name(p): p for p in sorted(PACKAGE.rglob('*.py'))}


def imports(name: str, path: Path) -> tuple[set[str], set[str]]:
    """
    Return (cgags_ros modules, third-party top-level modules) that ``path`` imports.

    Function-level imports count too: a lazy import still ties the layers together.
    """
    known = modules()
    package = name if path.name == '__init__.py' else name.rpartition('.')[0]
    ours, theirs = set(), set()
    for node in ast.walk(ast.parse(path.read_text(encoding='utf-8'))):
        if isinstance(node, ast.Import):
            targets = [(alias.name, None) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ''
            if node.level:
                anchor = package.split('.')[:len(package.split('.')) - node.level + 1]
                base = '.'.join(anchor + ([base] if base else []))
            targets = [(base, alias.name) for alias in node.names]
        else:
            continue
        for base, attr in targets:
            top = base.split('.')[0]
            if top in sys.stdlib_module_names or top == '__future__':
                continue
            if top != 'cgags_ros':
                theirs.add(top)
            elif attr and f'{base}.{attr}' in known:
                ours.add(f'{base}.{attr}')
            else:
                ours.add(base)
    ours.discard(name)
    return ours, theirs


def is_ros(module: str) -> bool:
    """Tell whether a top-level module is rclpy, a ROS library or a message package."""
    return module in ROS_MODULES or module.endswith(('_msgs', '_srvs', '_interfaces'))


def layer(name: str) -> tuple[int, str]:
    parts = name.split('.')
    if len(parts) == 1:
        return -1, ''  # the package __init__ sits below everything
    return LAYERS[parts[1]], parts[1]


GRAPH = {name: imports(name, path) for name, path in modules().items()}


@pytest.mark.source_only
def test_every_module_has_a_layer():
    for name in GRAPH:
        assert name == 'cgags_ros' or name.split('.')[1] in LAYERS, name


@pytest.mark.source_only
@pytest.mark.parametrize('name', sorted(GRAPH))
def test_imports_run_one_way(name):
    level, part = layer(name)
    for other in GRAPH[name][0]:
        other_level, other_part = layer(other)
        assert other_level < level or other_part == part, (
            f'{name} (layer {part}) imports {other} (layer {other_part}): imports must run '
            'tools -> ros -> pipeline -> frontend/registration -> geometry/config/io')


@pytest.mark.source_only
def test_no_import_cycle():
    graph = {name: ours for name, (ours, _) in GRAPH.items()}
    state: dict[str, int] = {}

    def visit(name: str, trail: list[str]) -> None:
        if state.get(name) == 2:
            return
        assert state.get(name) != 1, 'import cycle: ' + ' -> '.join(trail + [name])
        state[name] = 1
        for other in sorted(graph.get(name, ())):
            visit(other, trail + [name])
        state[name] = 2

    for name in sorted(graph):
        visit(name, [])


@pytest.mark.source_only
def test_only_ros_imports_ros_and_the_core_stays_numpy_scipy():
    for name, (ours, theirs) in GRAPH.items():
        _, part = layer(name)
        if part not in ('ros', 'register_node') and name not in ROS_CLIENTS:
            ros = sorted(filter(is_ros, theirs))
            assert not ros, f'{name} imports {ros}'
        if part == 'registration':
            assert theirs <= CORE_THIRD_PARTY, f'the core module {name} imports {theirs}'
            assert not any(layer(o)[1] in ('frontend', 'open3d_import') for o in ours), name


@pytest.mark.source_only
def test_open3d_is_imported_in_one_place():
    """Every module takes Open3D from open3d_import, which leaves open3d.ml and its kin out."""
    direct = sorted(name for name, (_, theirs) in GRAPH.items()
                    if 'open3d' in theirs and name != 'cgags_ros.open3d_import')
    assert not direct, f'{direct} import open3d: take it from cgags_ros.open3d_import'
    assert 'cgags_ros.open3d_import' in GRAPH['cgags_ros.frontend.features'][0]


@pytest.mark.source_only
def test_ros_is_wiring_only():
    """Every module of ros/ imports rclpy or a message package; ros/ stays small."""
    total = 0
    for name, path in modules().items():
        if layer(name)[1] != 'ros':
            continue
        total += len(path.read_text(encoding='utf-8').splitlines())
        if path.name != '__init__.py':
            assert any(map(is_ros, GRAPH[name][1])), (
                f'{name} imports neither rclpy nor a message package: what works without ROS '
                'belongs in engine/ (what the node decides) or below')
    assert 0 < total <= ROS_MAX_LINES, (
        f'ros/ holds {total} lines: it wires topics, services and parameters to the engine; '
        'decisions belong in engine/')


@pytest.mark.subprocess
def test_importing_the_package_sets_no_environment_and_the_entry_points_do():
    """The idle-thread settings belong to the processes that run the pipeline, not to importers."""
    # (Open3D sets KMP_* variables of its own when it loads.)
    show = "print(os.environ.get('OMP_WAIT_POLICY'), os.environ.get('OPENBLAS_THREAD_TIMEOUT'))"
    code = ('import os; import cgags_ros.pipeline.register, cgags_ros.engine.engine, '
            f'cgags_ros.register_node; {show}; import cgags_ros.tools; {show}')
    env = {k: v for k, v in os.environ.items()
           if k not in ('OMP_WAIT_POLICY', 'OPENBLAS_THREAD_TIMEOUT')}
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                         check=True, env=env, cwd=PACKAGE.parent).stdout.split()
    assert out == ['None', 'None', 'PASSIVE', '20']


@pytest.mark.source_only
def test_the_checker_sees_real_edges():
    # The checks above can only fail if the parser finds the imports: pin a few known ones.
    assert 'cgags_ros.registration.search' in GRAPH['cgags_ros.registration.cgags'][0]
    assert 'cgags_ros.config.fields' in GRAPH['cgags_ros.config.node'][0]
    assert 'rclpy' in GRAPH['cgags_ros.ros.node'][1]
    assert 'diagnostic_msgs' in GRAPH['cgags_ros.ros.outputs'][1]
    assert not any(map(is_ros, GRAPH['cgags_ros.engine.engine'][1]))
    # a function-level import
    assert 'cgags_ros.pipeline.map' in GRAPH['cgags_ros.runtime.process'][0]


@pytest.mark.source_only
def test_no_module_holds_two_ideas_by_its_length():
    long = {name: n for name, path in modules().items()
            if (n := len(path.read_text(encoding='utf-8').splitlines())) > MODULE_MAX_LINES}
    assert not long, f'modules over {MODULE_MAX_LINES} lines (split them by idea): {long}'
