"""cgags_ros.config: generated YAML and docs equal the dataclass defaults; validation."""

from __future__ import annotations

from pathlib import Path

from cgags_ros.config import fields, load_yaml, PipelineConfig
from cgags_ros.config.core import CoreConfig
from cgags_ros.config.files import migration_markdown, parameters_markdown, ros_parameters_yaml
from cgags_ros.config.node import (
    configs_from_parameters,
    default_parameters,
    NodeConfig,
    parameter_descriptions,
    READ_ONLY,
)
from cgags_ros.config.ros_parameters import (
    configs_from_ros,
    keys_to_ros,
    migration,
    NEWER_SECTIONS,
    ros_parameter_descriptions,
    ROS_PARAMETERS,
)
from cgags_ros.errors import InvalidConfigError
import pytest

ROOT = Path(__file__).resolve().parents[1]
YAML = ROOT / 'config' / 'register_node.yaml'
DOCS = ROOT / 'docs' / 'parameters.md'
MIGRATION = ROOT / 'docs' / 'parameter_migration.md'


def test_checked_in_yaml_and_docs_are_the_generated_ones():
    assert YAML.read_text(encoding='utf-8') == ros_parameters_yaml(), (
        'config/register_node.yaml is stale; regenerate it with '
        '`python -m cgags_ros.config.files yaml > config/register_node.yaml`')
    assert DOCS.read_text(encoding='utf-8') == parameters_markdown(), (
        'docs/parameters.md is stale; regenerate it with '
        '`python -m cgags_ros.config.files docs > docs/parameters.md`')
    assert MIGRATION.read_text(encoding='utf-8') == migration_markdown(), (
        'docs/parameter_migration.md is stale; regenerate it with '
        '`python -m cgags_ros.config.files migration > docs/parameter_migration.md`')


def test_yaml_holds_the_ros_parameters_at_their_defaults():
    values = load_yaml(YAML)
    assert list(values) == list(ros_parameter_descriptions()) == list(ROS_PARAMETERS)
    assert list(values)[0] == 'voxel_size' and len(values) <= 26
    assert values['core.gravity'] == [0.0, 0.0, 1.0]
    assert values['relocalization.base_from_sensor'] == [0.0] * 7
    assert {name.split('.')[0] for name in values if '.' in name} == {
        'frontend', 'core', 'pairing', 'map', 'relocalization', 'output', 'tracking'}
    pipe, node = configs_from_ros(values)
    assert pipe == PipelineConfig() and node == NodeConfig()


def test_ros_vectors_config_file_and_former_names(tmp_path):
    extra = tmp_path / 'extra.yaml'
    extra.write_text('core:\n  edge_tournament: 4\nmax_waiting_sources: 4\n')
    values = dict(load_yaml(YAML), **{
        'config_file': str(extra), 'core.gravity': [0.0, 2.0, 0.0],
        'relocalization.base_from_sensor': [0.1, 0.0, 0.5, 0.0, 0.0, 0.0, 1.0]})
    pipe, node = configs_from_ros(values)
    assert pipe.core.gravity_axis == (0.0, 1.0, 0.0) and pipe.core.edge_tournament == 4
    assert node.max_waiting_sources == 4 and node.base_from_sensor.split()[2] == '0.5'
    with pytest.raises(InvalidConfigError, match='core.gravity'):
        configs_from_ros({'core.gravity': [0.0, 1.0]})
    with pytest.raises(InvalidConfigError, match='base_from_sensor'):
        configs_from_ros({'relocalization.base_from_sensor': [1.0, 2.0, 3.0]})
    extra.write_text('core:\n  edge_sampling: uniform\n')  # settled by the ablation: gone
    with pytest.raises(InvalidConfigError, match="'core.edge_sampling' was removed"):
        configs_from_ros({'config_file': str(extra)})
    extra.write_text('pairing_mode: synchronized\n')  # a ROS parameter's key: refused
    with pytest.raises(InvalidConfigError, match="'pairing.mode'"):
        configs_from_ros({'config_file': str(extra)})
    # flat keys split back into ROS values and the rest, losslessly
    ros, rest = keys_to_ros({'voxel_size': 0.2, 'core.gravity_z': -1.0, 'source_depth': 9})
    assert ros == {'voxel_size': 0.2, 'core.gravity': [0.0, 0.0, -1.0]}
    assert rest == {'source_depth': 9}
    assert migration()['pairing_mode'] == 'renamed: pairing.mode'
    assert migration()['core.gravity_x'] == 'renamed: core.gravity'
    assert 'config_file' in migration()['core.edge_tournament']
    assert migration()['core.edge_sampling'].startswith('removed')
    assert not set(migration()) & set(ROS_PARAMETERS)
    unchanged = set(ROS_PARAMETERS) & set(parameter_descriptions())
    assert {'voxel_size', 'autostart', 'config_file', 'core.motion_model'} <= unchanged
    assert migration()['relocalization.mode'].startswith('renamed: mode')
    removed = {f'core.{name}' for name in CoreConfig.REMOVED}
    assert not removed & set(parameter_descriptions())
    newer = {k for k in parameter_descriptions() if k.startswith(NEWER_SECTIONS)}
    assert 'tracking.enabled' in newer  # never a ROS parameter: nothing to migrate
    assert set(migration()) == (set(parameter_descriptions()) - unchanged - newer) | {
        'relocalization.mode'} | removed


def test_every_parameter_is_documented_and_short():
    text = DOCS.read_text(encoding='utf-8')
    for name, meta in parameter_descriptions().items():
        assert f'`{name}`' in text
        # Descriptions say what a value means; measurements belong in docs/.
        assert len(meta['description']) <= 400, name
    advanced = [k for k, m in parameter_descriptions().items() if m['advanced']]
    assert 'core.edge_tournament' in advanced and 'voxel_size' not in advanced
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


def test_calibrate_mode_takes_calibration_keys_from_config_file(tmp_path):
    from cgags_ros.config.ros_parameters import calibration_config
    extra = tmp_path / 'calibration.yaml'
    extra.write_text('calibration:\n  max_frames: 4\n  min_agreement: 1.0\n')
    pipe, node = configs_from_ros({'mode': 'calibrate', 'voxel_size': 0.25,
                                   'config_file': str(extra)})
    cal = calibration_config(pipe, str(extra))
    assert node.mode == 'calibrate' and cal.max_frames == 4 and cal.min_agreement == 1.0
    assert cal.pipeline.voxel_size == 0.25  # the node's pipeline
    extra.write_text('calibration:\n  pipeline:\n    voxel_size: 0.5\n')
    with pytest.raises(InvalidConfigError, match='top level'):
        calibration_config(pipe, str(extra))
    with pytest.raises(InvalidConfigError, match='map.file'):
        configs_from_ros({'mode': 'calibrate', 'map.file': 'map.ply'})
    extra.write_text('calibration:\n  max_frames: 0\n')
    with pytest.raises(InvalidConfigError, match='max_frames'):
        calibration_config(pipe, str(extra))
