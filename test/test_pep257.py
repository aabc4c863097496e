# Copyright 2015 Open Source Robotics Foundation, Inc.
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

from ament_pep257.main import main
import pytest

# The package root (holds setup.py): checked whatever the cwd of pytest.
PACKAGE_ROOT = Path(__file__).resolve().parents[1]
# Generated folders that may sit in the package root. Folders whose names start
# with '.' or '_' (.venv, .git, __pycache__) are skipped by ament_pep257 itself.
GENERATED = ('build', 'install', 'log', 'out')


@pytest.mark.linter
@pytest.mark.pep257
def test_pep257(monkeypatch):
    monkeypatch.chdir(PACKAGE_ROOT)
    # '.' holds test/ too: naming it again would check every test module twice.
    rc = main(argv=['.', '--exclude', *(str(PACKAGE_ROOT / name) for name in GENERATED)])
    assert rc == 0, 'Found code style errors / warnings'
