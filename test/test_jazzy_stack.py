"""
ROS 2 Jazzy's Python stack as README's Jazzy install leaves it (scripts/jazzy_env.sh).

These run in the emulated stack only (`CGAGS_JAZZY_STACK=1`, set by scripts/test.sh for its
second run): a copy of CPython 3.12 holding apt's numpy, scipy, matplotlib and PyYAML versions and
the ROS wheels, marked externally managed as Ubuntu 24.04's system Python is, with the project's
requirements installed into a `--system-site-packages` virtual environment on top. The rest of the
suite (the node over DDS, replay, colcon) runs in that same environment.
"""

import json
import os
from pathlib import Path
import subprocess
import sys

import pytest

JAZZY = os.environ.get('CGAGS_JAZZY_STACK') == '1'
ROOT = Path(__file__).resolve().parents[1]
APT_VERSIONS = {'numpy': '1.26.4', 'scipy': '1.11.4', 'matplotlib': '3.6.3', 'yaml': '6.0.1'}

pytestmark = [pytest.mark.subprocess, pytest.mark.skipif(
    not JAZZY, reason='runs in the emulated Jazzy stack (scripts/test.sh runs the suite there)')]


def _system_python() -> str:
    return str(Path(sys.base_prefix) / 'bin' / 'python3')


def test_python_is_jazzys_in_a_venv_over_the_system():
    assert sys.version_info[:2] == (3, 12)
    assert sys.prefix != sys.base_prefix


@pytest.mark.parametrize('module', sorted(APT_VERSIONS))
def test_apt_packages_come_from_the_system_unchanged(module):
    imported = __import__(module)
    assert imported.__version__ == APT_VERSIONS[module]
    assert imported.__file__.startswith(sys.base_prefix), imported.__file__


def test_system_python_refuses_pip_as_noble_does():
    run = subprocess.run([_system_python(), '-m', 'pip', 'install', '--no-index', 'numpy'],
                         capture_output=True, text=True)
    assert run.returncode != 0
    assert 'externally-managed-environment' in run.stdout + run.stderr


def test_installing_the_requirements_again_changes_nothing_of_the_system():
    """A dry run of README's `pip install -r requirements.txt`: pip keeps apt's packages."""
    run = subprocess.run(
        [sys.executable, '-m', 'pip', 'install', '--dry-run', '--quiet', '--report', '-',
         '-r', str(ROOT / 'requirements.txt')], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    would_install = {item['metadata']['name'].lower()
                     for item in json.loads(run.stdout)['install']}
    assert not would_install & {'numpy', 'scipy', 'matplotlib', 'pyyaml'}, would_install
