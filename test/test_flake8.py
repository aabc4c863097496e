# Copyright 2017 Open Source Robotics Foundation, Inc.
#
# Licensed under the Apache License, Version 2.0 (the "License");
# you may not use this file except in compliance with the License.
# You may obtain a copy of the License at
#
#     http://www.apache.org/licenses/LICENSE-2.0
#
# Unless required by applicable law or agreed to in writing, software
# distributed under the License is distributed on an "AS IS" BASIS,
# WITHOUT WARRANTIES OR CONDITIONS OF ANY KIND, either express or implied.
# See the License for the specific language governing permissions and
# limitations under the License.

from pathlib import Path
import subprocess
import sys

import pytest

# The package root (holds setup.py): checked whatever the cwd of pytest.
PACKAGE_ROOT = Path(__file__).resolve().parents[1]
# Generated folders that may sit in the package root. Folders whose names start
# with '.' or '_' (.venv, .git, __pycache__) are skipped by ament_flake8 itself.
GENERATED = ('build', 'install', 'log', 'out')


@pytest.mark.flake8
@pytest.mark.linter
def test_flake8():
    # A fresh interpreter: flake8 forks worker processes, and a fork of this one (which
    # earlier tests left with DDS, executor and OpenMP threads) can crash in its workers.
    run = subprocess.run(
        [sys.executable, '-m', 'ament_flake8.main', '--exclude',
         *(str(PACKAGE_ROOT / name) for name in GENERATED)],
        cwd=PACKAGE_ROOT, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, f'flake8 found code style errors:\n{run.stdout}{run.stderr}'
