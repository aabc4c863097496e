"""
The node's /diagnostics: one flat key space, built here and read back by live replay.

:func:`build_statistics` makes the keys the node publishes; :func:`accounted_sources` and
:func:`last_result` read them back (from the string values a DiagnosticStatus carries),
so the names are defined once. ``sources.*`` and ``targets.*`` are the accounting buckets
of :mod:`.health` (``accounting.ok``: they balance; ``sources.lost_upstream``, scans that
never arrived, stands outside the balance); ``worker.*`` and ``memory.*`` the registration
process and the resident memory (MB); ``transport.profile`` the Fast DDS profile loaded;
``configure.error`` why configure failed (the node's last message before it is unconfigured,
its code in ``configure.refusal_code``). Every refusal's code sits beside its message:
``last_refusal_code`` beside ``last_reason``, ``calibration.refusal_code`` beside
``calibration.reason``.
"""

from __future__ import annotations

from typing import Any, Mapping

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
import numpy as np

from .health import lost_upstream_message
from .transport import user_line

REJECTED = 'rejected.'  # rejected.<cause>: clouds or pairs the node refused, per cause
PAIRING = 'pairing.'  # pairing.<counter> of cgags_ros.pipeline.pairing.Pairer.counters()
DROPPED = PAIRING + 'dropped.'  # pairing.dropped.<reason>
LAST = 'last_'  # last_<field>: the most recent registration
REFUSAL_CODE = LAST + 'refusal_code'  # its refusal's code ('' when valid), beside last_reason
LAST_TIMING = 'last_timing.'  # last_timing.<stage>: its stage times, seconds
ACCOUNTING_OK = 'accounting.ok'
LOST_UPSTREAM = 'sources.lost_upstream'
CONFIGURE_ERROR = 'configure.error'  # why the configure transition failed
CONFIGURE_CODE = 'configure.refusal_code'  # its code


def build_statistics(snapshot: Mapping[str, Any], voxel_size: float,
                     extra: Mapping[str, Any]) -> dict[str, Any]:
    """
    Return the flat statistics of the node (what /diagnostics carries).

    ``snapshot`` is :meth:`.health.NodeHealth.snapshot`; ``extra`` holds the worker's and
    the memory's keys.
    """
    counts, rejected, last = snapshot['counts'], snapshot['rejected'], snapshot['last']
    latencies, pairing = snapshot['latencies'], snapshot['pairing']
    stats: dict[str, Any] = dict(counts)
    stats.update({f'{REJECTED}{k}': v for k, v in sorted(rejected.items())})
    stats['rejected'] = sum(rejected.values())
    for key, value in last.items():
        if key == 'timings':
            stats.update({f'{LAST_TIMING}{k}': v for k, v in value.items()})
        else:
            stats[f'{LAST}{key}'] = value
    stats['voxel_size'] = voxel_size
    lat = np.array(list(latencies))
    if lat.size:
        stats['latency_p50_s'] = float(np.percentile(lat, 50))
        stats['latency_p95_s'] = float(np.percentile(lat, 95))
    stats.update({f'{PAIRING}{k}': v for k, v in pairing.items()})
    for side in ('sources', 'targets'):
        stats.update({f'{side}.{k}': v for k, v in snapshot['accounting'][side].items()})
    if snapshot.get('source_period_s'):  # learnt from the stamps; lost_upstream relies on it
        stats['sources.period_s'] = round(snapshot['source_period_s'], 6)
    stats[ACCOUNTING_OK] = snapshot['accounting']['ok']
    if snapshot['failing']:
        stats['worker.failing'] = snapshot['failing']
    stats.update(extra)
    return stats


