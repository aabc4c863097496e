"""
Tests of cgags-calibrate on the real OpenCalib rig: cloud files and a bag, and its errors.

The bag is written here from the rig's clouds with their real capture stamps (up to 27 ms
apart), so pairing by time is exercised on real offsets.
"""

from __future__ import annotations

import json
from pathlib import Path

from bench.datasets.rigs import OPENCALIB, opencalib_rig, REFERENCE
from cgags_ros.geometry import make_transform, rotation_error_deg, translation_error
from cgags_ros.io.bag import write_bag
from cgags_ros.tools import calibrate_cli
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

RIG = ('real_world', 'right')
TOLERANCE = (0.5, 0.05)  # deg, m: the real rig's reference spread


@pytest.fixture(scope='module')
def rig(data_dir, require_shared):
    require_shared(data_dir / OPENCALIB, 'OpenCalib lidar2lidar rigs', marker=REFERENCE)
    frames, reference, _ = opencalib_rig(data_dir, *RIG)
    return data_dir / OPENCALIB / RIG[0], frames, reference


def _run(capsys, *argv) -> tuple[int, str, str]:
    code = calibrate_cli.main([str(a) for a in argv])
    out = capsys.readouterr()
    return code, out.out, out.err


def _tf2_transform(line: str) -> np.ndarray:
    tokens = line.split()
    flags = dict(zip(tokens[4::2], tokens[5::2]))
    R = Rotation.from_euler('xyz', [float(flags[k]) for k in ('--roll', '--pitch', '--yaw')])
    return make_transform(R.as_matrix(), [float(flags[k]) for k in ('--x', '--y', '--z')])


@pytest.mark.slow
def test_files_print_the_four_forms(rig, capsys):
    root, _, reference = rig
    parents = sorted(root.glob('*/top-*.pcd'))
    children = sorted(root.glob(f'*/{RIG[1]}-*.pcd'))
    code, out, err = _run(capsys, '--parent', *parents, '--child', *children,
                          '--parent-frame', 'top_lidar', '--child-frame', 'right_lidar')
    assert code == 0, err
    assert 'transform parent <- child (p_parent = R p_child + t)' in out
    line = next(x for x in out.splitlines() if x.startswith('ros2 run tf2_ros'))
    assert line.endswith('--frame-id top_lidar --child-frame-id right_lidar')
    T = _tf2_transform(line)
    assert rotation_error_deg(T, reference) <= TOLERANCE[0]
    assert translation_error(T, reference) <= TOLERANCE[1]
    assert '<parent link="top_lidar"/>' in out and '<child link="right_lidar"/>' in out
    assert 'parent_frame: top_lidar' in out and 'child_frame: right_lidar' in out  # YAML
    assert '"covariance": [' in out and '"frames": [' in out  # JSON


def _write_bag(path: Path, frames, offset_s: float = 0.0) -> None:
    messages = []
    for k, f in enumerate(frames):
        base = 100 * 10**9 + k * 5 * 10**9  # frames 5 s apart, real offsets within
        child_ns = base + (f.child_stamp_ns - f.parent_stamp_ns) + int(offset_s * 1e9)
        messages += [('/top/points', base, 'top', f.parent),
                     ('/right/points', child_ns, 'right', f.child)]
    write_bag(path, messages)


@pytest.mark.slow
def test_bag_frames_paired_by_time(rig, tmp_path, capsys):
    _, frames, reference = rig
    offsets = [(f.child_stamp_ns - f.parent_stamp_ns) * 1e-9 for f in frames]
    assert max(abs(o) for o in offsets) > 0.02  # real, unsynchronised captures
    bag = tmp_path / 'rig'
    _write_bag(bag, frames)
    code, out, err = _run(capsys, bag, '--parent-topic', '/top/points', '--child-topic',
                          '/right/points', '--json')
    assert code == 0, err
    result = json.loads(out)
    assert (result['parent_frame'], result['child_frame']) == ('top', 'right')
    assert result['valid'] and result['num_frames'] == 3
    assert np.allclose([f['time_offset_s'] for f in result['frames']], offsets, atol=1e-6)
    T = np.array(result['transform'])
    assert rotation_error_deg(T, reference) <= TOLERANCE[0]
    assert translation_error(T, reference) <= TOLERANCE[1]
    assert 'static_transform_publisher' in result['static_transform_publisher']
    assert result['refusal'] is None


def test_a_planar_scene_is_refused_with_its_code(tmp_path, capsys):
    rng = np.random.default_rng(0)
    floor = np.c_[rng.uniform(-5, 5, (20000, 2)), rng.normal(0, 0.005, 20000)]
    np.save(tmp_path / 'parent.npy', floor)
    np.save(tmp_path / 'child.npy', floor + [0.3, -0.2, 0.0])
    code, out, err = _run(capsys, '--parent', tmp_path / 'parent.npy', '--child',
                          tmp_path / 'child.npy', '--voxel-size', '0.2', '--json')
    assert code == calibrate_cli.EXIT_FAIL, err
    result = json.loads(out)
    assert not result['valid'] and result['refusal']['code'] == 'degenerate_axis', result
    assert result['refusal']['message'] == result['reason']
    code, out, _ = _run(capsys, '--parent', tmp_path / 'parent.npy', '--child',
                        tmp_path / 'child.npy', '--voxel-size', '0.2')
    assert code == calibrate_cli.EXIT_FAIL and 'FAIL (degenerate_axis): not observable' in out


def test_bag_offsets_beyond_the_limit_pair_nothing(rig, tmp_path, capsys):
    _, frames, _ = rig
    bag = tmp_path / 'late'
    _write_bag(bag, frames, offset_s=0.2)  # every child 200 ms late
    code, _, err = _run(capsys, bag, '--parent-topic', '/top/points', '--child-topic',
                        '/right/points', '--max-time-offset', '0.05')
    assert code == calibrate_cli.EXIT_ERROR
    assert 'no parent/child pair' in err and len(err.strip().splitlines()) == 1


def test_errors_are_one_line(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:  # argparse: --child without a cloud
        _run(capsys, '--parent', tmp_path / 'a.pcd', '--child')
    err = capsys.readouterr().err
    assert exc.value.code == calibrate_cli.EXIT_ERROR and len(err.strip().splitlines()) == 1
    code, _, err = _run(capsys, '--parent', tmp_path / 'a.pcd', tmp_path / 'b.pcd',
                        '--child', tmp_path / 'c.pcd')
    assert code == calibrate_cli.EXIT_ERROR and 'one cloud each per frame' in err
    code, _, err = _run(capsys, '--parent', tmp_path / 'a.pcd', '--child', tmp_path / 'c.pcd')
    assert code == calibrate_cli.EXIT_ERROR and 'no such file' in err
    code, _, err = _run(capsys, tmp_path / 'nobag', '--parent-topic', 'a')
    assert code == calibrate_cli.EXIT_ERROR and '--child-topic' in err
