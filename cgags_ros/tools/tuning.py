"""
Tuning from recorded data: the settings that register a user's own bags best, as ROS parameters.

One **trial** replays every pair of the bags through the path ``cgags-replay`` takes
(:func:`~.replay_offline.register_row`, a stream tracked as the node tracks it) with one
set of settings and scores it: the pairs right and valid count, a valid pair that is wrong
counts against it (at most ``max_wrong`` are tolerated), and among equals the faster median
pair wins. Optuna's seeded TPE sampler proposes the settings; a study lives in a storage (a
local SQLite file by default) so that it can be stopped and resumed, or shared by several
machines.

Right and wrong are judged against the bags' ground truth when they have it. Without it,
by **consistency** (:func:`check_consistency`): each valid pair is registered again the
other way round, globally (target onto source, no tracking); a pair whose two estimates
compose to the identity within the success limits counts as right, one whose reverse is
valid and disagrees counts as wrong, one whose reverse is refused counts as neither.
docs/tuning.md says what this can and cannot catch.

Features are computed afresh in every trial (the pipeline's cache keeps only the last two
clouds): a trial's median time is a cold pair's, so times compare across trials. A trial
whose settings were tried before is not replayed: its score is read back from the study.

The search space is small on purpose: ``voxel_size`` (the one number users tune), on a
log grid of ``GRID_STEPS`` steps a decade around the reference voxel (the automatic
choice, and the user's start); and a
setting only where the bags' own refusals name it as the fix (docs/refusals.md):
``frontend.normal_orientation`` for free-space refusals (clouds not in their sensor frame),
``core.motion_model`` for tilt refusals (levelled clouds expected), ``core.time_budget``
for pairs that ran into a timeout, each opened when the best trials so far are refused so
(:mod:`.tune_search`). No research switch is searched, nor a setting the user fixes
(:mod:`.tune_fixed`): that one applies to every trial.

Part of the pairs (``holdout``) is held out, chosen by a seeded shuffle: the search sees
only the rest, and the best trial is then replayed on both, so that a setting that only
fits the pairs it was chosen on shows as such. Fewer than ``MIN_HELD_OUT`` held-out pairs
could never show it (:func:`holdout_warning`: one pair missed is within noise of any
recall), so a bag that small is tuned on whole.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from .replay_common import (auto_voxel_size, DEFAULT_GT_TOPIC, DEFAULT_MAX_RE_DEG,
                            DEFAULT_MAX_TE_VOXELS, iter_pairs, read_bag_contents, ReplayError)
from .replay_offline import register_row, stream_tracker
from .report import PairRow, SuccessCriteria
from ..config.node import configs_from_parameters, NODE_NAME, ros_value
from ..engine.pairing import Pairer
from ..errors import InvalidConfigError, InvalidInputError
from ..geometry import rotation_error_deg, translation_error
from ..refusal import RefusalCode

GRID_STEPS = 10  # voxel sizes a decade: neighbours 26 % apart
GRID_SPAN = 1.5  # decades either side of the reference (and of the user's start)
MIN_HELD_OUT = 2  # the fewest held-out pairs whose misses can exceed noise
WRONG_PENALTY = 1000.0  # a wrong valid pair past max_wrong outweighs any right one
# The refusal codes whose documented fix is a setting, and that setting's choices.
FIXES = {
    RefusalCode.FREE_SPACE: ('frontend.normal_orientation', ('origin', 'centroid')),
    RefusalCode.TILT: ('core.motion_model', ('6dof', '4dof')),
    RefusalCode.TIMEOUT: ('core.time_budget', (0.0, 0.5, 1.0, 2.0)),
}


class SettingRefused(InvalidConfigError):
    """The node refused a trial's settings (out of its range, read-only): never retried."""


@dataclasses.dataclass
class TunePair:
    """
    One pair of a bag: both clouds (their frames, metres), the truth and the stream stamp.

    ``truth`` is None when the bag has no ground truth (then consistency judges the pair).
    """

    bag: str
    index: int
    source: np.ndarray
    target: np.ndarray
    truth: np.ndarray | None
    stamp_ns: int
    source_frame: str
    target_frame: str


