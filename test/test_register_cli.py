"""cgags-register: happy path on a real pair, and every error path exits cleanly."""

import json

from bench.datasets.gt_pairs import find_pair
from cgags_ros.geometry import rotation_error_deg, translation_error
from cgags_ros.io.clouds import read_cloud
from cgags_ros.tools.register_cli import EXIT_ERROR, main
import numpy as np
import pytest


@pytest.fixture(scope='module')
def bunny_pair(data_dir):
    return find_pair(data_dir / 'objects/stanford_bunny_scans/gt_pairs.txt',
                     'bun045.ply', 'bun000.ply')


def test_text_output_plot_and_aligned_cloud(bunny_pair, tmp_path, capsys):
    src, dst, T = bunny_pair
    aligned, png = tmp_path / 'aligned.ply', tmp_path / 'overlay.png'
    rc = main([str(src), str(dst), '--voxel-size', '0.003', '--output', str(aligned),
               '--plot', str(png)])
    out = capsys.readouterr().out
    assert rc == 0
    for text in ('transform (source -> target', 'valid: yes', 'inliers:', 'time [s]:'):
        assert text in out
    expected = read_cloud(src) @ T[:3, :3].T + T[:3, 3]
    assert np.median(np.linalg.norm(read_cloud(aligned) - expected, axis=1)) < 0.002
    assert png.read_bytes()[:4] == b'\x89PNG'


def test_json_with_config_set_seed_and_no_refine(bunny_pair, tmp_path, capsys):
    src, dst, T = bunny_pair
    cfg = tmp_path / 'params.yaml'
    cfg.write_text('register_node:\n  ros__parameters:\n    voxel_size: 0.003\n'
                   '    frontend:\n      max_correspondences: 2000\n')
    rc = main([str(src), str(dst), '--config', str(cfg), '--set', 'core.max_iterations=20000',
               '--no-refine', '--seed', '3', '--json'])
    data = json.loads(capsys.readouterr().out)
    assert rc == 0 and data['valid'] and data['refined'] is False
    assert data['voxel_size'] == 0.003 and data['num_correspondences'] <= 2000
    E = np.asarray(data['transform'])
    assert rotation_error_deg(E, T) < 5 and translation_error(E, T) < 0.01
    cov = np.asarray(data['covariance'])  # the pose covariance, ROS order
    assert cov.shape == (6, 6) and np.allclose(cov, cov.T) and np.all(np.diag(cov) > 0)
    assert np.all(np.diag(cov) < 1e-3)  # millimetre-scale object, many inliers


@pytest.mark.parametrize('args, message', [
    (['{missing}', '{dst}'], 'no such file'),
    (['{bad}', '{dst}'], 'not a PLY file'),
    (['{src}', '{dst}', '--voxel-size', 'abc'], 'invalid float value'),
    (['{src}', '{dst}', '--voxel-size', '-1'], 'below its minimum'),
    (['{src}', '{dst}', '--set', 'core.nope=1'], 'unknown configuration key'),
    (['{src}', '{dst}', '--set', 'novalue'], 'KEY=VALUE'),
    (['{src}', '{dst}', '--set', 'refine.method=fast'], 'not one of'),
    (['{src}', '{dst}', '--config', '{missing}'], 'cannot read config file'),
])
def test_errors_are_one_line_without_traceback(bunny_pair, tmp_path, capsys, args, message):
    src, dst, _ = bunny_pair
    bad = tmp_path / 'bad.ply'
    bad.write_text('not a cloud\n')
    names = {'src': src, 'dst': dst, 'bad': bad, 'missing': tmp_path / 'missing.ply'}
    argv = [a.format(**names) for a in args]
    if 'abc' in args:  # argparse's own type check exits (with our one-line message)
        with pytest.raises(SystemExit) as exc:
            main(argv)
        assert exc.value.code == EXIT_ERROR
    else:
        assert main(argv) == EXIT_ERROR
    err = capsys.readouterr().err
    assert message in err and 'Traceback' not in err
    assert len(err.strip().splitlines()) == 1 and err.startswith('cgags-register: error:')


def test_help_documents_every_option(capsys):
    with pytest.raises(SystemExit) as exc:
        main(['--help'])
    out = capsys.readouterr().out
    assert exc.value.code == 0
    for option in ('--voxel-size', '--config', '--set', '--no-refine', '--json', '--output',
                   '--plot', '--seed', 'Exit status'):
        assert option in out
