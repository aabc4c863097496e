"""
Replay results: rows, summary numbers, result files and printed tables.

One row per registered pair, summary numbers, CSV/JSON files, a PNG plot and the tables
printed at the end of ``cgags-replay`` and ``cgags-demo``.

Pure bookkeeping: numpy, the geometry metrics and (lazily, Agg backend) matplotlib.
Transforms are 4x4 source->target (``p_target = R p_source + t``), metres; stamps are
integer nanoseconds since the epoch (ROS time); times are seconds.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from ..geometry import matrix_to_quaternion, rotation_error_deg, translation_error
from ..refusal import Refusal, summary as refusal_summary

RESULTS_CSV = 'results.csv'
RESULTS_JSON = 'results.json'
PLOT_PNG = 'errors.png'

CSV_COLUMNS = (
    'index', 'source_stamp_ns', 'target_stamp_ns', 'source_frame', 'target_frame',
    'valid', 'path', 'refusal', 'reason', 'inliers', 'fitness', 'time_s', 'latency_s',
    're_deg', 'te_m', 'success', 'tx', 'ty', 'tz', 'qx', 'qy', 'qz', 'qw',
)
_POSE_COLUMNS = 7  # the last ones: translation and quaternion


@dataclasses.dataclass
class SuccessCriteria:
    """A pair is a success when RE <= max_re_deg (degrees) and TE <= max_te_m (metres)."""

    max_re_deg: float
    max_te_m: float


@dataclasses.dataclass
class PairRow:
    """
    One source cloud that was registered (offline) or sent to the node (live).

    ``transform`` is the estimate (4x4 source->target, metres) or None when there is none
    (live replay: the node published nothing for this source). ``time_s`` is the
    ``register_clouds`` wall time (offline) or the node's reported pipeline time (live);
    ``latency_s`` (live only) the time from publishing the source to receiving its pose.
    ``re_deg``/``te_m``/``success`` are None without ground truth. ``covariance`` is the
    estimate's 6x6 covariance (ROS order: x, y, z in metres, rotations in radians), in the
    JSON output only. ``path`` is what produced the estimate: 'tracked' (refined from the
    stream's last pose) or 'global' (None when no registration ran). ``refusal`` says why
    the pair is not valid (None when it is, or when the node published an invalid pose it
    did not explain); ``reason`` is its message.
    """

    index: int
    source_stamp_ns: int
    target_stamp_ns: int | None
    source_frame: str
    target_frame: str
    valid: bool
    path: str | None = None
    refusal: Refusal | None = None
    inliers: int | None = None
    fitness: float | None = None
    time_s: float | None = None
    latency_s: float | None = None
    transform: np.ndarray | None = None
    ground_truth: np.ndarray | None = None
    re_deg: float | None = None
    te_m: float | None = None
    success: bool | None = None
    candidates: list[dict[str, Any]] | None = None
    covariance: np.ndarray | None = None

    @property
    def reason(self) -> str:
        """Return the refusal's message ('' without one)."""
        return '' if self.refusal is None else self.refusal.message

    def evaluate(self, criteria: SuccessCriteria) -> None:
        """
        Fill RE/TE/success from ``ground_truth`` (no-op without it).

        A pair without an estimate, or with an invalid one, is a failure.
        """
        if self.ground_truth is None:
            return
        if self.transform is None:
            self.re_deg = self.te_m = None
            self.success = False
            return
        self.re_deg = rotation_error_deg(self.transform, self.ground_truth)
        self.te_m = translation_error(self.transform, self.ground_truth)
        self.success = bool(self.valid and self.re_deg <= criteria.max_re_deg
                            and self.te_m <= criteria.max_te_m)

    def csv_row(self) -> dict[str, Any]:
        row = {k: getattr(self, k) for k in CSV_COLUMNS[:-_POSE_COLUMNS]}
        row['valid'] = int(self.valid)
        row['refusal'] = '' if self.refusal is None else self.refusal.code.value
        row['success'] = '' if self.success is None else int(self.success)
        pose = _pose7(self.transform)
        row.update(zip(CSV_COLUMNS[-_POSE_COLUMNS:],
                       pose if pose is not None else [''] * _POSE_COLUMNS))
        return {k: ('' if v is None else v) for k, v in row.items()}

    def to_json(self) -> dict[str, Any]:
        out = {k: getattr(self, k) for k in CSV_COLUMNS[:-_POSE_COLUMNS]}
        out['refusal'] = refusal_summary(self.refusal)
        out['transform'] = None if self.transform is None else np.asarray(self.transform).tolist()
        out['ground_truth'] = (None if self.ground_truth is None
                               else np.asarray(self.ground_truth).tolist())
        out['covariance'] = (None if self.covariance is None
                             else np.asarray(self.covariance).tolist())
        if self.candidates is not None:
            out['candidates'] = self.candidates
        return _finite_or_none(out)


@dataclasses.dataclass
class BrokenMessage:
    """A message skipped because it could not be read or converted (never fatal)."""

    topic: str
    stamp_ns: int | None
    reason: str


@dataclasses.dataclass
class BagReport:
    """Everything one replay produced. ``mode`` is 'offline' or 'live'."""

    bag: str
    mode: str
    voxel_size: float
    pairing: str
    criteria: SuccessCriteria
    rows: list[PairRow] = dataclasses.field(default_factory=list)
    broken: list[BrokenMessage] = dataclasses.field(default_factory=list)
    notes: list[str] = dataclasses.field(default_factory=list)
    output_bag: str = ''
    wall_time_s: float = 0.0

    @property
    def evaluated(self) -> list[PairRow]:
        return [r for r in self.rows if r.success is not None]

    @property
    def has_ground_truth(self) -> bool:
        return bool(self.evaluated)

    @property
    def num_valid(self) -> int:
        return sum(r.valid for r in self.rows)

    @property
    def num_success(self) -> int:
        return sum(bool(r.success) for r in self.evaluated)

    @property
    def recall(self) -> float | None:
        """Successes / pairs with ground truth; None when no pair has ground truth."""
        ev = self.evaluated
        return self.num_success / len(ev) if ev else None

    def mean_errors(self) -> tuple[float | None, float | None]:
        """Mean RE (degrees) and TE (metres) over successful pairs (the usual convention)."""
        ok = [r for r in self.evaluated if r.success]
        if not ok:
            return None, None
        return float(np.mean([r.re_deg for r in ok])), float(np.mean([r.te_m for r in ok]))

    def median_time_s(self) -> float | None:
        times = [r.time_s for r in self.rows if r.time_s is not None]
        return float(np.median(times)) if times else None

    def summary(self) -> dict[str, Any]:
        mean_re, mean_te = self.mean_errors()
        return _finite_or_none({
            'bag': self.bag, 'mode': self.mode, 'voxel_size': self.voxel_size,
            'pairing': self.pairing, 'pairs': len(self.rows), 'valid': self.num_valid,
            'with_ground_truth': len(self.evaluated), 'successes': self.num_success,
            'recall': self.recall, 'mean_re_deg': mean_re, 'mean_te_m': mean_te,
            'median_time_s': self.median_time_s(), 'broken_messages': len(self.broken),
            'max_re_deg': self.criteria.max_re_deg, 'max_te_m': self.criteria.max_te_m,
            'output_bag': self.output_bag, 'wall_time_s': self.wall_time_s,
        })

    def to_json(self) -> dict[str, Any]:
        return {'summary': self.summary(), 'pairs': [r.to_json() for r in self.rows],
                'broken_messages': [dataclasses.asdict(b) for b in self.broken],
                'notes': list(self.notes)}


# --- files ---------------------------------------------------------------------------------

def write_results(report: BagReport, out_dir: str | Path) -> dict[str, Path]:
    """Write results.csv, results.json and (with ground truth or timings) errors.png."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {'csv': out_dir / RESULTS_CSV, 'json': out_dir / RESULTS_JSON}
    with open(paths['csv'], 'w', newline='', encoding='utf-8') as f:
        writer = csv.DictWriter(f, fieldnames=CSV_COLUMNS)
        writer.writeheader()
        writer.writerows(r.csv_row() for r in report.rows)
    with open(paths['json'], 'w', encoding='utf-8') as f:
        json.dump(report.to_json(), f, indent=2)
    if report.rows:
        paths['plot'] = plot_report(report, out_dir / PLOT_PNG)
    return paths


def plot_report(report: BagReport, path: str | Path) -> Path:
    """RE, TE (with the success thresholds) and time per pair over the bag's time, PNG."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    rows = report.rows
    t0 = rows[0].source_stamp_ns
    x = np.array([(r.source_stamp_ns - t0) * 1e-9 for r in rows])
    panels = [('RE [deg]', [r.re_deg for r in rows], report.criteria.max_re_deg),
              ('TE [m]', [r.te_m for r in rows], report.criteria.max_te_m),
              ('time [s]', [r.time_s for r in rows], None)]
    if not report.has_ground_truth:
        panels = panels[2:]
    fig, axes = plt.subplots(len(panels), 1, sharex=True, figsize=(7, 2.2 * len(panels) + 0.6),
                             squeeze=False)
    for ax, (label, values, limit) in zip(axes[:, 0], panels):
        y = np.array([np.nan if v is None else v for v in values], dtype=float)
        colors = ['tab:green' if r.success or (r.success is None and r.valid) else 'tab:red'
                  for r in rows]
        ax.plot(x, y, color='0.7', lw=1, zorder=1)
        ax.scatter(x, y, c=colors, s=25, zorder=2)
        if limit is not None:
            ax.axhline(limit, color='tab:red', ls='--', lw=1, label='success threshold')
            ax.legend(loc='upper right', fontsize=7)
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[-1, 0].set_xlabel('source stamp - first source stamp [s]')
    recall = report.recall
    title = f'{report.bag} ({report.mode}, voxel {report.voxel_size:g} m)'
    if recall is not None:
        title += f': recall {report.num_success}/{len(report.evaluated)}'
    axes[0, 0].set_title(title + '  (green: success/valid, red: failure)', fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


# --- tables ---------------------------------------------------------------------------------

def markdown_table(headers: Sequence[str], rows: Iterable[Sequence[Any]]) -> str:
    """Format a GitHub markdown table; floats are formatted compactly, None as '-'."""
    lines = ['| ' + ' | '.join(headers) + ' |', '|' + '|'.join('---' for _ in headers) + '|']
    lines += ['| ' + ' | '.join(fmt(v) for v in row) + ' |' for row in rows]
    return '\n'.join(lines)


def fmt(value: Any) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return '-'
    if isinstance(value, bool):
        return 'yes' if value else 'no'
    if isinstance(value, float):
        return f'{value:.4g}'
    return str(value)


def pairs_table(report: BagReport) -> str:
    """Per-pair table printed at the end of a replay."""
    t0 = report.rows[0].source_stamp_ns if report.rows else 0
    rows = [(r.index, (r.source_stamp_ns - t0) * 1e-9, r.valid, r.inliers, r.re_deg, r.te_m,
             r.success, r.time_s, r.reason[:60]) for r in report.rows]
    return markdown_table(('pair', 't [s]', 'valid', 'inliers', 'RE [deg]', 'TE [m]', 'success',
                           'time [s]', 'reason'), rows)


def summary_line(report: BagReport) -> str:
    """One line: pairs, valid, recall, mean RE/TE over successes, median time, broken."""
    mean_re, mean_te = report.mean_errors()
    parts = [f'{report.bag} [{report.mode}]', f'pairs {len(report.rows)}',
             f'valid {report.num_valid}']
    if report.recall is not None:
        parts.append(f'recall {report.num_success}/{len(report.evaluated)} '
                     f'({100 * report.recall:.0f}%, RE<={report.criteria.max_re_deg:g} deg, '
                     f'TE<={report.criteria.max_te_m:g} m)')
        parts.append(f'mean RE {fmt(mean_re)} deg, mean TE {fmt(mean_te)} m')
    parts.append(f'median time {fmt(report.median_time_s())} s')
    parts.append(f'broken messages {len(report.broken)}')
    return ', '.join(parts)


def summary_table(reports: Sequence[BagReport]) -> str:
    """One row per bag (used by cgags-demo)."""
    rows = []
    for rep in reports:
        mean_re, mean_te = rep.mean_errors()
        recall = None if rep.recall is None else f'{rep.num_success}/{len(rep.evaluated)}'
        rows.append((rep.bag, rep.mode, rep.voxel_size, len(rep.rows), recall, mean_re,
                     mean_te, rep.median_time_s(), len(rep.broken)))
    return markdown_table(('bag', 'mode', 'voxel [m]', 'pairs', 'recall', 'mean RE [deg]',
                           'mean TE [m]', 'median time [s]', 'broken'), rows)


# --- helpers --------------------------------------------------------------------------------

def _pose7(T: np.ndarray | None) -> list[float] | None:
    """tx, ty, tz, qx, qy, qz, qw of a 4x4 transform (geometry_msgs quaternion order)."""
    if T is None:
        return None
    T = np.asarray(T, dtype=float)
    return [*T[:3, 3].tolist(), *matrix_to_quaternion(T[:3, :3]).tolist()]


def _finite_or_none(value: Any) -> Any:
    """JSON has no NaN/inf: map them (and numpy scalars) to None / Python numbers."""
    if isinstance(value, dict):
        return {k: _finite_or_none(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite_or_none(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value
