"""
The node's /diagnostics, ROS-free: one flat key space and its status, decided here.

:func:`build_statistics` makes the keys the node publishes, the constants name them once
and :func:`status` says what they amount to (a level and one line, which
``cgags_ros.ros.diagnostics`` puts into the message); what became of each source, typed,
is on ``~/result``. ``sources.*`` and
``targets.*`` are the accounting buckets of :mod:`cgags_ros.engine.accounting`
(``accounting.ok``: they balance; ``sources.lost_upstream``, scans that never arrived,
stands outside the balance); ``registration.*`` and ``memory.*`` the registration process and the
resident memory (MB); ``transport.profile`` the Fast DDS profile loaded; ``configure.error``
why configure failed (the node's last message before it is unconfigured, its code in
``configure.refusal_code``). Every refusal's code sits beside its message:
``last_refusal_code`` beside ``last_reason``, ``calibration.refusal_code`` beside
``calibration.reason``.
"""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from .accounting import lost_upstream_message
from .transport import user_line

# The levels of diagnostic_msgs/DiagnosticStatus, by name.
OK, WARN, ERROR, STALE = 'OK', 'WARN', 'ERROR', 'STALE'
REJECTED = 'rejected.'  # rejected.<code>: sources the node refused, per refusal code
REJECTED_TARGETS = 'rejected_targets.'  # rejected_targets.<code>: targets it could not use
PAIRING = 'pairing.'  # pairing.<counter> of cgags_ros.engine.pairing.Pairer.counters()
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

    ``snapshot`` is :meth:`cgags_ros.engine.accounting.Accounting.snapshot`; ``extra`` holds
    the registration process's and the memory's keys.
    """
    counts, rejected, last = snapshot['counts'], snapshot['rejected'], snapshot['last']
    latencies, pairing = snapshot['latencies'], snapshot['pairing']
    stats: dict[str, Any] = dict(counts)
    stats.update({f'{REJECTED}{k}': v for k, v in sorted(rejected.items())})
    stats.update({f'{REJECTED_TARGETS}{k}': v
                  for k, v in sorted(snapshot['rejected_targets'].items())})
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
        stats['registration.failing'] = snapshot['failing']
    stats.update(extra)
    return stats


def status(stats: Mapping[str, Any]) -> tuple[str, str]:
    """Return (level, one-line message) of the node's statistics, the first problem first."""
    if stats.get(CONFIGURE_ERROR):  # the last message before the node is unconfigured
        level = ERROR
        message = (f'configure failed ({stats.get(CONFIGURE_CODE, "")}): '
                   f'{stats[CONFIGURE_ERROR]}')
    elif not stats.get(ACCOUNTING_OK, True):
        level = ERROR
        message = 'internal error: received clouds do not balance the counted outcomes'
    elif stats.get('calibration.status') == 'failed':
        level = ERROR
        message = (f"calibration FAILED ({stats.get('calibration.refusal_code', '')}): "
                   f"{stats.get('calibration.reason', '')}")
    elif stats.get('calibration.status') in ('converged', 'max_frames'):
        level = OK
        message = (f"calibrated ({stats['calibration.status']}): "
                   f"{stats.get('calibration.parent_frame')} <- "
                   f"{stats.get('calibration.child_frame')} on ~/calibration")
    elif stats.get('map.error'):
        level = ERROR
        message = str(stats['map.error'])
    elif stats.get('registration.failing'):
        level = ERROR
        message = (f"registration failed ({stats['registration.failing']}); "
                   'restarted, no pair has succeeded since')
    elif stats.get('active') is False:
        level = STALE
        message = 'inactive (lifecycle): sources are counted, nothing is published'
    elif stats.get('registration.ready') is False:
        level = STALE
        message = 'registration process warming up; pairs wait for it'
    elif not stats.get('received_source') or not stats.get('received_target'):
        level = STALE
        message = 'waiting for source and target clouds'
        if stats.get('received_target'):  # the first thing a user of big scans sees
            message = ('waiting for source clouds (large clouds published without '
                       f'the Fast DDS profile never arrive: {user_line()})')
    elif stats.get(LOST_UPSTREAM):
        level = WARN
        message = lost_upstream_message(stats[LOST_UPSTREAM])
    elif stats.get(f'{LAST}valid') is False:
        level = WARN
        message = (f'last registration invalid ({stats.get(REFUSAL_CODE, "")}): '
                   f"{stats.get(f'{LAST}reason', '')}")
    elif stats['rejected'] or stats.get('targets.rejected') or stats[f'{PAIRING}dropped']:
        level = WARN
        message = 'running; some clouds rejected or dropped'
    else:
        level, message = OK, 'running'
    return level, message
