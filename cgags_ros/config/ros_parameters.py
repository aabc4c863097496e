"""
The node's ROS parameters: a short, grouped interface over the configuration keys.

ROS-free. Every ROS parameter sets one configuration key (``voxel_size``, ``pairing_mode``,
``core.motion_model``...) or, for a vector, several in order (``core.gravity`` ->
``core.gravity_x``, ``core.gravity_y``, ``core.gravity_z``); its description, range and
default come from that key's field (:mod:`.fields`), so nothing is written twice. Every
other key (the research switches of the method, rarely changed node options) is set in the
YAML file named by ``config_file`` (the format of ``cgags-register --config``: flat or
nested keys, or a ROS parameter file). A parameter name of the former flat interface given
to the node is refused with its new name (:func:`migration`).
"""

from __future__ import annotations

from typing import Any, Mapping

from . import fields
from .calibration import CalibrationConfig
from .core import CoreConfig
from .node import configs_from_parameters, NodeConfig, parameter_descriptions, parse_pose7
from .pipeline import load_yaml, PipelineConfig
from ..errors import InvalidConfigError

# ROS parameter -> the configuration key(s) it sets. Voxel size first; then by group.
ROS_PARAMETERS: dict[str, tuple[str, ...]] = {
    'voxel_size': ('voxel_size',),
    'mode': ('mode',),
    'autostart': ('autostart',),
    'config_file': ('config_file',),
    'frontend.normal_orientation': ('frontend.normal_orientation',),
    'core.motion_model': ('core.motion_model',),
    'core.gravity': ('core.gravity_x', 'core.gravity_y', 'core.gravity_z'),
    'core.time_budget': ('core.time_budget',),
    'core.registration_timeout': ('registration_timeout',),
    'pairing.mode': ('pairing_mode',),
    'pairing.sync_slop': ('sync_slop',),
    'pairing.queue_depth': ('queue_depth',),
    'pairing.source_qos': ('source_qos',),
    'pairing.target_durability': ('target_durability',),
    'map.file': ('map_file',),
    'map.frame': ('map_frame',),
    'map.cache_dir': ('map_cache_dir',),
    'relocalization.publish_initial_pose': ('publish_initial_pose',),
    'relocalization.base_from_sensor': ('base_from_sensor',),
    'relocalization.min_ratio': ('initial_pose_min_ratio',),
    'output.pose_frame_id': ('pose_frame_id',),
    'output.publish_invalid': ('publish_invalid',),
    'output.publish_aligned_cloud': ('publish_aligned_cloud',),
    'output.broadcast_tf': ('broadcast_tf',),
    'output.diagnostics_period': ('diagnostics_period',),
    'tracking.enabled': ('tracking.enabled',),
}
# ROS parameters of this interface renamed since -> what to do now.
RENAMED = {'relocalization.mode': 'renamed: mode (which also takes calibrate)'}
# Keys of config_file under this prefix configure calibrate mode (CalibrationConfig keys).
CALIBRATION_PREFIX = 'calibration.'
# Sections and keys (by prefix) added after the flat interface was retired: never ROS
# parameters, nothing to migrate.
NEWER_SECTIONS = ('tracking.', 'backlog')
# base_from_sensor as a ROS parameter: [x, y, z, qx, qy, qz, qw]; seven zeros leave it unset.
UNSET_POSE = [0.0] * 7


def ros_parameter_descriptions() -> dict[str, dict[str, Any]]:
    """Return ``{ROS name: {description, default, low, high, choices, read_only}}``."""
    keys = parameter_descriptions()
    out = {}
    for name, sources in ROS_PARAMETERS.items():
        meta = dict(keys[sources[0]])
        if len(sources) > 1:
            meta['default'] = [keys[k]['default'] for k in sources]
            meta['description'] = (f"[{', '.join(k.rsplit('.', 1)[-1] for k in sources)}]: "
                                   + meta['description'])
        elif name == 'relocalization.base_from_sensor':
            meta['default'] = list(UNSET_POSE)
            meta['description'] = ('Sensor pose in the robot base frame, [x, y, z, qx, qy, '
                                   'qz, qw] (metres, unit quaternion): p_base = T p_sensor; '
                                   'seven zeros (the default) take it from TF (base_frame <- '
                                   'sensor frame) when tf2_ros is importable, else the '
                                   'identity.')
        meta['key'] = ', '.join(sources)
        out[name] = meta
    return out


def ros_to_keys(values: Mapping[str, Any]) -> dict[str, Any]:
    """Return the configuration keys set by ROS parameter ``values`` (vectors split)."""
    out: dict[str, Any] = {}
    for name, value in values.items():
        sources = ROS_PARAMETERS[name]
        if name == 'relocalization.base_from_sensor':
            out[sources[0]] = _pose_text(value)
        elif len(sources) > 1:
            items = list(value) if isinstance(value, (list, tuple)) or hasattr(value, 'tolist') \
                else None
            if items is None or len(items) != len(sources):
                raise InvalidConfigError(f'{name} must be {len(sources)} numbers, got {value!r}')
            out.update(zip(sources, items))
        else:
            out[sources[0]] = value
    return out


