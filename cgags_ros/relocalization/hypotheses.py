"""
Hypotheses of a relocalization over several scans, their checks, and the decision.

Each hypothesis is a pose of the odometry frame in the map, checked on every scan;
:func:`judge` decides between them.

See :mod:`.relocalizer` for the method; this module holds what is checked and how the checks
decide, a pure function of them, so that thresholds can be studied on recorded checks.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from ..config.pipeline import PipelineConfig
from ..geometry import rotation_error_deg, translation_error
from ..pipeline.candidates import distinct
from ..pipeline.result import PipelineResult
from ..refusal import Judged, Refusal, RefusalCode
from ..validity import (more_scans_refusal, sequence_ambiguity_refusal, unalike,
                        unexplained_refusal)


@dataclasses.dataclass
class SequenceConfig:
    """
    How scans and odometry decide between hypotheses.

    :ivar max_scans: scans taken before an unconfirmed answer is refused.
    :ivar min_scans: scans a confirmed answer needs (1: one valid scan confirms, as a single
        registration is judged; 2, the default: a second scan must agree, since a valid
        single scan is now and then a turned room).
    :ivar submap: from the second scan on, when the scans' own candidates do not settle it,
        also register every scan so far, fused with the odometry into the latest scan's
        frame, onto the map; its candidates are hypotheses too (more of the place in view
        than any one scan).
    :ivar drift_deg: rotation (degrees) a check may move a scan from where the hypothesis
        puts it, a step: the odometry's drift and the error of the registration the
        hypothesis came from (a few degrees and centimetres).
    :ivar drift_m: translation (metres) it may move it, a step...
    :ivar drift_fraction: ...plus this share of the distance travelled.
    :ivar min_fitness: a scan explains a hypothesis only with at least this fitness.
    :ivar refute_ratio: a contender is refuted by a scan that the best hypothesis fits this
        many times better (or, one the contender does not explain, fits at all better).
    """

    max_scans: int = 3
    min_scans: int = 2
    submap: bool = True
    drift_deg: float = 5.0
    drift_m: float = 0.2
    drift_fraction: float = 0.05
    min_fitness: float = 0.3
    refute_ratio: float = 1.2


@dataclasses.dataclass
class Check:
    """
    One scan put where one hypothesis predicts it, refined against the map.

    :ivar transform: the refined pose, map <- sensor (metres).
    :ivar moved_deg, moved_m: how far the refinement moved it from the prediction.
    :ivar steps, travelled_m: scans and odometry distance (metres) between the scan and the
        one that proposed the hypothesis (the drift allowance grows with them).
    :ivar fitness: share of the scan's points within the refinement distance of the map.
    :ivar free_space: the free-space violation of the refined pose (NaN: not measured).
    :ivar descriptor_ratio, observability: the scan's overlap with the map under the refined
        pose, measured as a single registration's (``PipelineResult``; NaN: not measured,
        which no gate refuses).
    """

    transform: np.ndarray
    moved_deg: float
    moved_m: float
    steps: int
    travelled_m: float
    fitness: float
    free_space: float
    descriptor_ratio: float = float('nan')
    observability: float = float('nan')

    def explains(self, seq: SequenceConfig, config: PipelineConfig) -> bool:
        """
        Tell whether the scan fits the hypothesis within the drift allowance.

        It must also pass the single registration's gates on what it shares with the map:
        free space (``gates.max_free_space_violation``), an overlap that constrains every
        motion (``gates.min_observability``) and a shared surface whose descriptors look
        alike (:func:`~cgags_ros.validity.unalike`). A scan placed in a wrong place of a
        larger map can fit its surfaces there (a floor, walls) without them looking like
        its own; on a degenerate overlap (a road, a floor) it fits anywhere along it, and
        whether its descriptors look alike is not judged: such a check says nothing.
        """
        return (self.moved_deg <= seq.drift_deg * max(self.steps, 1)
                and self.moved_m <= (seq.drift_m * max(self.steps, 1)
                                     + seq.drift_fraction * self.travelled_m)
                and self.fitness >= seq.min_fitness
                and not self.free_space > config.gates.max_free_space_violation
                and not self.observability < config.gates.min_observability
                and not unalike(self.descriptor_ratio, self.observability, config))


@dataclasses.dataclass
class Hypothesis:
    """
    A pose of the odometry frame in the map and its checks, one a scan.

    :ivar map_from_odom: 4x4 map <- odom as proposed (metres).
    :ivar scan: the scan whose candidate proposed it; ``rank`` that candidate's rank;
        ``source`` 'scan', 'submap' (the scans so far fused, in that scan's frame) or
        'symmetry' (a hypothesis turned by a symmetry of the map).
    :ivar inliers: the proposing candidates' inliers (summed when several proposed it).
    :ivar checks: scan index -> :class:`Check`.
    """

    map_from_odom: np.ndarray
    scan: int
    rank: int
    inliers: int
    source: str = 'scan'
    checks: dict[int, Check] = dataclasses.field(default_factory=dict)

    def summary(self, seq: SequenceConfig, config: PipelineConfig) -> dict[str, Any]:
        """Return a JSON-friendly dict: the pose, who proposed it, how each scan sees it."""
        return {'map_from_odom': self.map_from_odom.tolist(), 'proposed_by_scan': self.scan,
                'candidate_rank': self.rank, 'inliers': self.inliers,
                'scans_explained': sum(c.explains(seq, config)
                                       for c in self.checks.values()),
                'fitness': [round(self.checks[i].fitness, 4) for i in sorted(self.checks)]}


@dataclasses.dataclass
class Answer(Judged):
    """
    What the relocalizer says after a scan.

    :ivar confirmed: one hypothesis explains every scan used and its contenders are refuted.
    :ivar done: confirmed, or refused (``max_scans`` used); else it asks for another scan.
    :ivar transform: 4x4 map <- the latest scan's sensor (the best hypothesis's pose).
    :ivar map_from_odom: 4x4 map <- odom of the best hypothesis.
    :ivar scans_used: scans taken; ``refusal``: why not confirmed (None when confirmed; its
        message is ``reason``).
    :ivar hypotheses: ranked, best first; ``results``: each scan's own registration.
    """

    confirmed: bool
    done: bool
    transform: np.ndarray
    map_from_odom: np.ndarray
    scans_used: int
    refusal: Refusal | None
    hypotheses: list[Hypothesis]
    results: list[PipelineResult]


def judge(hypotheses: list[Hypothesis], results: list[PipelineResult], odom: list[np.ndarray],
          config: PipelineConfig, seq: SequenceConfig) -> Answer:
    """
    Rank checked hypotheses over two scans or more and decide (see the module doc).

    A scan that no hypothesis explains, not even one its own candidates proposed (each is
    moved to where its scan settles first), fits the map nowhere: taken where the map has
    nothing, or too little of it in view. It says nothing for or against any hypothesis and
    is left out. With one scan left the answer is that scan's own verdict when it is the
    latest (else refused: the latest scan is not in the map); with none, refused. A scan
    that fits somewhere, but not where the odometry puts it under a hypothesis, refutes it,
    unless it fits where that hypothesis's check moved it better than under the best.

    A pure function of the checks, so that thresholds can be studied on recorded ones.
    """
    n = len(results)

    def explains(h: Hypothesis, i: int) -> bool:  # a check left out: refuted earlier
        return i in h.checks and h.checks[i].explains(seq, config)

    if not hypotheses:
        return make_answer(results[-1].transform, odom[-1], results[-1].refusal
                           or Refusal(RefusalCode.NO_ESTIMATE, 'no scan gave a candidate pose'),
                           [], results, seq)
    void = [i for i in range(n) if not any(explains(h, i) for h in hypotheses)]
    used = [i for i in range(n) if i not in void]

    def explained(h: Hypothesis) -> list[bool]:  # only the scans some hypothesis explains
        return [explains(h, i) for i in used]

    def score(h: Hypothesis) -> tuple:
        return (sum(explained(h)), sum(c.fitness for c in h.checks.values()), h.inliers)

    def latest(h: Hypothesis) -> np.ndarray:  # the latest scan's pose under h
        return (h.checks[n - 1].transform if explains(h, n - 1)
                else h.map_from_odom @ odom[-1])

    ranked = sorted(hypotheses, key=score, reverse=True)
    if void and used == [n - 1]:
        return make_answer(results[-1].transform, odom[-1], results[-1].refusal, ranked,
                           results, seq, used=1)
    if void and len(used) < 2:
        return make_answer(results[-1].transform, odom[-1], unexplained_refusal(void), ranked,
                           results, seq)
    best = ranked[0]
    last = latest(best)
    misses = [i for i, ok in zip(used, explained(best)) if not ok]
    refusal = unexplained_refusal(misses) if misses else None

    def refutes(i: int, ok: bool, contender: Hypothesis) -> bool:
        # A scan the contender does not explain refutes it only when it fits the best no
        # worse: moved out of the allowance to where it fits the map better than under the
        # best, it says the best is no better placed (a scan whose own registration is off).
        if i not in contender.checks:
            return True
        fitness, best_fitness = contender.checks[i].fitness, best.checks[i].fitness
        return (fitness * seq.refute_ratio < best_fitness if ok
                else fitness <= best_fitness)

    for contender in ranked[1:] if not refusal else ():
        if any(refutes(i, ok, contender) for i, ok in zip(used, explained(contender))):
            continue  # refuted
        pose = latest(contender)
        if distinct(pose, last, config):
            refusal = sequence_ambiguity_refusal(n, rotation_error_deg(pose, last),
                                                 translation_error(pose, last))
            break
    return make_answer(last, odom[-1], refusal, ranked, results, seq, used=len(used))


def make_answer(transform: np.ndarray, odom: np.ndarray, refusal: Refusal | None,
                hypotheses: list[Hypothesis], results: list[PipelineResult],
                seq: SequenceConfig, used: int | None = None) -> Answer:
    """
    Return the answer: confirmed without a refusal and with enough scans, else why not.

    ``used``: the scans the decision rests on (default all; a scan left out does not count
    towards ``min_scans``).
    """
    n = len(results)
    used = n if used is None else used
    refusal = refusal or more_scans_refusal(used, min(seq.min_scans, seq.max_scans))
    done = refusal is None or n >= seq.max_scans
    if refusal is not None and not done:
        refusal = Refusal(refusal.code,
                          f'{refusal.message}; send another scan with its odometry pose')
    T = np.asarray(transform, dtype=np.float64)
    return Answer(refusal is None, done, T, T @ np.linalg.inv(odom), n, refusal,
                  list(hypotheses), list(results))
