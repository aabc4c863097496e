"""
The suite's own rules: markers that keep the fast loop fast, DDS modules that cannot meet.

``bash scripts/test.sh --fast`` deselects the markers ``ros``, ``subprocess`` and ``slow``
(setup.cfg): a module that starts DDS participants or processes without saying so would
slow the inner loop down or hang it. DDS modules run one after another in one pytest
process, each on its own ROS_DOMAIN_ID: a domain set in ``os.environ`` at import time is
shared by every module (pytest imports all before running any), and a bare
``executor.spin`` thread dies at the first callback exception.
"""

from pathlib import Path
import re

import pytest

HERE = Path(__file__).resolve().parent
MODULES = sorted(HERE.glob('test_*.py'))

DDS = re.compile(r'spun_context\(|rclpy\.init\(|RegisterNode\(|--live|'
                 r"'-m', 'cgags_ros\.register_node'")
PROCESS = re.compile(r'subprocess\.(run|Popen|check_output|call)\(|Supervisor\(|CheckLane\(|'
                     r'multiprocessing\.|colcon\', \'build')
DOMAIN = re.compile(r"^DOMAIN_ID = (\d+)|'ROS_DOMAIN_ID': '(\d+)'", re.M)


def marked(text: str, name: str) -> bool:
    """Return whether ``text`` marks tests (or the module) with ``pytest.mark.<name>``."""
    return re.search(rf'pytest\.mark\.{name}\b', text) is not None


@pytest.mark.parametrize('path', MODULES, ids=lambda p: p.name)
def test_dds_and_process_tests_are_marked(path):
    text = path.read_text()
    if DDS.search(text):
        assert marked(text, 'ros'), f'{path.name} uses DDS: mark it pytest.mark.ros'
    # The linters run their tool in a process of its own, briefly: they stay in the fast loop.
    if PROCESS.search(text) and path.name != Path(__file__).name and not marked(text, 'linter'):
        assert marked(text, 'subprocess') or marked(text, 'ros'), \
            f'{path.name} starts processes: mark those tests pytest.mark.subprocess'


def test_each_dds_module_has_its_own_domain():
    owners = {}
    for path in MODULES:
        if path.name == Path(__file__).name:
            continue
        text = path.read_text()
        assert "os.environ['ROS_DOMAIN_ID'] =" not in text, (
            f'{path.name} sets ROS_DOMAIN_ID at import: every module would share it; '
            'use spun_context(DOMAIN_ID, ...) and pass it to child processes')
        assert 'target=executor.spin' not in text, (
            f'{path.name} spins a bare executor thread: use waiting.spun_context')
        if DDS.search(text):
            found = {int(a or b) for a, b in DOMAIN.findall(text)}
            assert len(found) == 1, f'{path.name} uses DDS: declare one DOMAIN_ID ({found})'
            (domain,) = found
            assert domain not in owners, f'{path.name} and {owners.get(domain)} share {domain}'
            owners[domain] = path.name


def test_fast_markers_are_registered(pytestconfig):
    registered = {line.split(':')[0].strip() for line in pytestconfig.getini('markers')}
    assert {'ros', 'subprocess', 'slow'} <= registered
