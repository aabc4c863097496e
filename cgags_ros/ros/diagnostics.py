"""The node's /diagnostics message, from :mod:`cgags_ros.engine.statistics`."""

from __future__ import annotations

from typing import Any, Mapping

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from ..engine.statistics import status


def diagnostic_array(stats: Mapping[str, Any], name: str, hardware_id: str,
                     stamp: Any) -> DiagnosticArray:
    """Return the /diagnostics message of ``stats``, with a level and a one-line message."""
    level, message = status(stats)
    msg = DiagnosticArray(status=[DiagnosticStatus(
        name=name, hardware_id=hardware_id, level=getattr(DiagnosticStatus, level),
        message=message, values=[KeyValue(key=str(k), value=str(v)) for k, v in stats.items()])])
    msg.header.stamp = stamp
    return msg