def diagnostic_array(stats: Mapping[str, Any], name: str, hardware_id: str,
                     stamp: Any) -> DiagnosticArray:
    """Return the /diagnostics message of ``stats``, with a level and a one-line message."""
    status = DiagnosticStatus(name=name, hardware_id=hardware_id)
    if stats.get(CONFIGURE_ERROR):  # the last message before the node is unconfigured
        status.level = DiagnosticStatus.ERROR
        status.message = (f'configure failed ({stats.get(CONFIGURE_CODE, "")}): '
                          f'{stats[CONFIGURE_ERROR]}')
    elif not stats.get(ACCOUNTING_OK, True):
        status.level = DiagnosticStatus.ERROR
        status.message = 'internal error: received clouds do not balance the counted outcomes'
    elif stats.get('calibration.status') == 'failed':
        status.level = DiagnosticStatus.ERROR
        status.message = (f"calibration FAILED ({stats.get('calibration.refusal_code', '')}): "
                          f"{stats.get('calibration.reason', '')}")
    elif stats.get('calibration.status') in ('converged', 'max_frames'):
        status.level = DiagnosticStatus.OK
        status.message = (f"calibrated ({stats['calibration.status']}): "
                          f"{stats.get('calibration.parent_frame')} <- "
                          f"{stats.get('calibration.child_frame')} on ~/calibration")
    elif stats.get('map.error'):
        status.level = DiagnosticStatus.ERROR
        status.message = str(stats['map.error'])
    elif stats.get('worker.failing'):
        status.level = DiagnosticStatus.ERROR
        status.message = (f"registration worker failed ({stats['worker.failing']}); "
                          'restarted, no pair has succeeded since')
    elif stats.get('active') is False:
        status.level = DiagnosticStatus.STALE
        status.message = 'inactive (lifecycle): sources are counted, nothing is published'
    elif stats.get('worker.ready') is False:
        status.level = DiagnosticStatus.STALE
        status.message = 'registration process warming up; pairs wait for it'
    elif not stats.get('received_source') or not stats.get('received_target'):
        status.level = DiagnosticStatus.STALE
        status.message = 'waiting for source and target clouds'
        if stats.get('received_target'):  # the first thing a user of big scans sees
            status.message = ('waiting for source clouds (large clouds published without '
                              f'the Fast DDS profile never arrive: {user_line()})')
    elif as_int(stats.get(LOST_UPSTREAM)):
        status.level = DiagnosticStatus.WARN
        status.message = lost_upstream_message(stats[LOST_UPSTREAM])
    elif stats.get(f'{LAST}valid') is False:
        status.level = DiagnosticStatus.WARN
        status.message = (f'last registration invalid ({stats.get(REFUSAL_CODE, "")}): '
                          f"{stats.get(f'{LAST}reason', '')}")
    elif stats['rejected'] or stats[f'{PAIRING}dropped']:
        status.level = DiagnosticStatus.WARN
        status.message = 'running; some clouds rejected or dropped'
    else:
        status.level, status.message = DiagnosticStatus.OK, 'running'
    status.values = [KeyValue(key=str(k), value=str(v)) for k, v in stats.items()]
    msg = DiagnosticArray(status=[status])
    msg.header.stamp = stamp
    return msg


def accounted_sources(values: Mapping[str, str]) -> int:
    """Count the sources the node is done with: published + rejected + dropped + waiting."""
    return (sum(as_int(values.get(f'sources.{k}')) for k in ('published', 'rejected', 'dropped'))
            + as_int(values.get(f'{PAIRING}waiting_sources')))


def last_result(values: Mapping[str, str]) -> dict[str, Any]:
    """Return the last registration's fields (valid, reason, code, inliers, fitness, time_s)."""
    return {'valid': values.get(f'{LAST}valid', 'True') == 'True',
            'reason': values.get(f'{LAST}reason', ''), 'code': values.get(REFUSAL_CODE, ''),
            'inliers': as_int(values[f'{LAST}inliers']) if f'{LAST}inliers' in values else None,
            'fitness': as_float(values.get(f'{LAST}fitness')),
            'time_s': as_float(values.get(f'{LAST_TIMING}total'))}


def last_source_stamp_ns(values: Mapping[str, str]) -> int | None:
    """Return the source stamp of the last registration, or None before the first."""
    stamp = values.get(f'{LAST}source_stamp_ns')
    return int(stamp) if stamp else None


def nonzero_drops(values: Mapping[str, str]) -> list[str]:
    """Return 'key: value' for every rejection and pairing drop the node counted."""
    keys = [k for k in values if k.startswith((REJECTED, DROPPED))]
    return [f'{k}: {values[k]}' for k in sorted(keys) if as_int(values[k])]


def as_int(value: Any) -> int:
    """Read a counter published as text (0 when it is not a number)."""
    try:
        return int(float(value))
    except (TypeError, ValueError):
        return 0


def as_float(value: Any) -> float | None:
    """Read a number published as text (None when it is not one)."""
    try:
        return float(value)
    except (TypeError, ValueError):
        return None
