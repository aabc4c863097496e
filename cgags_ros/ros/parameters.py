"""ROS parameter descriptors generated from the config fields (type, range, read-only)."""

from __future__ import annotations

from typing import Any

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, ParameterType

from ..config.node import parameter_descriptions

_INT64_MAX = 2**63 - 1
_FLOAT_MAX = 1.7976931348623157e308


def descriptor(name: str, meta: dict[str, Any]) -> ParameterDescriptor:
    """Return the ParameterDescriptor of a config field (type, description, range, read-only)."""
    default = meta['default']
    desc = ParameterDescriptor(name=name, description=str(meta['description']),
                               read_only=bool(meta.get('read_only')))
    if meta.get('choices'):
        desc.additional_constraints = 'one of: ' + ', '.join(map(str, meta['choices']))
    ranged = meta.get('low') is not None or meta.get('high') is not None
    if isinstance(default, bool):
        desc.type = ParameterType.PARAMETER_BOOL
    elif isinstance(default, int):
        desc.type = ParameterType.PARAMETER_INTEGER
        if ranged:
            low, high = _bounds(meta, int, _INT64_MAX)
            desc.integer_range = [IntegerRange(from_value=low, to_value=high, step=1)]
    elif isinstance(default, float):
        desc.type = ParameterType.PARAMETER_DOUBLE
        if ranged:
            low, high = _bounds(meta, float, _FLOAT_MAX)
            desc.floating_point_range = [FloatingPointRange(from_value=low, to_value=high,
                                                            step=0.0)]
    elif isinstance(default, str):
        desc.type = ParameterType.PARAMETER_STRING
    elif isinstance(default, (list, tuple)):  # a vector (core.gravity, base_from_sensor)
        desc.type = ParameterType.PARAMETER_DOUBLE_ARRAY
    else:  # None default (optional value): let the YAML decide the type
        desc.dynamic_typing = True
    return desc


def _bounds(meta: dict[str, Any], kind: type, largest: Any) -> tuple[Any, Any]:
    """Return the field's (low, high) as ``kind``; an open end becomes -largest/largest."""
    low, high = meta.get('low'), meta.get('high')
    return (kind(low) if low is not None else -largest,
            kind(high) if high is not None else largest)


def not_a_parameter(name: str) -> str:
    """Say why ``name`` is no ROS parameter of the node, and where it is set instead."""
    if name in parameter_descriptions():
        return (f'{name}: not a ROS parameter; set it in the YAML of config_file '
                '(docs/parameters.md)')
    return f'{name}: unknown parameter (docs/parameters.md)'
