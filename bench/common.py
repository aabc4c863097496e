"""
What the benchmarks share: where results go, the ``--set`` option, success limits, tables, plots.

Results go under ``out/bench/`` (git-ignored) unless ``--output`` names another place, so
that a run never changes docs/: docs/benchmarks.md keeps the current table of each question
with the command that made it.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
import platform
import signal
import subprocess
from typing import Any, Iterable, Sequence

from cgags_ros.config import PipelineConfig
from cgags_ros.config.fields import parse_key_values, update_from_flat
import numpy as np

OUT = Path('out') / 'bench'

# Success (RE degrees, TE metres) by the data's kind, as that kind's literature counts it:
# object scans, 3DMatch's registration recall, outdoor LiDAR (KITTI-style). The faulty bag
# holds bunny scans.
LIMITS = {'bunny': (5.0, 0.01), 'faulty': (5.0, 0.01), 'redkitchen': (15.0, 0.3),
          'lidar': (5.0, 0.6)}


def output_path(name: str) -> Path:
    """Return ``out/bench/<name>``, where a benchmark writes unless ``--output`` says."""
    return OUT / name


def write_text(path: Path, text: str) -> Path:
    """Write ``text`` to ``path`` (its folder created); return the path."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding='utf-8')
    return path


def write_json(path: Path, data: Any, **dump: Any) -> Path:
    """Write ``data`` as JSON to ``path`` (its folder created); ``dump``: ``json.dumps``'s."""
    return write_text(path, json.dumps(data, **{'indent': 1, **dump}))


def machine() -> dict[str, str]:
    """Return the platform and the Python version a run had."""
    return {'platform': platform.platform(), 'python': platform.python_version()}


# --- the command line --------------------------------------------------------------------------

def argument_parser(module: str, doc: str, **kwargs: Any) -> argparse.ArgumentParser:
    """Return the parser of ``python -m <module>``: its docstring's first paragraph as help."""
    kwargs.setdefault('description', doc.strip().split('\n\n')[0])
    return argparse.ArgumentParser(prog=f'python -m {module}', **kwargs)


def add_set_option(parser: argparse.ArgumentParser) -> None:
    """Add ``--set KEY=VALUE`` (repeatable): one of our pipeline parameters, changed."""
    parser.add_argument('--set', action='append', default=[], metavar='KEY=VALUE',
                        help='change one of our parameters (repeatable), e.g. '
                        '--set frontend.max_keypoints=5000')


def parse_overrides(sets: Sequence[str]) -> dict[str, Any]:
    """Return ``--set`` values as flat keys; a typo fails here, not in every trial."""
    values = parse_key_values(sets)
    update_from_flat(PipelineConfig(), values)
    return values


def stop_process(proc: subprocess.Popen, log: Any) -> str:
    """SIGTERM a node process (SIGKILL after 20 s), wait for it; return its log (a file)."""
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(timeout=20)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
    log.seek(0)
    out = log.read()
    log.close()
    return out


# --- tables -----------------------------------------------------------------------------------

def cell(value: Any, digits: int = 4) -> str:
    """Format one table cell: ``digits`` significant digits, '-' for none or non-finite."""
    if isinstance(value, (bool, np.bool_)):
        return 'yes' if value else 'no'
    if isinstance(value, (float, np.floating)):
        return f'{value:.{digits}g}' if math.isfinite(value) else '-'
    return '-' if value is None else str(value)


def markdown_table(headers: Sequence[str], rows: Iterable[Sequence[Any]],
                   digits: int = 4) -> str:
    """Return a GitHub Markdown table of ``rows`` under ``headers``."""
    def line(cells: Iterable[str]) -> str:
        return '| ' + ' | '.join(cells) + ' |'

    body = [line(cell(v, digits) for v in row) for row in rows]
    return '\n'.join([line(headers), '|' + '---|' * len(headers), *body])


# --- plots ------------------------------------------------------------------------------------

def pyplot():
    """Return ``matplotlib.pyplot`` drawing off-screen (no display is needed)."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path: Path, dpi: int = 100) -> Path:
    """Save ``fig`` as ``path`` (its folder created) and close it; return the path."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    pyplot().close(fig)
    return path


# --- a pair as the pipeline sees it -----------------------------------------------------------

def pair_features(source: np.ndarray, target: np.ndarray, config: PipelineConfig) -> tuple:
    """
    Return ``(source features, target features, correspondences)`` as the pipeline has them.

    The feature cache's entries at ``config.voxel_size`` (computed when absent), matched
    once on one thread: what ``register_clouds`` hands the core, for a study to look at.
    """
    from cgags_ros.frontend.keypoints import match_keypoints
    from cgags_ros.pipeline.cache import cached_features

    v = config.voxel_size
    fs = cached_features(source, v, config.frontend, 'source')
    ft = cached_features(target, v, config.frontend, 'target')
    corr = match_keypoints(fs.points, fs.descriptors, ft.descriptors, v, config.frontend, 1,
                           ft.descriptor_index(1))
    return fs, ft, corr
