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
from .fields import option
from .frontend import FrontEndConfig, RefineConfig
from .tracking import TrackingConfig
from ..errors import InvalidConfigError


@dataclasses.dataclass
class PipelineConfig:
    """Everything ``register_clouds`` needs: the voxel size, each layer's options, a seed."""

    voxel_size: float = option(
        0.05, 'Voxel size in metres; normals, FPFH radii and thresholds derive from it.',
        low=1e-6, high=100.0)
    frontend: FrontEndConfig = dataclasses.field(default_factory=FrontEndConfig)
    core: CoreConfig = dataclasses.field(default_factory=CoreConfig)
    refine: RefineConfig = dataclasses.field(default_factory=RefineConfig)
    tracking: TrackingConfig = dataclasses.field(default_factory=TrackingConfig)
    seed: int = option(0, 'Random seed of the sampler (results are deterministic per seed).',
                       low=0)
    num_candidates: int = option(
        5, 'Distinct candidate poses reported, best first (the estimate itself is the first); '
        'the others are found by searching again among the correspondences no earlier '
        'candidate explains. 1 reports the estimate only and skips the ambiguity check.',
        low=1, high=50)
    candidate_min_rotation_deg: float = option(
        10.0, 'Two candidates are distinct when their rotations differ by more than this '
        '(degrees) or their translations by more than candidate_min_translation_factor '
        'voxel sizes.', low=0.0, high=180.0)
    candidate_min_translation_factor: float = option(
        10.0, 'Translation (in voxel sizes) by which two candidates must differ to be '
        'distinct (or see candidate_min_rotation_deg).', low=0.0, high=1e6)
    ambiguity_ratio: float = option(
        1.5, 'The estimate is ambiguous (reported invalid, flagged ambiguous) when the best '
        "candidate's inlier count is below this times the runner-up's: two poses are then "
        'nearly equally supported (a symmetric room, a corridor).', low=1.0, high=100.0)
    min_confidence: float = option(
        0.5, 'The estimate is valid only when its confidence (the calibrated probability that '
        "it is right, from the gates' measurements) is at least this, on top of every gate. "
        '6-DoF pairs only: against a map or in 4-DoF mode the confidence is reported but '
        'decides nothing. 0 leaves the decision to the gates.', low=0.0, high=1.0)
    verify_rivals: bool = option(
        True, 'Refine the rivals that make an estimate ambiguous; one that converges onto '
        "it, whose overlap the estimate's exceeds ambiguity_ratio times, or that fails the "
        'free-space gate is not plausible; only a plausible rival makes it ambiguous.',
        advanced=True)
    structured_rivals: bool = option(
        True, 'Before calling an estimate valid, try the poses a near-symmetric or weakly '
        'constrained scene would also accept (the estimate turned 180 degrees about the '
        "overlap's principal axes, slid along its least constrained direction), each refined "
        'and judged like the estimate; a plausible one makes the result ambiguous. 6-DoF '
        'pairs of sensor-frame clouds only (the free-space gate must apply).',
        advanced=True)
    candidate_max_iterations: int = option(
        1000, 'Hypotheses generated in each search for a further candidate (the search for '
        'the estimate itself uses core.max_iterations).', low=1, high=10**8, advanced=True)


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
