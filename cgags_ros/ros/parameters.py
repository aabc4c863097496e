"""ROS parameter descriptors generated from the config fields (type, range, read-only)."""

from __future__ import annotations

from typing import Any

from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                ParameterType)

_INT64_MAX = 2**63 - 1
_FLOAT_MAX = 1.7976931348623157e308


def descriptor(name: str, meta: dict[str, Any]) -> ParameterDescriptor:
    """ParameterDescriptor from configutil metadata (type, description, range, read-only)."""
    default = meta["default"]
    desc = ParameterDescriptor(name=name, description=str(meta["description"]),
                               read_only=bool(meta.get("read_only")))
    if meta.get("choices"):
        desc.additional_constraints = "one of: " + ", ".join(map(str, meta["choices"]))
    low, high = meta.get("low"), meta.get("high")
    if isinstance(default, bool):
        desc.type = ParameterType.PARAMETER_BOOL
    elif isinstance(default, int):
        desc.type = ParameterType.PARAMETER_INTEGER
        if low is not None or high is not None:
            desc.integer_range = [IntegerRange(
                from_value=int(low) if low is not None else -_INT64_MAX,
                to_value=int(high) if high is not None else _INT64_MAX, step=1)]
    elif isinstance(default, float):
        desc.type = ParameterType.PARAMETER_DOUBLE
        if low is not None or high is not None:
            desc.floating_point_range = [FloatingPointRange(
                from_value=float(low) if low is not None else -_FLOAT_MAX,
                to_value=float(high) if high is not None else _FLOAT_MAX, step=0.0)]
    elif isinstance(default, str):
        desc.type = ParameterType.PARAMETER_STRING
    else:  # None default (optional value): let the YAML decide the type
        desc.dynamic_typing = True
    return desc
