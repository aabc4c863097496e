"""
One scan of a relocalization over several scans, run where the map is prepared.

The node's registration process holds the map's features (:mod:`.isolated`), so the
:class:`~.relocalizer.Relocalizer` of a sequence lives there too, one per process: a
:class:`SequenceStep` sent as the target of a registration adds the scan to it and the
answer comes back as a :class:`StepAnswer` (the scan's own registration and the
relocalizer's verdict, without the clouds). A process that was restarted has forgotten the
sequence: the next step starts a new one, and ``scans_used`` says so.

This module is light (numpy only at import), so that the node's process, which never loads
Open3D, can build the steps.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from ..config.pipeline import PipelineConfig
from ..refusal import Judged, Refusal

_relocalizer: Any = None  # in the process running the pipeline: the sequence's relocalizer


@dataclasses.dataclass(frozen=True)
class SequenceStep:
    """
    Add a scan to the process's relocalization sequence (the target of a registration).

    :ivar map_target: the map the scans are registered onto (a ``MapRef`` or a ``PreparedMap``).
    :ivar odom_from_sensor: 4x4 pose of the sensor in the odometry frame at the scan's stamp
        (metres); None: no odometry, the scan is judged alone and the sequence starts over.
    :ivar max_scans: scans after which an unconfirmed answer is refused.
    :ivar restart: forget the scans so far first.
    """

    map_target: Any
    odom_from_sensor: np.ndarray | None
    max_scans: int
    restart: bool


@dataclasses.dataclass
class StepAnswer(Judged):
    """
    The relocalizer's answer after one scan, as :class:`~.relocalizer.Answer` without clouds.

    :ivar refusal: why not confirmed (None: confirmed).
    :ivar result: the scan's own registration (a ``PipelineResult``).
    :ivar confirmed, done, transform, map_from_odom, scans_used: as in ``Answer``.
    :ivar hypotheses: how many hypotheses the sequence holds.
    """

    refusal: Refusal | None
    result: Any
    confirmed: bool
    done: bool
    transform: np.ndarray
    map_from_odom: np.ndarray
    scans_used: int
    hypotheses: int


def run_step(source: np.ndarray, step: SequenceStep, prepared: Any,
             config: PipelineConfig) -> StepAnswer:
    """Add ``source`` (sensor frame, metres) to this process's sequence on ``prepared``."""
    from .relocalizer import Relocalizer, SequenceConfig

    global _relocalizer
    reloc = _relocalizer
    if (step.restart or reloc is None or reloc.prepared is not prepared
            or reloc.config != config or reloc.sequence.max_scans != step.max_scans):
        reloc = _relocalizer = Relocalizer(prepared, config,
                                           SequenceConfig(max_scans=step.max_scans))
    answer = reloc.add(source, step.odom_from_sensor)
    return StepAnswer(answer.refusal, answer.results[-1], answer.confirmed, answer.done,
                      answer.transform, answer.map_from_odom, answer.scans_used,
                      len(answer.hypotheses))
