"""
The front end's compiled functions (frontend/compiled/): compiled once, from their declarations.

What they compute is tested against Open3D, a k-d tree and brute force in test_fpfh.py and
test_descriptor_index.py; here, that each is compiled at import from its declared signature,
that other argument types raise a TypeError instead of compiling, and that the front end
hands them only the declared types, whatever the input's dtype and layout.
"""

from __future__ import annotations

from cgags_ros.config.frontend import FrontEndConfig
from cgags_ros.frontend import compiled
from cgags_ros.frontend.compiled import descriptor_index, fpfh, neighbours
from cgags_ros.frontend.descriptor_index import DescriptorIndex
from cgags_ros.frontend.features import extract_features
from cgags_ros.frontend.matching import match_features
from cgags_ros.frontend.neighbours import NeighbourGrid
import numpy as np
import pytest


def _compiled_functions():
    """Every compiled function of the front end with a declared signature (not the inlined)."""
    return [getattr(m, name) for m in (descriptor_index, fpfh, neighbours) for name in dir(m)
            if hasattr(getattr(m, name), 'signatures')
            and getattr(m, name).targetoptions.get('inline') != 'always']


def _read_only(a):
    a = a.copy()
    a.flags.writeable = False
    return a


def _box_cloud(seed, n=6000):
    """Points on the faces of a 1 m box (metres): corners and edges give FPFH structure."""
    rng = np.random.default_rng(seed)
    points = rng.uniform(-0.5, 0.5, (n, 3))
    face = rng.integers(0, 3, n)
    points[np.arange(n), face] = np.where(rng.random(n) < 0.5, -0.5, 0.5)
    return points


def test_compiled_at_import_from_the_declared_signatures():
    functions = _compiled_functions()
    assert {compiled.radius_neighbours, compiled.spfh_pass, compiled.fpfh_pass, compiled.search,
            compiled.nearest_is, descriptor_index._nearest} <= set(functions)
    for fn in functions:
        assert len(fn.signatures) == 1, fn  # compiled (or loaded from the cache) at import
    rng = np.random.default_rng(0)
    a, b = rng.random((5, 33)), rng.random((5, 33))
    out = np.empty(5)
    compiled.squared_pair_distances(a, b, out)
    np.testing.assert_allclose(out, ((a - b) ** 2).sum(axis=1), rtol=1e-15)
    for other in ((a.astype(np.float32), b, out),  # another dtype
                  (np.asfortranarray(a), b, out),  # another layout
                  (a, b, _read_only(out))):  # read-only output
        with pytest.raises(TypeError):
            compiled.squared_pair_distances(*other)
    assert all(len(fn.signatures) == 1 for fn in functions)


def test_a_named_tuple_with_a_wrong_field_raises():
    """The named tuples are typed field by field: one wrong array is a TypeError too."""
    points = _box_cloud(1, 500)
    grid = NeighbourGrid.build(points, 0.2)
    nearest = np.empty(len(points))
    lists = grid.neighbours(0, len(points), 30, nearest)
    compiled.radius_neighbours(grid.arrays, 0, len(points), lists, nearest)
    wrong_lists = lists._replace(nbr=lists.nbr.astype(np.int64))
    wrong_grid = grid.arrays._replace(lower=grid.arrays.lower.astype(np.float32))
    for args in ((grid.arrays, 0, len(points), wrong_lists, nearest),
                 (wrong_grid, 0, len(points), lists, nearest)):
        with pytest.raises(TypeError):
            compiled.radius_neighbours(*args)
    index = DescriptorIndex(np.random.default_rng(2).random((300, 33)))
    queries = np.random.default_rng(3).random((4, 33))
    found, dist = np.empty((4, 1), np.int64), np.empty((4, 1))
    compiled.search(index.arrays, queries, 1, 0, found, dist)
    wrong_index = index.arrays._replace(points=np.asfortranarray(index.arrays.points))
    with pytest.raises(TypeError):
        compiled.search(wrong_index, queries, 1, 0, found, dist)
    assert all(len(fn.signatures) == 1 for fn in _compiled_functions())


def test_the_front_end_calls_only_the_declared_signatures():
    """Any dtype and layout, read-only descriptors too: the front end converts them first."""
    functions = _compiled_functions()
    before = {fn: list(fn.signatures) for fn in functions}
    cfg = FrontEndConfig()
    source = np.asfortranarray(_box_cloud(4)).astype(np.float32)
    target = _box_cloud(5)
    features = [extract_features(c, 0.05, cfg, workers=2) for c in (source, target)]
    descriptors = [_read_only(f.descriptors) for f in features]
    matches = match_features(*descriptors, FrontEndConfig(), workers=2, ratio=0.9)
    assert len(matches) > 0
    index = DescriptorIndex(descriptors[1])
    queries = _read_only(np.asfortranarray(descriptors[0][:50]))
    nearest = index.query(queries, 2)[0]
    rows = _read_only(nearest[:, 0].astype(np.int32))
    assert index.is_nearest(queries, rows).all()
    assert {fn: list(fn.signatures) for fn in functions} == before
