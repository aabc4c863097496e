"""
Offline replay: every pair of a bag through :func:`register_clouds`, in-process, no ROS.

In continuous mode with ``tracking.enabled`` (the defaults) the pairs are a stream, as in
the node: one :class:`~cgags_ros.tracking.Tracker` registers them, falling back to
``register_clouds``; each row says which path made it.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
from tqdm import tqdm

from .replay_common import (finish_report, iter_pairs, load_contents, make_row, note_pairing_drops,
                            ReplayOptions, resolve_configs, stamp_s, start_report)
from .report import BagReport, PairRow
from ..config.pipeline import PipelineConfig
from ..engine.pairing import Pairer
from ..errors import InvalidInputError
from ..refusal import Refusal
from ..runtime.jobs import tracks


def replay_offline(opts: ReplayOptions) -> BagReport:
    """Register every pair of the bag in-process; write and return the report."""
    start = time.perf_counter()
    contents = load_contents(opts)
    pipe, node, _, how = resolve_configs(opts.parameters, contents)
    report = start_report(opts, contents, pipe, node, 'offline')
    report.notes.append(f'voxel size {pipe.voxel_size:g} m ({how})')
    progress = tqdm(total=len(contents.sources), disable=opts.quiet or None, unit='pair',
                    leave=False)
    pairer = Pairer.from_config(node.pairing)  # popped after every message: the queue never fills
    tracker = stream_tracker(pipe, node.mode)
    for pair in iter_pairs(contents, pairer):
        src, tgt = pair.source.payload, pair.target.payload
        progress.set_postfix_str(f'source {stamp_s(src.stamp_ns)}')
        progress.update()
        row = make_row(len(report.rows), src, tgt, contents)
        report.rows.append(register_row(row, src.xyz, tgt.xyz, pipe, tracker=tracker))
    progress.close()
    note_pairing_drops(report, pairer)
    note_tracking(report, tracker)
    report.wall_time_s = time.perf_counter() - start
    return finish_report(report, opts, contents)


def stream_tracker(pipe: PipelineConfig, mode: str) -> Any:
    """Return a :class:`~cgags_ros.tracking.Tracker` for the bag's stream, as the node's."""
    from ..tracking import Tracker  # here: the replay CLI must start without Open3D

    return Tracker() if tracks(mode, pipe) else None


def note_tracking(report: BagReport, tracker: Any) -> None:
    """Add the tracker's counts (how many scans each path registered) to the notes."""
    if tracker is not None:
        counts = ', '.join(f'{k} {v}' for k, v in tracker.counts().items())
        report.notes.append(f'tracking: {counts}')


def register_row(row: PairRow, source: np.ndarray, target: Any, pipe: PipelineConfig,
                 candidates: bool = False, tracker: Any = None) -> PairRow:
    """
    Register ``source`` onto ``target`` (points or a prepared map) and fill ``row``.

    With ``tracker`` the source is the stream's next scan (stamped with the row's source
    stamp), tracked from the last pose when the gates allow. A cloud the pipeline rejects
    (the node rejects it too) leaves the row invalid with the error's refusal;
    ``candidates`` also records the ranked candidates.
    """
    from ..pipeline import register_clouds  # here: the replay CLI must start without Open3D

    t0 = time.perf_counter()
    try:
        result = (register_clouds(source, target, config=pipe) if tracker is None
                  else tracker.register(source, target, row.source_stamp_ns * 1e-9, config=pipe))
    except InvalidInputError as exc:
        row.refusal = Refusal(exc.code, f'rejected by the pipeline: {exc}')
    else:
        row.valid, row.path = bool(result.valid), result.path
        row.refusal, row.inliers = result.refusal, result.num_inliers
        row.fitness = float(result.fitness)
        row.transform = np.asarray(result.transform, dtype=np.float64)
        row.covariance = np.asarray(result.covariance, dtype=np.float64)
        if candidates:
            row.candidates = [c.summary() for c in result.candidates]
    row.time_s = time.perf_counter() - t0
    return row