@dataclasses.dataclass
class Score:
    """
    A replay's outcome: pairs right and valid, valid but wrong, refusal codes, time.

    ``judged_by`` says what right and wrong mean: 'ground truth', or 'consistency' (right:
    confirmed by the reverse registration; wrong: contradicted by it; ``unconfirmed``:
    valid, the reverse refused).
    """

    pairs: int
    right: int
    wrong: int
    median_s: float
    refusals: dict[str, int]
    judged_by: str = 'ground truth'
    unconfirmed: int = 0

    @property
    def recall(self) -> float:
        """Return the share of the pairs that are right and valid."""
        return self.right / self.pairs if self.pairs else 0.0

    def value(self, max_wrong: int) -> float:
        """
        Return the objective: pairs right and valid, less every wrong one past ``max_wrong``.

        No time in it, so that a seed replays the same proposals; the median time breaks
        ties when the best trial is picked.
        """
        return self.right - WRONG_PENALTY * max(0, self.wrong - max_wrong)


def load_pairs(bags: Sequence[Path], source_topic: str, target_topic: str,
               ground_truth_topic: str | None, ground_truth_file: Path | None = None
               ) -> list[TunePair]:
    """Return every pair of ``bags`` with its truth if known (:func:`load_bags`' pairs)."""
    return load_bags(bags, source_topic, target_topic, ground_truth_topic,
                     ground_truth_file)[0]


def load_bags(bags: Sequence[Path], source_topic: str, target_topic: str,
              ground_truth_topic: str | None, ground_truth_file: Path | None = None,
              fixed: dict[str, Any] | None = None
              ) -> tuple[list[TunePair], list[tuple[str, Any]]]:
    """
    Return every pair of ``bags`` (as the node pairs them) and each bag's contents.

    The pairing is the node's with the ``fixed`` settings (its defaults when None).

    The contents (``(name, BagContents)``, every cloud with its message) are what a live
    study plays to the node, so that each bag is read once.

    The truth comes from ``ground_truth_file`` or ``ground_truth_topic``; ``None`` for the
    topic means ``/ground_truth`` when the bags have it. Without ground truth in any bag,
    every pair's ``truth`` is None (consistency judges them).

    :raises ReplayError: a bag without a cloud topic or without pairs, a named ground-truth
        topic it lacks, ground truth that matches no source stamp, or some bags with ground
        truth and some without (tune them apart).
    """
    pairs = []
    read = []
    with_truth = set()
    for bag in bags:
        topic = ground_truth_topic or DEFAULT_GT_TOPIC
        contents = read_bag_contents(bag, source_topic, target_topic,
                                     None if ground_truth_file else topic,
                                     require_ground_truth=(ground_truth_file is None
                                                           and ground_truth_topic is not None))
        if ground_truth_file is not None:
            contents.ground_truth = read_ground_truth(ground_truth_file)
        has_truth = ground_truth_file is not None or contents.ground_truth_topic is not None
        name = bag.stem if bag.suffix == '.mcap' else bag.resolve().name
        read.append((name, contents))
        _, node = configs_from_parameters(fixed or {})
        found = matched = 0
        for pair in iter_pairs(contents, Pairer.from_config(node.pairing)):
            src, tgt = pair.source.payload, pair.target.payload
            found += 1
            truth = contents.ground_truth.get(int(src.stamp_ns))
            if truth is None and has_truth:
                continue
            matched += truth is not None
            pairs.append(TunePair(name, found - 1, src.xyz, tgt.xyz, truth,
                                  int(src.stamp_ns), src.frame_id, tgt.frame_id))
        if not found:
            raise ReplayError(f'{bag}: no pair of a {source_topic} and a {target_topic} cloud')
        if has_truth and not matched:
            raise ReplayError(f'{bag}: the ground truth matches no source stamp (tuning '
                              'needs the truth of some pairs)')
        if has_truth:
            with_truth.add(name)
    if with_truth and len(with_truth) < len(bags):
        raise ReplayError('some bags have ground truth and some do not: tune them apart (the '
                          'two objectives do not add up)')
    return pairs, read


