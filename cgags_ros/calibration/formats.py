"""
The extrinsic in the forms a user pastes: tf2 command line, URDF joint, YAML, JSON.

Every form is the transform parent <- child (``p_parent = R p_child + t``): the pose of
the child frame in the parent frame, which is what ``static_transform_publisher
--frame-id PARENT --child-frame-id CHILD`` and a URDF joint's ``<origin>`` (parent link
-> child link) both take. Angles are roll, pitch, yaw in radians about the fixed parent
axes x, y, z: ``R = Rz(yaw) Ry(pitch) Rx(roll)``, the convention of both.
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np

from .result import CalibrationResult, TRANSFORM_WORDS
from ..geometry import matrix_to_quaternion, rpy


def static_transform_publisher(T: np.ndarray, parent: str, child: str) -> str:
    """Return the ``ros2 run tf2_ros static_transform_publisher`` line (named flags)."""
    x, y, z = (float(v) for v in T[:3, 3])
    roll, pitch, yaw = rpy(T)
    return (f'ros2 run tf2_ros static_transform_publisher --x {x:.6f} --y {y:.6f} '
            f'--z {z:.6f} --roll {roll:.6f} --pitch {pitch:.6f} --yaw {yaw:.6f} '
            f'--frame-id {parent} --child-frame-id {child}')


def urdf_joint(T: np.ndarray, parent: str, child: str) -> str:
    """Return a fixed URDF ``<joint>`` from link ``parent`` to link ``child``."""
    x, y, z = (float(v) for v in T[:3, 3])
    roll, pitch, yaw = rpy(T)
    return '\n'.join([
        f'<!-- {TRANSFORM_WORDS}: pose of {child} in {parent} -->',
        f'<joint name="{parent}_to_{child}" type="fixed">',
        f'  <parent link="{parent}"/>',
        f'  <child link="{child}"/>',
        f'  <origin xyz="{x:.6f} {y:.6f} {z:.6f}" rpy="{roll:.6f} {pitch:.6f} {yaw:.6f}"/>',
        '</joint>'])


def as_dict(result: CalibrationResult) -> dict[str, Any]:
    """Return the result as the YAML/JSON mapping: pose forms, uncertainty, frames."""
    out = result.summary()
    T = result.transform
    if T is not None:
        roll, pitch, yaw = rpy(T)
        q = matrix_to_quaternion(T[:3, :3])
        out['translation_m'] = {k: float(v) for k, v in zip('xyz', T[:3, 3])}
        out['rpy_rad'] = {'roll': roll, 'pitch': pitch, 'yaw': yaw}
        out['quaternion_xyzw'] = [float(v) for v in q]
        if result.valid:
            out['static_transform_publisher'] = static_transform_publisher(
                T, result.parent_frame, result.child_frame)
            out['urdf_joint'] = urdf_joint(T, result.parent_frame, result.child_frame)
    return out


def to_json(result: CalibrationResult) -> str:
    """Return :func:`as_dict` as indented JSON."""
    return json.dumps(as_dict(result), indent=2)


def to_yaml(result: CalibrationResult) -> str:
    """Return the pose and its uncertainty as YAML (frames' details: see the JSON)."""
    import yaml

    d = as_dict(result)
    keys = ('valid', 'reason', 'refusal', 'transform_meaning', 'parent_frame', 'child_frame',
            'translation_m', 'rpy_rad', 'quaternion_xyzw', 'std', 'unobservable',
            'num_frames', 'num_agreeing', 'converged')
    return yaml.safe_dump({k: d[k] for k in keys if k in d}, sort_keys=False)


def to_text(result: CalibrationResult) -> str:
    """Return the report a user reads: verdict, the four forms (when valid), the frames."""
    P, C = result.parent_frame, result.child_frame
    lines = [f'{TRANSFORM_WORDS}, parent = {P}, child = {C}']
    if result.valid:
        s = result.std
        lines += [
            f'OK: {result.num_agreeing} of {len(result.frames)} frames agree'
            + ('' if result.converged else ' (not converged: the last frame still moved '
               'the estimate by more than one standard deviation, or too few frames)'),
            f"std: x {1000 * s['x_m']:.1f} mm, y {1000 * s['y_m']:.1f} mm, z "
            f"{1000 * s['z_m']:.1f} mm, rx {s['rx_deg']:.3f} deg, ry {s['ry_deg']:.3f} deg, "
            f"rz {s['rz_deg']:.3f} deg",
            '', '# tf2 (pose of the child frame in the parent frame):',
            static_transform_publisher(result.transform, P, C),
            '', '# URDF:', urdf_joint(result.transform, P, C),
            '', '# YAML:', to_yaml(result).rstrip(),
            '', '# JSON (with the covariance and every frame; --json prints it alone):',
            to_json(result)]
    else:
        lines.append(f'FAIL ({result.refusal.code.value}): {result.reason}')
    lines.append('')
    lines.append('frames:')
    for f in result.frames:
        offset = ('' if not np.isfinite(f.time_offset_s)
                  else f', dt {1000 * f.time_offset_s:+.0f} ms')
        verdict = 'agrees' if f.agrees else f'disagrees ({f.reason})'
        alone = 'valid alone' if f.single_frame_valid else 'refused alone'
        lines.append(f'  {f.name}: {verdict}; {alone}; fitness {f.fitness:.3f}, '
                     f'shift {1000 * f.shift_m:.1f} mm{offset}')
    return '\n'.join(lines)
