"""
A map prepared once: ``cgags-map prepare``, the cache memory-mapped, shared, and kept fresh.

The map is the bundled LiDAR fixture's target scan (test/fixtures/small_gicp) written as a
PLY of doubles; the query its source scan, whose ground truth the fixture gives.
"""

from __future__ import annotations

import json
import multiprocessing
from pathlib import Path

from cgags_ros.config import pipeline_config_from
from cgags_ros.geometry import rotation_error_deg, translation_error
from cgags_ros.io import map_cache
from cgags_ros.io.clouds import write_cloud
from cgags_ros.pipeline import register_clouds
from cgags_ros.pipeline.map import load_map
from cgags_ros.tools import map_cli
import numpy as np
import pytest

FIXTURE = Path(__file__).resolve().parent / 'fixtures' / 'small_gicp'
VOXEL = 0.3


@pytest.fixture()
def lidar_map(tmp_path):
    path = tmp_path / 'map.ply'
    write_cloud(path, np.load(FIXTURE / 'target.npy').astype(np.float64))
    return path, tmp_path / 'cache', pipeline_config_from({'voxel_size': VOXEL})


def test_a_prepared_map_loads_memory_mapped_and_registers_as_computed(lidar_map, capsys):
    path, cache, cfg = lidar_map
    assert map_cli.main(['prepare', str(path), '--voxel-size', str(VOXEL),
                         '--cache-dir', str(cache)]) == 0
    assert 'stored in' in capsys.readouterr().out
    prepared = load_map(path, cfg, cache)
    assert prepared.cache == 'hit'
    f = prepared.features
    for array in (f.points, f.normals, f.descriptors, f.descriptor_index().arrays.points):
        assert isinstance(array.base, np.memmap)  # a view of the file, not a copy
    computed = load_map(path, cfg)  # no cache: computed in this process
    assert computed.cache == 'off'
    assert np.array_equal(computed.features.descriptors, f.descriptors)
    source = np.load(FIXTURE / 'source.npy').astype(np.float64)
    truth = np.loadtxt(FIXTURE / 'T_target_source.txt')
    a, b = register_clouds(source, prepared, config=cfg), register_clouds(source, computed,
                                                                          config=cfg)
    # The same answer (to the last bits, which the refinement's threaded sums may change).
    assert a.valid and a.num_inliers == b.num_inliers
    assert np.allclose(a.transform, b.transform, rtol=0, atol=1e-12)
    assert rotation_error_deg(a.transform, truth) < 1 and translation_error(a.transform,
                                                                            truth) < 0.1


def test_a_changed_map_file_is_rebuilt_and_its_old_entry_said_stale(lidar_map, capsys):
    path, cache, cfg = lidar_map
    first = load_map(path, cfg, cache)
    assert first.cache == 'miss'
    assert map_cli.main(['inspect', str(path), '--cache-dir', str(cache), '--json']) == 0
    [entry] = json.loads(capsys.readouterr().out)['entries']
    assert not entry['stale'] and entry['points'] == len(first.features.points)
    assert entry['voxel_size'] == VOXEL
    write_cloud(path, np.load(FIXTURE / 'target.npy')[::2].astype(np.float64))
    second = load_map(path, cfg, cache)
    assert second.cache == 'miss' and second.cache_path != first.cache_path
    assert len(second.features.points) < len(first.features.points)
    assert map_cli.main(['inspect', str(path), '--cache-dir', str(cache)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 2 and 'STALE' in lines[0] and 'fresh' in lines[1]


def test_a_damaged_entry_is_recomputed_not_trusted(lidar_map):
    path, cache, cfg = lidar_map
    entry = Path(load_map(path, cfg, cache).cache_path)
    (entry / 'descriptors.npy').write_bytes(b'not an array')
    again = load_map(path, cfg, cache)
    assert again.cache == 'miss' and again.features.descriptors.shape[1] == 33


def _touch_and_share(path, cache, voxel, ready, done, out, finished):
    """Load the map, touch every page of its arrays, report the mappings' Rss and Shared."""
    cfg = pipeline_config_from({'voxel_size': voxel})
    prepared = load_map(path, cfg, cache)
    index = prepared.features.descriptor_index()
    arrays = [prepared.features.points, prepared.features.descriptors, index.arrays.points]
    float(sum(np.asarray(a, dtype=np.float64).sum() for a in arrays))
    ready.set()
    done.wait(60)
    entry = prepared.cache_path
    rss = shared = 0
    current = False
    for line in Path('/proc/self/smaps').read_text().splitlines():
        if not line[:1].isupper() or ':' not in line.split()[0]:  # a mapping's header
            current = entry in line
        elif current and line.startswith('Rss:'):
            rss += int(line.split()[1])
        elif current and line.startswith('Shared_Clean:'):
            shared += int(line.split()[1])
    out.put((rss, shared))
    finished.wait(60)  # alive until every process has read its mappings


@pytest.mark.subprocess
def test_two_processes_that_load_one_map_share_one_copy(lidar_map):
    path, cache, cfg = lidar_map
    load_map(path, cfg, cache)
    ctx = multiprocessing.get_context('spawn')
    ready, done, out, finished = [ctx.Event(), ctx.Event()], ctx.Event(), ctx.Queue(), ctx.Event()
    procs = [ctx.Process(target=_touch_and_share,
                         args=(path, cache, VOXEL, r, done, out, finished)) for r in ready]
    for p in procs:
        p.start()
    try:
        assert all(r.wait(120) for r in ready)
        done.set()
        reports = [out.get(timeout=60) for _ in procs]
    finally:
        finished.set()
        for p in procs:
            p.join(30)
    [(entry, _)] = map_cache.entries(cache)
    size_kb = sum(f.stat().st_size for f in entry.iterdir()) / 1024
    for rss, shared in reports:
        assert rss > 0.5 * size_kb, (rss, size_kb)  # the arrays are mapped from the cache
        assert shared >= 0.9 * rss, reports  # and each of their pages is the other process's too
