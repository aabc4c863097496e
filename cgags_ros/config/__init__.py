"""
Configuration: one typed dataclass per layer, all declared with :func:`fields.option`.

- :mod:`.fields`: the field helper (descriptions, ranges, validation, flat keys).
- :mod:`.core`, :mod:`.frontend`, :mod:`.gates`, :mod:`.pipeline`, :mod:`.tracking`,
  :mod:`.node`: the per-layer dataclasses; a key's dotted path is its one name (YAML,
  ``--set``, and the ROS parameter for fields declared ``ros=True``).
- :mod:`.files`: ``config/register_node.yaml`` and ``docs/parameters.md``, generated.
"""

from .core import CoreConfig
from .frontend import FrontEndConfig, RefineConfig
from .gates import GatesConfig
from .node import configs_from_parameters, NodeConfig
from .pipeline import load_yaml, pipeline_config_from, PipelineConfig
from .tracking import TrackingConfig

__all__ = ['CoreConfig', 'FrontEndConfig', 'GatesConfig', 'NodeConfig', 'PipelineConfig',
           'RefineConfig', 'TrackingConfig', 'configs_from_parameters', 'load_yaml',
           'pipeline_config_from']
