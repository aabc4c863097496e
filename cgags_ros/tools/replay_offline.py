"""Offline replay: every pair of a bag through :func:`register_clouds`, in-process, no ROS."""

from __future__ import annotations

import time

import numpy as np
from tqdm import tqdm

from .replay_common import (
    finish_report,
    iter_pairs,
    load_contents,
    make_row,
    note_pairing_drops,
    ReplayOptions,
    resolve_configs,
    stamp_s,
    start_report,
)
from .report import BagReport
from ..errors import InvalidInputError
from ..pipeline import register_clouds
from ..pipeline.pairing import Pairer


def replay_offline(opts: ReplayOptions) -> BagReport:
    """Register every pair of the bag in-process; write and return the report."""
    start = time.perf_counter()
    contents = load_contents(opts)
    pipe, node, _, how = resolve_configs(opts.parameters, contents)
    report = start_report(opts, contents, pipe, node, 'offline')
    report.notes.append(f'voxel size {pipe.voxel_size:g} m ({how})')
    progress = tqdm(total=len(contents.sources), disable=opts.quiet or None, unit='pair',
                    leave=False)
    pairer = Pairer.from_config(node)  # popped after every message: the queue never fills
    for pair in iter_pairs(contents, pairer):
        src, tgt = pair.source.payload, pair.target.payload
        progress.set_postfix_str(f'source {stamp_s(src.stamp_ns)}')
        progress.update()
        row = make_row(len(report.rows), src, tgt, contents)
        t0 = time.perf_counter()
        try:
            result = register_clouds(src.xyz, tgt.xyz, config=pipe)
        except InvalidInputError as exc:  # the node rejects these pairs too
            row.reason = f'rejected by the pipeline: {exc}'
        else:
            row.valid = bool(result.valid)
            row.reason, row.inliers = result.reason, result.num_inliers
            row.fitness = float(getattr(result, 'fitness', float('nan')))
            row.transform = np.asarray(result.transform, dtype=np.float64)
        row.time_s = time.perf_counter() - t0
        report.rows.append(row)
    progress.close()
    note_pairing_drops(report, pairer)
    report.wall_time_s = time.perf_counter() - start
    return finish_report(report, opts, contents)