def _pose_text(value: Any) -> str:
    """Return ``base_from_sensor`` text of a 7-vector ('' for seven zeros)."""
    try:
        values = [float(v) for v in value]
    except (TypeError, ValueError):
        raise InvalidConfigError(f'relocalization.base_from_sensor must be [x, y, z, qx, qy, '
                                 f'qz, qw], got {value!r}') from None
    if values == UNSET_POSE:
        return ''
    text = ' '.join(repr(v) for v in values)
    parse_pose7(text)  # seven numbers, a nonzero quaternion, or InvalidConfigError
    return text


def configs_from_ros(values: Mapping[str, Any], *,
                     base: tuple[PipelineConfig, NodeConfig] | None = None
                     ) -> tuple[PipelineConfig, NodeConfig]:
    """
    Return validated configurations from ROS parameter values.

    Without ``base``: the defaults, then the keys of ``config_file`` (none of which may be a
    ROS parameter's), then ``values``. With ``base``: ``values`` over it (a run-time change).
    """
    keys = ros_to_keys(values)
    if base is None:
        extra = config_file_keys(str(keys.get('config_file', '')))
        base = configs_from_parameters(
            {k: v for k, v in extra.items() if not k.startswith(CALIBRATION_PREFIX)})
    pipe, node = configs_from_parameters(keys, base=base)
    if node.mode == 'calibrate' and node.map_file:
        raise InvalidConfigError('mode calibrate takes two live sensors (source_cloud = child, '
                                 'target_cloud = parent); map.file must be empty')
    return pipe, node


def calibration_config(pipeline: PipelineConfig, config_file: str) -> CalibrationConfig:
    """
    Return the :class:`CalibrationConfig` of calibrate mode.

    Its pipeline is the node's (``voxel_size`` and every pipeline key); the other
    calibration keys come from ``config_file`` under ``calibration.`` (``calibration.max_frames:
    5``); a ``calibration.pipeline.*`` key is refused, as the node's own keys set the pipeline.
    """
    keys = {k[len(CALIBRATION_PREFIX):]: v for k, v in config_file_keys(config_file).items()
            if k.startswith(CALIBRATION_PREFIX)}
    nested = sorted(k for k in keys if k.startswith('pipeline.'))
    if nested:
        raise InvalidConfigError(f'config_file {config_file}: calibration.{nested[0]}: set the '
                                 'pipeline keys at the top level (the node and the calibration '
                                 'share them)')
    return fields.update_from_flat(CalibrationConfig(pipeline=pipeline), keys)


def config_file_keys(path: str) -> dict[str, Any]:
    """Return the flat keys of ``config_file`` ({} for ''); a ROS parameter's key is refused."""
    if not path:
        return {}
    keys = fields.flatten_mapping(load_yaml(path))
    ros_keys = {k: name for name, ks in ROS_PARAMETERS.items() for k in ks}
    for key in keys:
        if key in ros_keys:
            raise InvalidConfigError(f'config_file {path}: {key!r} is the ROS parameter '
                                     f'{ros_keys[key]!r}; set it there')
    return keys


def keys_to_ros(flat: Mapping[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """
    Split flat configuration keys into (ROS parameter values, keys for ``config_file``).

    A vector parameter takes the defaults of the components ``flat`` does not give.
    """
    descriptions = parameter_descriptions()
    ros: dict[str, Any] = {}
    rest = dict(flat)
    for name, sources in ROS_PARAMETERS.items():
        if not any(k in rest for k in sources):
            continue
        if name == 'relocalization.base_from_sensor':
            pose = parse_pose7(str(rest.pop(sources[0])))
            ros[name] = list(pose) if pose else list(UNSET_POSE)
        elif len(sources) > 1:
            ros[name] = [float(rest.pop(k, descriptions[k]['default'])) for k in sources]
        else:
            ros[name] = rest.pop(sources[0])
    return ros, rest


def migration() -> dict[str, str]:
    """Return ``{former ROS parameter: what to do now}`` for every renamed or removed one."""
    renamed = {k: name for name, ks in ROS_PARAMETERS.items() for k in ks if k != name}
    out = dict(RENAMED)
    for key in parameter_descriptions():
        if key in ROS_PARAMETERS or key.startswith(NEWER_SECTIONS):
            continue
        if key in renamed:
            out[key] = f'renamed: {renamed[key]}'
        else:
            out[key] = 'not a ROS parameter any more: set it in the YAML of config_file'
    out.update({f'core.{name}': why for name, why in CoreConfig.REMOVED.items()})
    return out
