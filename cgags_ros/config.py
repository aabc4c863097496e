"""Configuration of the whole pipeline: one dataclass per layer, composed here.

Defaults live in the dataclasses and are mirrored in ``config/register_node.yaml``
(a test checks the two agree). ``voxel_size`` (metres) is the one scale every radius and
threshold derives from.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Mapping

from . import configutil
from .configutil import option
from .errors import InvalidConfigError
from .features.config import FrontEndConfig, RefineConfig
from .registration.config import CoreConfig


@dataclasses.dataclass
class PipelineConfig:
    voxel_size: float = option(
        0.05, "Voxel size in metres; normals, FPFH radii and thresholds derive from it.",
        low=1e-6, high=100.0)
    frontend: FrontEndConfig = dataclasses.field(default_factory=FrontEndConfig)
    core: CoreConfig = dataclasses.field(default_factory=CoreConfig)
    refine: RefineConfig = dataclasses.field(default_factory=RefineConfig)
    seed: int = option(0, "Random seed of the sampler (results are deterministic per seed).",
                       low=0)


def load_yaml(path: str | Path) -> dict[str, Any]:
    """Read a YAML file and return its mapping. Accepts ROS-style files
    (``node_name: {ros__parameters: {...}}``) and plain mappings."""
    import yaml

    try:
        with open(path, "r", encoding="utf-8") as f:
            data = yaml.safe_load(f) or {}
    except OSError as exc:
        raise InvalidConfigError(f"cannot read config file {path}: {exc}") from exc
    except yaml.YAMLError as exc:
        raise InvalidConfigError(f"config file {path} is not valid YAML: {exc}") from exc
    if not isinstance(data, Mapping):
        raise InvalidConfigError(f"config file {path} must hold a mapping")
    for value in data.values():  # unwrap {node: {ros__parameters: {...}}}
        if isinstance(value, Mapping) and "ros__parameters" in value:
            return dict(value["ros__parameters"])
    return dict(data)


def pipeline_config_from(values: Mapping[str, Any] | None = None,
                         base: PipelineConfig | None = None) -> PipelineConfig:
    """A validated PipelineConfig from flat (``core.p1``) or nested keys; unknown keys raise."""
    base = base or PipelineConfig()
    return configutil.update_from_flat(base, values or {})
