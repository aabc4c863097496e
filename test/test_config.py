"""cgags_ros.config: generated YAML and docs equal the dataclass defaults; validation."""

from __future__ import annotations

from pathlib import Path

from cgags_ros.config import fields, load_yaml, PipelineConfig
from cgags_ros.config.calibration import CalibrationConfig
from cgags_ros.config.files import parameters_markdown, ros_parameters_yaml
from cgags_ros.config.node import (
    calibration_config,
    configs_from_file,
    configs_from_parameters,
    NodeConfig,
    parameter_descriptions,
    ros_parameter_descriptions,
)
from cgags_ros.errors import InvalidConfigError
import pytest

ROOT = Path(__file__).resolve().parents[1]
YAML = ROOT / 'config' / 'register_node.yaml'
DOCS = ROOT / 'docs' / 'parameters.md'
# The node's ROS parameters: the keys declared ros=True, nothing else.
ROS_NAMES = [
    'voxel_size', 'frontend.normal_orientation', 'core.motion_model', 'core.gravity',
    'core.time_budget', 'tracking.enabled', 'mode', 'autostart', 'config_file', 'pairing.mode',
    'pairing.sync_slop',
    'pairing.queue_depth', 'pairing.source_qos', 'pairing.target_durability',
    'runtime.registration_timeout', 'map.file', 'map.frame', 'map.cache_dir',
    'relocalization.publish_initial_pose', 'relocalization.base_from_sensor',
    'relocalization.min_ratio', 'output.pose_frame_id', 'output.publish_invalid',
    'output.publish_aligned_cloud', 'output.broadcast_tf', 'output.diagnostics_period']


@pytest.mark.source_only
def test_checked_in_yaml_and_docs_are_the_generated_ones():
    assert YAML.read_text(encoding='utf-8') == ros_parameters_yaml(), (
        'config/register_node.yaml is stale; regenerate it with '
        '`python -m cgags_ros.config.files yaml > config/register_node.yaml`')
    assert DOCS.read_text(encoding='utf-8') == parameters_markdown(), (
        'docs/parameters.md is stale; regenerate it with '
        '`python -m cgags_ros.config.files docs > docs/parameters.md`')


def test_yaml_holds_the_ros_parameters_at_their_defaults():
    values = load_yaml(YAML)
    assert list(values) == list(ros_parameter_descriptions()) == ROS_NAMES
    assert list(values)[0] == 'voxel_size' and len(values) <= 26
    assert values['core.gravity'] == [0.0, 0.0, 1.0]
    assert values['relocalization.base_from_sensor'] == [0.0] * 7
    assert {name.split('.')[0] for name in values if '.' in name} == {
        'frontend', 'core', 'pairing', 'runtime', 'map', 'relocalization', 'output',
        'tracking'}
    pipe, node = configs_from_parameters(values)
    assert pipe == PipelineConfig() and node == NodeConfig()
    # one name per setting: the ROS name is the key, and reads the same field
    assert (node.pairing.mode, node.map.file, pipe.core.gravity) == (
        'latest_target', '', (0.0, 0.0, 1.0))


def test_the_ros_flag_is_on_the_declaration_and_never_on_a_research_switch():
    desc = parameter_descriptions()
    assert [k for k, m in desc.items() if m['ros']] == ROS_NAMES
    assert not [k for k, m in desc.items() if m['ros'] and m['advanced']]
    with pytest.raises(ValueError, match='never a ROS parameter'):
        fields.option(1, 'a research switch', advanced=True, ros=True)


