"""
Clouds not in their sensor's frame: ``frontend.source_sensor`` and ``frontend.target_sensor``.

The bundled redkitchen bag (real depth-camera clouds, in their camera's frame) is moved as a
tool that re-centres clouds would: every cloud by one rigid motion M, its ground truth with
it. The sensor then sits at M's translation in every cloud's frame. Judged from the frames'
origins, right poses are refused; with the sensors' positions given by a config (a YAML
file, ``--set``), the same pairs register valid and right, through the Python API and
``cgags-replay``.
"""

from __future__ import annotations

from pathlib import Path

from cgags_ros.config import configs_from_parameters, load_yaml, pipeline_config_from
from cgags_ros.errors import InvalidConfigError
from cgags_ros.geometry import apply_transform, make_transform, rotation_error_deg
from cgags_ros.geometry import translation_error
from cgags_ros.io.bag import read_messages, write_bag
from cgags_ros.io.clouds import write_cloud
from cgags_ros.io.pointcloud2 import pointcloud2_to_xyz, pose_to_transform
from cgags_ros.pipeline import register_clouds
from cgags_ros.pipeline.map import load_map
from cgags_ros.pipeline.register import terrain_patch
from cgags_ros.tools import replay
from cgags_ros.tools.demo import DEMO_BAGS
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
import yaml

VOXEL = 0.05
MAX_RE_DEG, MAX_TE = DEMO_BAGS['redkitchen']
MOTION = make_transform(Rotation.from_euler('xyz', [70, -40, 120], degrees=True).as_matrix(),
                        [8.0, -6.0, 5.0])
# Two of the bag's four pairs, one refused each way without the sensors' positions:
# ambiguous (the front end, its normals facing the wrong way, proposes a wrong pose) and
# low_confidence (the free-space measure reads the right pose from a viewpoint no sensor had).
PAIRS = (1, 2)
SENSOR = [float(c) for c in MOTION[:3, 3]]


@pytest.fixture(scope='module')
def moved(data_dir: Path) -> list[tuple]:
    """Return the chosen pairs ``(stamp_ns, source, target, truth)``, all moved by MOTION."""
    clouds: dict[str, list] = {'/source_cloud': [], '/target_cloud': [], '/ground_truth': []}
    for rec in read_messages(data_dir / 'bags' / 'redkitchen', list(clouds)):
        assert not rec.error
        if rec.topic == '/ground_truth':
            value = MOTION @ pose_to_transform(rec.msg) @ np.linalg.inv(MOTION)
        else:
            value = apply_transform(MOTION, pointcloud2_to_xyz(rec.msg))
        clouds[rec.topic].append((rec.stamp_ns, value))
    # The bag's pairing (latest_target): source k was taken with target k.
    return [(clouds['/source_cloud'][k][0], clouds['/source_cloud'][k][1],
             clouds['/target_cloud'][k][1], clouds['/ground_truth'][k][1]) for k in PAIRS]


def _right(transform: np.ndarray, truth: np.ndarray) -> bool:
    """Tell whether ``transform`` meets redkitchen's limits in the camera's frame."""
    # Taken back to the camera's frame: the translation error of a moved frame would also
    # count the rotation error times M's lever arm.
    back = np.linalg.inv(MOTION)
    transform, truth = back @ transform @ MOTION, back @ truth @ MOTION
    return (rotation_error_deg(transform, truth) < MAX_RE_DEG
            and translation_error(transform, truth) < MAX_TE)


def test_moved_clouds_register_with_their_sensors_positions_from_a_config(moved, tmp_path):
    path = tmp_path / 'sensors.yaml'
    path.write_text(yaml.safe_dump({'voxel_size': VOXEL, 'frontend': {
        'source_sensor': SENSOR, 'target_sensor': SENSOR}}))
    config = pipeline_config_from(load_yaml(path))
    for _, source, target, truth in moved:
        unknown = register_clouds(source, target, voxel_size=VOXEL)
        assert not unknown.valid, 'judged from the frame origin, the pair is refused'
        result = register_clouds(source, target, config=config)
        assert result.valid, result.reason
        assert _right(result.transform, truth)
        # The config's positions are the arguments' defaults: the same answer.
        given = register_clouds(source, target, voxel_size=VOXEL, source_sensor=SENSOR,
                                target_sensor=SENSOR)
        assert np.allclose(given.transform, result.transform)


def test_cgags_replay_takes_the_sensors_positions_from_set(moved, tmp_path):
    bag = tmp_path / 'redkitchen_moved'
    messages = []
    for stamp, source, target, truth in moved:
        messages += [('/target_cloud', stamp - 1, 'moved', target),
                     ('/source_cloud', stamp, 'moved', source),
                     ('/ground_truth', stamp, 'moved', truth)]
    write_bag(bag, messages)

    def replayed(*sets: str):
        argv = [str(bag), '--voxel-size', str(VOXEL), '--quiet', '--output',
                str(tmp_path / 'out')]
        for item in sets:
            argv += ['--set', item]
        report = replay.run(*replay.options_from_args(replay.build_parser().parse_args(argv)))
        assert len(report.rows) == len(PAIRS)
        return report.rows

    assert not any(row.valid for row in replayed())
    rows = replayed(f'frontend.source_sensor={SENSOR}', f'frontend.target_sensor={SENSOR}')
    for row, (_, _, _, truth) in zip(rows, moved):
        assert row.valid and _right(row.transform, truth), row


def test_a_sensor_position_in_a_config_is_three_finite_numbers_or_empty():
    config = pipeline_config_from({'frontend.source_sensor': [1, 2, 3],
                                   'frontend.target_sensor': []})
    assert config.frontend.source_sensor == (1.0, 2.0, 3.0)
    assert config.frontend.target_sensor is None  # empty: the cloud's origin
    for bad in ([1.0, 2.0], [1.0, 2.0, 3.0, 4.0], [0.0, float('nan'), 0.0], 'base_link', 5.0,
                [True, 0.0, 0.0]):
        with pytest.raises(InvalidConfigError, match=r'frontend.target_sensor must be \[x, y'):
            pipeline_config_from({'frontend.target_sensor': bad})


def test_a_map_target_has_no_sensor(tmp_path):
    path = tmp_path / 'map.ply'
    write_cloud(path, terrain_patch(np.random.default_rng(0)))
    config = pipeline_config_from({'voxel_size': 0.15, 'frontend.target_sensor': [0, 0, 1]})
    prepared = load_map(path, config)
    with pytest.raises(InvalidConfigError, match='target_sensor is for target clouds'):
        register_clouds(prepared.features.points, prepared, config=config)
    with pytest.raises(InvalidConfigError, match='target_sensor is for target clouds'):
        configs_from_parameters({'map.file': str(path), 'frontend.target_sensor': [0, 0, 1]})
    # The source's sensor applies against a map as against a cloud.
    pipe, _ = configs_from_parameters({'map.file': str(path), 'frontend.source_sensor': [0, 0, 1]})
    assert pipe.frontend.source_sensor == (0.0, 0.0, 1.0)
