"""
register_node's calibrate mode, without ROS: synchronized pairs -> one extrinsic.

ROS-free. :class:`CalibrationRun` feeds each synchronized pair of the node (source =
child sensor, target = parent sensor) to a :class:`~cgags_ros.calibration.Calibrator` and,
once it is done, hands the result to :meth:`EngineOutputs.publish_calibration` (a valid
result) or logs its reason (a FAIL, never a pose). It runs on the engine thread,
in-process: the calibrator keeps every frame's downsampled clouds and candidates for the
joint solve, which the registration process (one pair in, one result out) does not keep.
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np

from .interface import Calibration, EngineOutputs
from ..config.calibration import CalibrationConfig
from ..config.pipeline import PipelineConfig
from ..engine.pairing import Pair
from ..refusal import Refusal, RefusalCode

COLLECTING, CONVERGED, FINAL, FAILED = 'collecting', 'converged', 'max_frames', 'failed'


class CalibrationRun:
    """
    One calibration of the pair (target frame <- source frame) from the node's pairs.

    The engine thread alone takes pairs; :meth:`statistics` may be read from any thread: what it
    reads is replaced whole (the status with its refusal as one pair), so no lock is needed.
    """

    def __init__(self, config: CalibrationConfig, outputs: EngineOutputs):
        self.config, self._outputs = config, outputs
        self._calibrator: Any = None  # a Calibrator from the first frame on
        # The status, and why the calibration failed (None unless it did).
        self._ended: tuple[str, Refusal | None] = (COLLECTING, None)

    @classmethod
    def for_mode(cls, mode: str, pipeline: PipelineConfig, config: CalibrationConfig | None,
                 outputs: EngineOutputs) -> 'CalibrationRun | None':
        """Return a run in mode 'calibrate' (``config`` defaults to ``pipeline``'s), else None."""
        if mode != 'calibrate':
            return None
        return cls(config or CalibrationConfig(pipeline=pipeline), outputs)

    @property
    def status(self) -> str:
        """Tell where the calibration stands: collecting, converged, max_frames or failed."""
        return self._ended[0]

    @property
    def done(self) -> bool:
        """Tell whether the calibration has ended (published or failed)."""
        return self.status != COLLECTING

    def take(self, pair: Pair) -> Refusal | None:
        """
        Add one synchronized pair as a frame; solve, and publish once done.

        :returns: None, or why the pair is not used, for the engine's accounting.
        """
        # Imported on the first frame: it loads the pipeline (the other modes load it in
        # the engine's start()).
        from ..calibration import Calibrator, Frame, TRANSFORM_WORDS
        from ..calibration.formats import as_dict

        if self.done:
            return Refusal(RefusalCode.IGNORED, (
                f'calibration {self.status}: further pairs are not used (reconfigure the node '
                'to calibrate again)'))
        child, parent = pair.source.payload, pair.target.payload
        parent_id, child_id = str(parent.header.frame_id), str(child.header.frame_id)
        cal = self._calibrator
        if cal is None:
            cal = Calibrator(self.config, parent_frame=parent_id, child_frame=child_id)
        elif (parent_id, child_id) != (cal.parent_frame, cal.child_frame):
            return Refusal(RefusalCode.IGNORED, (
                f'calibration pair {parent_id} <- {child_id} is not the one being calibrated '
                f'({cal.parent_frame} <- {cal.child_frame}): ignored'))
        cal.add(Frame(parent.xyz, child.xyz, f'{pair.target.stamp_ns}',
                      pair.target.stamp_ns, pair.source.stamp_ns))
        self._calibrator = cal
        if len(cal.evidence) >= cal.config.min_frames:
            cal.solve()
        if not cal.done:
            return None
        result = cal.result if cal.result is not None else cal.solve()
        status = CONVERGED if result.converged else FINAL
        if not result.valid or result.transform is None:
            status = FAILED
        self._ended = (status, result.refusal)
        frames = f'{result.num_agreeing} of {len(result.frames)} frames agree'
        if status == FAILED:
            self._outputs.log('error', f'calibration FAILED ({frames}): {result.refusal}')
            return None
        report = as_dict(result)
        self._outputs.publish_calibration(Calibration(
            np.asarray(result.transform, dtype=np.float64),
            np.asarray(result.covariance, dtype=np.float64), parent.header,
            result.parent_frame, result.child_frame, json.dumps(report)))
        self._outputs.log('info', f'calibration {status} ({frames}): {TRANSFORM_WORDS}, '
                          f'parent {result.parent_frame}, child {result.child_frame}: '
                          f"{report.get('static_transform_publisher', '')}")
        return None

    def statistics(self) -> dict[str, Any]:
        """Return the ``calibration.*`` keys of /diagnostics."""
        cal, (status, refusal) = self._calibrator, self._ended
        stats: dict[str, Any] = {'calibration.status': status,
                                 'calibration.max_frames': self.config.max_frames}
        if cal is not None:
            stats['calibration.parent_frame'] = cal.parent_frame
            stats['calibration.child_frame'] = cal.child_frame
            stats['calibration.frames_taken'] = len(cal.evidence)
            if cal.result is not None:
                stats['calibration.frames_agreeing'] = cal.result.num_agreeing
        if refusal:
            stats['calibration.reason'] = refusal.message
            stats['calibration.refusal_code'] = refusal.code.value
        return stats