def test_vectors_are_arrays_validated_as_numbers():
    pipe, node = configs_from_parameters({
        'core.gravity': [0.0, 2.0, 0.0],
        'relocalization.base_from_sensor': [0.1, 0.0, 0.5, 0.0, 0.0, 0.0, 1.0]})
    assert pipe.core.gravity_axis == (0.0, 1.0, 0.0) and pipe.core.gravity == (0.0, 2.0, 0.0)
    assert node.relocalization.sensor_pose == (0.1, 0.0, 0.5, 0.0, 0.0, 0.0, 1.0)
    assert NodeConfig().relocalization.sensor_pose is None  # seven zeros: unset
    for values, match in [
            ({'core.gravity': [0.0, 1.0]}, 'core.gravity must be a list of 3'),
            ({'core.gravity': [0.0, 0.0, 0.0]}, 'zero length'),
            ({'core.gravity': [0.0, float('nan'), 1.0]}, 'finite'),
            ({'core.gravity': '0 0 1'}, 'core.gravity must be a list'),
            ({'core.gravity': [0.0, True, 1.0]}, 'core.gravity'),
            ({'relocalization.base_from_sensor': [1.0, 2.0, 3.0]}, 'base_from_sensor'),
            ({'relocalization.base_from_sensor': [1.0, 2.0, 3.0, 0, 0, 0, 0]},
             'nonzero quaternion')]:
        with pytest.raises(InvalidConfigError, match=match):
            configs_from_parameters(values)


def test_config_file_may_hold_any_key_in_any_layout(tmp_path):
    extra = tmp_path / 'extra.yaml'
    extra.write_text('core:\n  edge_tournament: 4\npairing.max_waiting_sources: 4\n'
                     'pairing:\n  mode: synchronized\ncore.gravity: [0.0, 0.0, -1.0]\n')
    pipe, node = configs_from_file(str(extra))
    assert pipe.core.edge_tournament == 4 and pipe.core.gravity == (0.0, 0.0, -1.0)
    assert node.pairing.max_waiting_sources == 4 and node.pairing.mode == 'synchronized'
    wrapped = tmp_path / 'wrapped.yaml'  # a ROS parameter file reads the same
    wrapped.write_text('register_node:\n  ros__parameters:\n    pairing.mode: synchronized\n'
                       '    core:\n      edge_tournament: 4\n')
    pipe, node = configs_from_file(str(wrapped))
    assert pipe.core.edge_tournament == 4 and node.pairing.mode == 'synchronized'
    assert configs_from_file('') == (PipelineConfig(), NodeConfig())
    for text, match in [('core:\n  edge_sampling: uniform\n', "'core.edge_sampling'"),
                        ('pairing_mode: synchronized\n', "'pairing_mode'")]:
        extra.write_text(text)
        with pytest.raises(InvalidConfigError, match=f'unknown configuration key {match}'):
            configs_from_file(str(extra))


def test_every_parameter_is_documented_and_short():
    text = DOCS.read_text(encoding='utf-8')
    for name, meta in parameter_descriptions().items():
        assert f'`{name}`' in text
        # Descriptions say what a value means; measurements belong in docs/.
        assert len(meta['description']) <= 400, name
    advanced = [k for k, m in parameter_descriptions().items() if m['advanced']]
    assert 'core.edge_tournament' in advanced and 'voxel_size' not in advanced
    assert len(advanced) <= 12
    calibration = [k for k in fields.describe(CalibrationConfig) if not k.startswith('pipeline.')]
    assert len(parameter_descriptions()) + len(calibration) <= 90  # the options a user sets


def test_node_and_pipeline_keys_are_disjoint_and_described():
    desc = parameter_descriptions()
    assert set(desc) == set(fields.flatten(PipelineConfig())) | set(fields.flatten(NodeConfig()))
    assert not set(fields.flatten(PipelineConfig())) & set(fields.flatten(NodeConfig()))
    assert {'voxel_size', 'core.p1', 'frontend.fpfh_radius_factor', 'pairing.mode',
            'core.inlier_threshold', 'gates.min_fitness', 'gates.ambiguity_ratio'} <= set(desc)
    read_only = {k for k, m in desc.items() if m['read_only']}
    assert {'pairing.mode', 'map.file', 'config_file'} <= read_only
    assert read_only <= set(fields.flatten(NodeConfig()))
    assert all(meta['description'] for meta in desc.values())


