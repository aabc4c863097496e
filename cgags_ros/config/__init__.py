"""
Configuration: one typed dataclass per layer, all declared with :func:`fields.option`.

- :mod:`.fields`: the field helper (descriptions, ranges, validation, flat keys).
- :mod:`.core`, :mod:`.frontend`, :mod:`.pipeline`, :mod:`.tracking`,
  :mod:`.node`: the per-layer dataclasses.
- :mod:`.files`: ``config/register_node.yaml`` and ``docs/parameters.md``, generated.
"""

from .core import CoreConfig
from .frontend import FrontEndConfig, RefineConfig
from .node import configs_from_parameters, NodeConfig
from .pipeline import load_yaml, pipeline_config_from, PipelineConfig
from .tracking import TrackingConfig

__all__ = ['CoreConfig', 'FrontEndConfig', 'NodeConfig', 'PipelineConfig', 'RefineConfig',
           'TrackingConfig', 'configs_from_parameters', 'load_yaml', 'pipeline_config_from']
