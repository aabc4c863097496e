"""Map replay: every source scan of a bag localized in a prior map (``cgags-replay --map``)."""

from __future__ import annotations

import time

from tqdm import tqdm

from .replay_common import (finish_report, load_contents, make_row, ReplayOptions,
                            resolve_configs, start_report)
from .replay_offline import note_tracking, register_row, stream_tracker
from .report import BagReport
from ..pipeline.map import load_map


def replay_map(opts: ReplayOptions) -> BagReport:
    """Localize every source scan in ``opts.map_file``; write and return the report."""
    start = time.perf_counter()
    contents = load_contents(opts)
    pipe, node, _, how = resolve_configs(opts.parameters, contents, map_target=True)
    report = start_report(opts, contents, pipe, node, 'offline-map')
    prepared = load_map(opts.map_file, pipe, opts.map_cache_dir or None)
    info = prepared.info()
    report.notes.append(f'voxel size {pipe.voxel_size:g} m ({how})')
    report.notes.append(f"map {info['path']}: {info['raw_points']} points -> {info['points']} "
                        f"after voxels, cache {info['cache']}, loaded in {info['load_s']:.2f} s")
    tracker = stream_tracker(pipe, node.mode)
    for src in tqdm(contents.sources, disable=opts.quiet or None, unit='scan', leave=False):
        row = make_row(len(report.rows), src, None, contents)
        row.target_frame = 'map'
        report.rows.append(register_row(row, src.xyz, prepared, pipe, candidates=True,
                                        tracker=tracker))
    note_tracking(report, tracker)
    report.wall_time_s = time.perf_counter() - start
    return finish_report(report, opts, contents)