@pytest.mark.parametrize('values, match', [
    ({'pairing.mode': 'nearest'}, 'pairing.mode'),
    ({'pairing.sync_slop': -0.1}, 'pairing.sync_slop'),
    ({'pairing_mode': 'nearest'}, 'pairing_mode'),
    ({'core.p1': 2.0}, 'core.p1'),
    ({'voxel_size': 'big'}, 'voxel_size'),
    ({'no_such_key': 1}, 'no_such_key'),
])
def test_invalid_values_name_the_key(values, match):
    with pytest.raises(InvalidConfigError, match=match):
        configs_from_parameters(values)


def test_flat_changes_apply_over_a_base():
    pipe, node = configs_from_parameters({'voxel_size': 0.3, 'pairing.sync_slop': 0.1})
    pipe2, node2 = configs_from_parameters({'core.p1': 0.9}, base=(pipe, node))
    assert (pipe2.voxel_size, pipe2.core.p1, node2.pairing.sync_slop) == (0.3, 0.9, 0.1)
    assert pipe.core.p1 == PipelineConfig().core.p1  # base untouched


def test_calibrate_mode_takes_calibration_keys_from_config_file(tmp_path):
    extra = tmp_path / 'calibration.yaml'
    extra.write_text('calibration:\n  max_frames: 4\n  min_agreement: 1.0\n')
    pipe, node = configs_from_parameters({'mode': 'calibrate', 'voxel_size': 0.25,
                                          'config_file': str(extra)})
    cal = calibration_config(pipe, str(extra))
    assert node.mode == 'calibrate' and cal.max_frames == 4 and cal.min_agreement == 1.0
    assert cal.pipeline.voxel_size == 0.25  # the node's pipeline
    extra.write_text('calibration:\n  pipeline:\n    voxel_size: 0.5\n')
    with pytest.raises(InvalidConfigError, match='top level'):
        calibration_config(pipe, str(extra))
    with pytest.raises(InvalidConfigError, match='map.file'):
        configs_from_parameters({'mode': 'calibrate', 'map.file': 'map.ply'})
    extra.write_text('calibration:\n  max_frames: 0\n')
    with pytest.raises(InvalidConfigError, match='max_frames'):
        calibration_config(pipe, str(extra))


def test_the_tools_read_the_node_format(tmp_path):
    from cgags_ros.config.node import calibration_from_keys, pipeline_from_keys
    from cgags_ros.tools import calibrate_cli, register_cli

    node_file = tmp_path / 'node.yaml'  # one file for the node, cgags-register, cgags-calibrate
    node_file.write_text('register_node:\n  ros__parameters:\n    voxel_size: 0.2\n'
                         '    pairing.mode: synchronized\n    core:\n      p1: 0.9\n'
                         '    calibration.max_frames: 4\n')
    pipe = pipeline_from_keys(load_yaml(node_file))
    assert (pipe.voxel_size, pipe.core.p1) == (0.2, 0.9)
    args = register_cli.build_parser().parse_args(
        ['a.ply', 'b.ply', '--config', str(node_file), '--set', 'core.gravity=[0, 1, 0]'])
    assert register_cli.config_from_args(args).core.gravity == (0.0, 1.0, 0.0)
    args = calibrate_cli.build_parser().parse_args(
        ['--parent', 'p.ply', '--child', 'c.ply', '--config', str(node_file),
         '--set', 'calibration.min_agreement=1.0'])
    cal = calibrate_cli._config(args)
    assert (cal.pipeline.voxel_size, cal.pipeline.core.p1, cal.max_frames, cal.min_agreement) \
        == (0.2, 0.9, 4, 1.0)
    assert calibration_from_keys({}).pipeline.voxel_size == 0.3  # the calibration's default
    with pytest.raises(InvalidConfigError, match="unknown configuration key 'pairing.nope'"):
        pipeline_from_keys({'pairing.nope': 1})  # the node's keys are checked, not ignored
