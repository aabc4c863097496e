"""
register_node's calibrate mode without ROS: synchronized pairs -> Calibrator -> outputs.

The engine is fed the simulated OpenCalib rig (parent = top LiDAR as target_cloud, child =
left LiDAR as source_cloud) and publishes into a recorder; the result is checked against
the rig's reference extrinsic within its spread, and nothing may be published before the
calibration has ended. A planar scene must end as a FAIL: logged, no pose.
"""

from __future__ import annotations

import json
import time

from bench.datasets.rigs import OPENCALIB, opencalib_rig, REFERENCE
from cgags_ros.config.calibration import CalibrationConfig
from cgags_ros.config.node import NodeConfig
from cgags_ros.config.pipeline import PipelineConfig
from cgags_ros.engine.engine import RegistrationEngine
from cgags_ros.engine.interface import Cloud
from cgags_ros.geometry import rotation_error_deg, translation_error
import numpy as np
import pytest
from test_calibration import _plane_rig
from test_engine import balanced, Header, Recorder
from waiting import wait_for

pytestmark = pytest.mark.slow
VOXEL = 0.3  # test_calibration's OpenCalib voxel
TOLERANCE = (0.2, 0.03)  # simulated rig: deg, m (the reference spread)


class CalibrationRecorder(Recorder):
    """Recorder that also records calibrations."""

    def __init__(self):
        super().__init__()
        self.calibrations = []

    def publish_calibration(self, calibration):
        self.calibrations.append(calibration)


@pytest.fixture(scope='module')
def rig(data_dir, require_shared):
    require_shared(data_dir / OPENCALIB, 'OpenCalib lidar2lidar rigs', marker=REFERENCE)
    frames, reference, _ = opencalib_rig(data_dir, 'carla_data', 'left')
    return frames, reference


def make(voxel=VOXEL, **calibration):
    out = CalibrationRecorder()
    pipe = PipelineConfig(voxel_size=voxel)
    engine = RegistrationEngine(pipe, NodeConfig(mode='calibrate'), out,
                                calibration=CalibrationConfig(pipeline=pipe, **calibration))
    engine.start()
    engine.activate()
    return engine, out


def send_frame(engine, k, parent, child, parent_id='top', child_id='left'):
    """
    Send frame ``k``: the child 20 ms before the parent (within sync_slop).

    A synchronized pair is final once a parent stamp at or after the child's has arrived.
    """
    t = 10.0 + k
    for role, xyz, frame, stamp in (('target', parent, parent_id, t),
                                    ('source', child, child_id, t - 0.02)):
        engine.receive(role, int(round(stamp * 1e9)), frame,
                       Cloud(np.asarray(xyz, dtype=np.float64), Header(frame, stamp),
                             time.monotonic_ns()))


def taken(engine, n):
    return lambda: engine.statistics().get('calibration.frames_taken') == n


def test_three_synchronized_frames_give_the_reference_extrinsic(rig):
    frames, reference = rig
    engine, out = make()
    try:
        for k, f in enumerate(frames[:3]):
            if k == 1:  # a deactivate/activate cycle keeps the frames taken so far
                engine.deactivate()
                send_frame(engine, 1, f.parent, f.child)
                assert engine.snapshot()['rejected'] == {'inactive': 1}
                engine.activate()
            send_frame(engine, k + 2, f.parent, f.child)
            wait_for(taken(engine, k + 1), 300, f'frame {k} taken')
            if k < 2:  # min_frames is 3: nothing before
                assert not out.calibrations
                assert engine.statistics()['calibration.status'] == 'collecting'
        wait_for(lambda: out.calibrations, 60, 'a calibration')
        cal = out.calibrations[0]
        assert (cal.parent_frame, cal.child_frame) == ('top', 'left')
        assert cal.header.frame_id == 'top'
        assert rotation_error_deg(cal.transform, reference) <= TOLERANCE[0]
        assert translation_error(cal.transform, reference) <= TOLERANCE[1]
        assert cal.covariance.shape == (6, 6) and np.all(np.diag(cal.covariance) > 0)
        report = json.loads(cal.report)
        assert report['valid'] and report['parent_frame'] == 'top'
        assert '--frame-id top --child-frame-id left' in report['static_transform_publisher']
        stats = engine.statistics()
        assert stats['calibration.status'] in ('converged', 'max_frames')
        assert stats['calibration.frames_agreeing'] == 3
        # A pair after the end is counted, not used; nothing more is published.
        f = frames[0]
        send_frame(engine, 9, f.parent, f.child)
        wait_for(lambda: engine.snapshot()['rejected'].get('ignored') == 1, 30,
                 'the extra pair counted')
        assert len(out.calibrations) == 1
        balanced(engine)
    finally:
        engine.stop()


def test_a_planar_scene_fails_with_the_reason_and_no_pose():
    frames = _plane_rig([(np.array([0.0, 0.0, 1.0]), 0.0)], 1)
    engine, out = make(0.2, max_frames=len(frames))
    try:
        for k, f in enumerate(frames):
            send_frame(engine, k, f.parent, f.child, 'base_lidar', 'cam')
            wait_for(taken(engine, k + 1), 120, f'frame {k} taken')
        wait_for(lambda: engine.statistics()['calibration.status'] == 'failed', 60, 'a FAIL')
        assert not out.calibrations
        assert engine.statistics()['calibration.reason'].startswith('not observable')
        assert engine.statistics()['calibration.refusal_code'] == 'degenerate_axis'
        assert any(level == 'error' and 'calibration FAILED' in m for level, m in out.logs)
    finally:
        engine.stop()