def judged_by(pairs: Sequence[TunePair]) -> str:
    """Return what judges the pairs: 'ground truth' when they have it, else 'consistency'."""
    return 'ground truth' if pairs and pairs[0].truth is not None else 'consistency'


def read_ground_truth(path: Path) -> dict[int, np.ndarray]:
    """
    Read ``STAMP_NS x y z qx qy qz qw`` lines (source -> target, metres) into a stamp map.

    Lines starting with ``#`` are comments.
    """
    from ..geometry import make_transform, quaternion_to_matrix

    truth = {}
    try:
        lines = Path(path).read_text(encoding='utf-8').splitlines()
    except OSError as exc:
        raise ReplayError(f'cannot read the ground truth {path}: {exc}') from exc
    for number, line in enumerate(lines, 1):
        parts = line.split('#', 1)[0].split()
        if not parts:
            continue
        try:
            stamp, values = int(parts[0]), [float(x) for x in parts[1:]]
        except ValueError:
            values = []
        if len(values) != 7:
            raise ReplayError(f'{path}:{number}: expected STAMP_NS x y z qx qy qz qw')
        truth[stamp] = make_transform(quaternion_to_matrix(values[3:]), values[:3])
    return truth


def holdout_split(pairs: Sequence[TunePair], share: float, seed: int
                  ) -> tuple[list[TunePair], list[TunePair]]:
    """
    Return (tuned on, held out): ``share`` of the pairs, chosen by a seeded shuffle.

    None is held out when that would leave fewer than ``MIN_HELD_OUT`` pairs (or none) to it.
    """
    order = np.random.default_rng(seed).permutation(len(pairs))
    held = min(int(round(share * len(pairs))), len(pairs) - 1)
    held = held if held >= MIN_HELD_OUT else 0
    keep = sorted(order[held:])
    return [pairs[i] for i in keep], [pairs[i] for i in sorted(order[:held])]


def reference_voxel(pairs: Sequence[TunePair]) -> float:
    """Return the automatic voxel size of the first pair's target (as ``cgags-replay``)."""
    return auto_voxel_size(pairs[0].target)


def criteria_for(voxel: float, max_re_deg: float | None, max_te_m: float | None
                 ) -> SuccessCriteria:
    """Return fixed success limits: a trial's own voxel must not loosen them."""
    return SuccessCriteria(DEFAULT_MAX_RE_DEG if max_re_deg is None else max_re_deg,
                           DEFAULT_MAX_TE_VOXELS * voxel if max_te_m is None else max_te_m)


def voxel_grid(reference: float, start: float | None) -> list[float]:
    """Return the voxel sizes searched: a log grid covering the reference and the start."""
    from ..config import PipelineConfig

    lo = min(reference, start or reference) / 10 ** GRID_SPAN
    hi = max(reference, start or reference) * 10 ** GRID_SPAN
    k_lo = math.floor(GRID_STEPS * math.log10(lo / reference))
    k_hi = math.ceil(GRID_STEPS * math.log10(hi / reference))
    grid = [float(f'{reference * 10 ** (k / GRID_STEPS):.3g}') for k in range(k_lo, k_hi + 1)]
    bounds = next(f.metadata for f in dataclasses.fields(PipelineConfig) if f.name == 'voxel_size')
    return [v for v in grid if bounds['low'] <= v <= bounds['high']]  # what the node accepts


def search_space(refusals: Iterable[str], fixed: Iterable[str] = ()) -> dict[str, tuple]:
    """
    Return the settings beside ``voxel_size`` that the bags' refusal codes call for.

    A setting the user ``fixed`` (its key) is never searched, whatever the refusals.
    """
    codes = {RefusalCode(code) for code in refusals}
    fixed = set(fixed)
    return {name: choices for code, (name, choices) in FIXES.items()
            if code in codes and name not in fixed}


