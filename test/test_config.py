"""cgags_ros.config: generated YAML and docs equal the dataclass defaults; validation."""

from __future__ import annotations

from pathlib import Path

from cgags_ros.config import fields, load_yaml, PipelineConfig
from cgags_ros.config.files import parameters_markdown, ros_parameters_yaml
from cgags_ros.config.node import (
    configs_from_parameters,
    default_parameters,
    NodeConfig,
    parameter_descriptions,
    READ_ONLY,
)
from cgags_ros.errors import InvalidConfigError
import pytest

ROOT = Path(__file__).resolve().parents[1]
YAML = ROOT / 'config' / 'register_node.yaml'
DOCS = ROOT / 'docs' / 'parameters.md'


def test_checked_in_yaml_and_docs_are_the_generated_ones():
    assert YAML.read_text(encoding='utf-8') == ros_parameters_yaml(), (
        'config/register_node.yaml is stale; regenerate it with '
        '`python -m cgags_ros.config.files yaml > config/register_node.yaml`')
    assert DOCS.read_text(encoding='utf-8') == parameters_markdown(), (
        'docs/parameters.md is stale; regenerate it with '
        '`python -m cgags_ros.config.files docs > docs/parameters.md`')


def test_yaml_holds_the_user_parameters_at_their_defaults():
    values = load_yaml(YAML)
    desc = parameter_descriptions()
    user = {k: v for k, v in default_parameters().items() if not desc[k]['advanced']}
    assert values == user
    assert 'voxel_size' in values and 'core.edge_sampling' not in values
    pipe, node = configs_from_parameters(values)
    assert pipe == PipelineConfig() and node == NodeConfig()


def test_every_parameter_is_documented_and_short():
    text = DOCS.read_text(encoding='utf-8')
    for name, meta in parameter_descriptions().items():
        assert f'`{name}`' in text
        # Descriptions say what a value means; measurements belong in docs/.
        assert len(meta['description']) <= 400, name
    advanced = [k for k, m in parameter_descriptions().items() if m['advanced']]
    assert 'core.edge_sampling' in advanced and 'voxel_size' not in advanced
    assert len(advanced) >= 12


def test_node_and_pipeline_keys_are_disjoint_and_described():
    desc = parameter_descriptions()
    assert set(desc) == set(default_parameters())
    assert {'voxel_size', 'core.p1', 'frontend.fpfh_radius_factor', 'pairing_mode'} <= set(desc)
    assert READ_ONLY <= set(fields.flatten(NodeConfig()))
    assert all(meta['description'] for meta in desc.values())


@pytest.mark.parametrize('values, match', [
    ({'pairing_mode': 'nearest'}, 'pairing_mode'),
    ({'sync_slop': -0.1}, 'sync_slop'),
    ({'core.p1': 2.0}, 'core.p1'),
    ({'voxel_size': 'big'}, 'voxel_size'),
    ({'no_such_key': 1}, 'no_such_key'),
])
def test_invalid_values_name_the_key(values, match):
    with pytest.raises(InvalidConfigError, match=match):
        configs_from_parameters(values)


def test_flat_changes_apply_over_a_base():
    pipe, node = configs_from_parameters({'voxel_size': 0.3, 'sync_slop': 0.1})
    pipe2, node2 = configs_from_parameters({'core.p1': 0.9}, base=(pipe, node))
    assert (pipe2.voxel_size, pipe2.core.p1, node2.sync_slop) == (0.3, 0.9, 0.1)
    assert pipe.core.p1 == PipelineConfig().core.p1  # base untouched
