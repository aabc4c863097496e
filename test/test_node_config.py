"""cgags_ros.node_config: the generated YAML equals the dataclass defaults; validation."""

from __future__ import annotations

from pathlib import Path

import pytest

from cgags_ros import configutil
from cgags_ros.config import PipelineConfig, load_yaml
from cgags_ros.errors import InvalidConfigError
from cgags_ros.node_config import (READ_ONLY, NodeConfig, configs_from_parameters,
                                   default_parameters, parameter_descriptions,
                                   ros_parameters_yaml)

YAML = Path(__file__).resolve().parents[1] / "config" / "register_node.yaml"


def test_checked_in_yaml_is_the_generated_one():
    assert YAML.read_text(encoding="utf-8") == ros_parameters_yaml(), (
        "config/register_node.yaml is stale; regenerate it with "
        "`python -m cgags_ros.node_config > config/register_node.yaml`")


def test_yaml_values_equal_dataclass_defaults():
    values = load_yaml(YAML)
    assert values == default_parameters()
    pipe, node = configs_from_parameters(values)
    assert pipe == PipelineConfig() and node == NodeConfig()


def test_node_and_pipeline_keys_are_disjoint_and_described():
    desc = parameter_descriptions()
    assert set(desc) == set(default_parameters())
    assert {"voxel_size", "core.p1", "frontend.fpfh_radius_factor", "pairing_mode"} <= set(desc)
    assert READ_ONLY <= set(configutil.flatten(NodeConfig()))
    assert all(meta["description"] for meta in desc.values())


@pytest.mark.parametrize("values, match", [
    ({"pairing_mode": "nearest"}, "pairing_mode"),
    ({"sync_slop": -0.1}, "sync_slop"),
    ({"core.p1": 2.0}, "core.p1"),
    ({"voxel_size": "big"}, "voxel_size"),
    ({"no_such_key": 1}, "no_such_key"),
])
def test_invalid_values_name_the_key(values, match):
    with pytest.raises(InvalidConfigError, match=match):
        configs_from_parameters(values)


def test_flat_changes_apply_over_a_base():
    pipe, node = configs_from_parameters({"voxel_size": 0.3, "sync_slop": 0.1})
    pipe2, node2 = configs_from_parameters({"core.p1": 0.9}, base=(pipe, node))
    assert (pipe2.voxel_size, pipe2.core.p1, node2.sync_slop) == (0.3, 0.9, 0.1)
    assert pipe.core.p1 == PipelineConfig().core.p1  # base untouched