def replay(pairs: Sequence[TunePair], settings: dict[str, Any],
           criteria: SuccessCriteria) -> tuple[Score, list[PairRow]]:
    """Register every pair with ``settings`` (bag by bag, a stream each) and score it."""
    pipe, node = configs_from_parameters(settings)
    rows = []
    for bag in dict.fromkeys(p.bag for p in pairs):
        tracker = stream_tracker(pipe, node.mode)
        for p in (p for p in pairs if p.bag == bag):
            rows.append(register_row(empty_row(p), p.source, p.target, pipe, tracker=tracker))
    return score(pairs, rows, settings, criteria), rows


def empty_row(pair: TunePair) -> PairRow:
    """Return the report row of ``pair`` before its registration."""
    return PairRow(index=pair.index, source_stamp_ns=pair.stamp_ns, target_stamp_ns=None,
                   source_frame=pair.source_frame, target_frame=pair.target_frame,
                   valid=False, ground_truth=pair.truth)


def score(pairs: Sequence[TunePair], rows: Sequence[PairRow], settings: dict[str, Any],
          criteria: SuccessCriteria) -> Score:
    """
    Judge the registered ``rows`` of ``pairs`` (same order) and return their score.

    Against the ground truth when the pairs have it, else by :func:`check_consistency`
    with ``settings``.
    """
    how = judged_by(pairs)
    unconfirmed = 0
    if how == 'consistency':
        unconfirmed = check_consistency(pairs, rows, settings, criteria)
    else:
        for row in rows:
            row.evaluate(criteria)
    refusals: dict[str, int] = {}
    for row in rows:
        if row.refusal is not None:
            refusals[row.refusal.code.value] = refusals.get(row.refusal.code.value, 0) + 1
    right = sum(bool(r.success) for r in rows)
    wrong = sum(bool(r.valid and r.success is False) for r in rows)
    times = [r.time_s for r in rows if r.time_s is not None]
    median = float(np.median(times)) if times else 0.0
    return Score(len(rows), right, wrong, median, refusals, how, unconfirmed)


def check_consistency(pairs: Sequence[TunePair], rows: Sequence[PairRow],
                      settings: dict[str, Any], criteria: SuccessCriteria) -> int:
    """
    Judge each valid row by the reverse registration of its pair; return those unconfirmed.

    The reverse (target onto source, ``settings`` with the sensors swapped, global: no
    tracking) must compose with the row's estimate to the identity within ``criteria``:
    then the row's ``success`` is True; a valid reverse that disagrees makes it False (the
    pair counts as wrong); a refused reverse leaves it None (neither). An invalid row is not
    right (False).
    """
    from ..pipeline import register_clouds  # here: the CLI must start without Open3D

    pipe, _ = configs_from_parameters(settings)
    unconfirmed = 0
    for pair, row in zip(pairs, rows):
        row.success = False
        if not row.valid or row.transform is None:
            continue
        try:
            reverse = register_clouds(pair.target, pair.source, config=pipe,
                                      source_sensor=pipe.frontend.target_sensor,
                                      target_sensor=pipe.frontend.source_sensor)
        except InvalidInputError:
            reverse = None
        if reverse is None or not reverse.valid:
            row.success = None
            unconfirmed += 1
            continue
        implied = np.linalg.inv(np.asarray(reverse.transform, dtype=np.float64))
        row.re_deg = rotation_error_deg(row.transform, implied)
        row.te_m = translation_error(row.transform, implied)
        row.success = bool(row.re_deg <= criteria.max_re_deg
                           and row.te_m <= criteria.max_te_m)
    return unconfirmed


def params_yaml(settings: dict[str, Any], comment: str = '') -> str:
    """Return a ROS 2 parameters file (``register_node: ros__parameters:``) of ``settings``."""
    import yaml

    values = {k: ros_value(v) for k, v in sorted(settings.items())}
    head = ''.join(f'# {line}\n' for line in comment.splitlines())
    return head + yaml.safe_dump({NODE_NAME: {'ros__parameters': values}}, sort_keys=False)
