"""
README.md as a user reads it: its commands parse, its examples run, its links resolve.

Each `cgags-*` command in README (code blocks and inline code) is parsed by that tool's own
argument parser; each `-p name:=value` is a ROS parameter of register_node and its value is
accepted; the Python block and the `cgags-register` line run on the committed LiDAR fixture
(test/fixtures/small_gicp/) and meet its ground truth. No shared data is needed. Which test
or script runs each README command: docs/design.md, "README commands and what runs them".
"""

from __future__ import annotations

import json
from pathlib import Path
import re
import shlex

from cgags_ros.config.node import configs_from_parameters, ros_parameter_descriptions
from cgags_ros.geometry import rotation_error_deg, translation_error
from cgags_ros.tools import calibrate_cli, map_cli, register_cli, relocalize_cli, replay
import numpy as np
import pytest
from test_docs import broken_links
import yaml

REPO = Path(__file__).resolve().parents[1]
README = REPO / 'README.md'
FIXTURE = REPO / 'test' / 'fixtures' / 'small_gicp'
PARSERS = {'cgags-register': register_cli.build_parser, 'cgags-replay': replay.build_parser,
           'cgags-calibrate': calibrate_cli.build_parser,
           'cgags-relocalize': relocalize_cli.build_parser, 'cgags-map': map_cli.build_parser}
# Two consecutive scans of the fixture: a right answer is within a degree and decimetres.
MAX_RE_DEG, MAX_TE_M = 2.0, 0.2


def _text() -> str:
    return README.read_text(encoding='utf-8')


def _blocks(language: str) -> list[str]:
    return re.findall(rf'^```{language}\n(.*?)^```', _text(), flags=re.M | re.S)


def _shell_commands() -> list[list[str]]:
    """Return every command of README's bash blocks and inline code, split as a shell does."""
    lines = []
    for block in _blocks('bash'):
        lines += block.replace('\\\n', ' ').splitlines()
    lines += re.findall(r'`([^`\n]+)`', re.sub(r'^```.*?^```', '', _text(), flags=re.M | re.S))
    commands = []
    for line in lines:
        for part in re.split(r'&&|;', line):
            words = shlex.split(part, comments=True)
            if words:
                commands.append(words)
    return commands


def _tool_commands() -> list[list[str]]:
    return [words for words in _shell_commands() if words[0] in PARSERS]


@pytest.mark.source_only
def test_readme_is_short_and_free_of_run_by_run_figures():
    text = _text()
    assert len(text.splitlines()) <= 150
    commit = r'\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*\d)[0-9a-f]{7,40}\b'
    for pattern in (r'this machine', r'\b(first|second|third|fourth|fifth) pass\b',
                    r'\bissue \d+', commit, r'\b20\d\d-\d\d-\d\d\b'):
        assert not re.search(pattern, text, flags=re.I), pattern


def test_every_tool_of_readme_is_shown_and_its_commands_parse():
    commands = _tool_commands()
    assert {words[0] for words in commands} == set(PARSERS)
    for words in commands:
        try:
            PARSERS[words[0]]().parse_args(words[1:])
        except SystemExit:
            pytest.fail(f'README command does not parse: {shlex.join(words)}')


def test_ros_parameters_of_readme_exist_and_are_accepted():
    names = ros_parameter_descriptions()
    given = re.findall(r'-p\s+"?([\w.]+):=([^\s`"]+)', _text())
    assert given, 'README gives no -p name:=value'
    for name, value in given:
        assert name in names, f'README sets {name}, which is no ROS parameter of register_node'
        configs_from_parameters({name: yaml.safe_load(value)})


@pytest.mark.source_only
def test_ros2_run_names_the_installed_executable():
    runs = [words for words in _shell_commands()
            if words[:2] == ['ros2', 'run'] and len(words) > 2]
    assert runs
    setup = (REPO / 'setup.py').read_text(encoding='utf-8')
    for words in runs:
        assert words[2] == 'cgags_ros' and f"'{words[3]} = " in setup, words


def _ground_truth() -> np.ndarray:
    return np.loadtxt(FIXTURE / 'T_target_source.txt')


def test_python_block_runs_on_the_fixture(monkeypatch, capsys):
    (block,) = _blocks('python')
    monkeypatch.chdir(REPO)
    scope: dict = {}
    exec(compile(block, str(README), 'exec'), scope)
    result = scope['result']
    assert result.valid, result.reason
    T = np.asarray(result.transform)
    assert rotation_error_deg(T, _ground_truth()) < MAX_RE_DEG
    assert translation_error(T, _ground_truth()) < MAX_TE_M
    assert 'True' in capsys.readouterr().out


def test_register_command_runs_on_the_fixture(monkeypatch, capsys):
    (words,) = [w for w in _tool_commands() if w[0] == 'cgags-register']
    monkeypatch.chdir(REPO)
    assert register_cli.main(words[1:]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data['valid'], data.get('reason')
    T = np.asarray(data['transform'])
    assert rotation_error_deg(T, _ground_truth()) < MAX_RE_DEG
    assert translation_error(T, _ground_truth()) < MAX_TE_M


@pytest.mark.source_only
def test_readme_links_resolve():
    assert broken_links(README) == []
