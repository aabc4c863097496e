"""
The settings a ``cgags-tune`` user fixes (``--config``, ``--set``): checked, kept, written.

Some settings no tuner can find: where a sensor stood in a cloud's frame
(``frontend.source_sensor``, ``frontend.target_sensor``, docs/frames.md), or what the user
already knows. The user fixes them, read as ``cgags-replay --config`` and ``--set`` read
them (:func:`~.replay_common.user_parameters`); they apply to every trial, the start
included, and the search never proposes a value for one (:func:`.tuning.search_space`).

They are checked before any trial (:func:`check`): every key must be one of the node's
with a value it takes; a map (``map.file``) or calibrate mode has no target clouds to
replay; ``--live`` can set only the node's ROS parameters that change at run time (start
the node with the others); a fixed ``voxel_size`` leaves no voxel to start from.

:func:`write_params` writes them with the tuned settings: the ROS parameters in
``params.yaml``, the keys that are none (the sensors' positions) in ``config.yaml``
beside it, which ``params.yaml`` names as the node's ``config_file``. The node reads it so,
and ``cgags-replay --config params.yaml`` follows it as the node does
(:func:`~.replay_common.config_keys`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

from . import tuning
from ..config.node import CALIBRATION_PREFIX, configs_from_parameters, parameter_descriptions
from ..config.node import ros_value
from ..errors import InvalidConfigError

CONFIG_NAME = 'config.yaml'  # beside params.yaml: the fixed keys that are no ROS parameters


def check(fixed: Mapping[str, Any], live: bool, voxel_size: float | None) -> None:
    """Raise InvalidConfigError for fixed settings no trial could run with (module doc)."""
    if not fixed:
        return
    if 'config_file' in fixed:
        raise InvalidConfigError('--set config_file: give the file as --config (its '
                                 'config_file is read as the node reads it)')
    try:
        if any(key.startswith(CALIBRATION_PREFIX) for key in fixed):
            raise InvalidConfigError('calibration.* keys configure calibrate mode, which '
                                     'cgags-tune does not tune (docs/calibration.md)')
        _, node = configs_from_parameters(fixed)
    except InvalidConfigError as exc:
        raise InvalidConfigError(f'--config/--set: {exc}') from None
    if node.map.file:
        raise InvalidConfigError("--config/--set: map.file: cgags-tune replays the bags' "
                                 'target clouds, not a map; leave map.file out')
    if node.mode == 'calibrate':
        raise InvalidConfigError('--config/--set: mode calibrate calibrates, it is not '
                                 'tuned (docs/calibration.md); leave mode out')
    if voxel_size is not None and 'voxel_size' in fixed:
        raise InvalidConfigError('--voxel-size starts the voxel search, and --config/--set '
                                 'fix voxel_size: give one of them')
    if live:
        meta = parameter_descriptions()
        cannot = sorted(k for k in fixed if not meta[k]['ros'] or meta[k]['read_only'])
        if cannot:
            raise InvalidConfigError(
                f"--live sets the node's parameters at run time, and {', '.join(cannot)} "
                'cannot be (no ROS parameter, or read-only): start the node with them (its '
                'config_file or --params-file) and leave them out of --config/--set')


def non_ros_keys(fixed: Mapping[str, Any]) -> dict[str, Any]:
    """Return the fixed keys that are no ROS parameter of the node (its config_file's)."""
    meta = parameter_descriptions()
    return {k: v for k, v in fixed.items() if not meta[k]['ros']}


def write_params(out: Path, written: Mapping[str, Any], fixed: Mapping[str, Any],
                 comment: str) -> dict[str, Path]:
    """
    Write ``params.yaml`` (and ``config.yaml`` when needed) of the written and fixed settings.

    Return the paths written, by name (``params``, and ``config``).
    """
    import yaml

    config = non_ros_keys(fixed)
    settings = {**{k: v for k, v in fixed.items() if k not in config}, **written}
    paths = {'params': out / 'params.yaml'}
    if config:
        paths['config'] = out / CONFIG_NAME
        paths['config'].write_text(
            '# cgags-tune: settings fixed by the user that are no ROS parameters; params.yaml '
            'names this file as config_file\n' + yaml.safe_dump(
                {k: ros_value(v) for k, v in sorted(config.items())}, sort_keys=False),
            encoding='utf-8')
        settings['config_file'] = str(paths['config'].resolve())
        comment += f'\nconfig_file: the fixed settings that are no ROS parameters ({CONFIG_NAME})'
    paths['params'].write_text(tuning.params_yaml(settings, comment), encoding='utf-8')
    return paths


def note(fixed: Mapping[str, Any]) -> str:
    """Return the report's line on the fixed settings ('' when none)."""
    if not fixed:
        return ''
    return ('fixed by the user (--config/--set; every trial, never searched): '
            + ', '.join(f'{k} {ros_value(v)}' for k, v in sorted(fixed.items())))
