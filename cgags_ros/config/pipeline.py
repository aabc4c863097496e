"""
Configuration of the whole pipeline: the per-layer dataclasses, composed.

Defaults live in the dataclasses; ``config/register_node.yaml`` is generated from them
(:mod:`cgags_ros.config.files`). ``voxel_size`` (metres) is the one scale every radius and
threshold derives from.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Mapping

from . import fields
from .core import CoreConfig
from .fields import option, section
from .frontend import FrontEndConfig, RefineConfig
from .gates import GatesConfig
from .regenerate import RegenerateConfig
from .tracking import TrackingConfig
from ..errors import InvalidConfigError


@dataclasses.dataclass
class PipelineConfig:
    """Everything ``register_clouds`` needs: the voxel size, each layer's options, a seed."""

    voxel_size: float = option(
        0.05, 'Voxel size in metres; normals, FPFH radii and thresholds derive from it.',
        low=1e-6, high=100.0, ros=True)
    frontend: FrontEndConfig = section(FrontEndConfig)
    core: CoreConfig = section(CoreConfig)
    refine: RefineConfig = section(RefineConfig)
    regenerate: RegenerateConfig = section(RegenerateConfig)
    gates: GatesConfig = section(GatesConfig)
    tracking: TrackingConfig = section(TrackingConfig)
    seed: int = option(0, 'Random seed of the sampler (results are deterministic per seed).',
                       low=0)
    num_candidates: int = option(
        5, 'Distinct candidate poses reported, best first (the estimate itself is the first); '
        'the others are found by searching again among the correspondences no earlier '
        'candidate explains. 1 reports the estimate only and skips the ambiguity check.',
        low=1, high=50)


def load_yaml(path: str | Path) -> dict[str, Any]:
    """
    Read a YAML file of parameters and return its mapping.

    Accepts ROS-style files (``node_name: {ros__parameters: {...}}``) and plain mappings.
    """
    import yaml

    try:
        with open(path, 'r', encoding='utf-8') as f:
            data = yaml.safe_load(f) or {}
    except OSError as exc:
        raise InvalidConfigError(f'cannot read config file {path}: {exc}') from exc
    except yaml.YAMLError as exc:
        raise InvalidConfigError(f'config file {path} is not valid YAML: {exc}') from exc
    if not isinstance(data, Mapping):
        raise InvalidConfigError(f'config file {path} must hold a mapping')
    for value in data.values():  # unwrap {node: {ros__parameters: {...}}}
        if isinstance(value, Mapping) and 'ros__parameters' in value:
            return dict(value['ros__parameters'])
    return dict(data)


def pipeline_config_from(values: Mapping[str, Any] | None = None,
                         base: PipelineConfig | None = None) -> PipelineConfig:
    """
    Return a validated PipelineConfig from flat (``core.p1``) or nested keys.

    Unknown keys raise InvalidConfigError.
    """
    base = base or PipelineConfig()
    return fields.update_from_flat(base, values or {})
