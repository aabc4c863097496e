"""The exact descriptor index against plain numpy brute force (frontend/descriptor_index.py)."""

from cgags_ros.config.frontend import FrontEndConfig
from cgags_ros.frontend.descriptor_index import Cells, DescriptorIndex
from cgags_ros.frontend.matching import informative_index, match_features
import numpy as np
import pytest
from scipy.spatial.distance import cdist


def _brute(query, reference, k):
    """Nearest k by exact distance, ties to the lower row (stable sort)."""
    d = np.sqrt(((query[:, None, :] - reference[None, :, :]) ** 2).sum(axis=2))
    return np.argsort(d, axis=1, kind='stable')[:, :k]


def _nearest(query, reference, k, workers=1):
    """Return the index's answer, built over ``reference`` for this one query set."""
    return DescriptorIndex(reference, workers).query(query, k, workers)[0]


def _clustered(rng, n, dim=33, clusters=12):
    """FPFH-like rows: clustered, non-negative, with exact duplicates among them."""
    centres = rng.random((clusters, dim)) * 50
    rows = centres[rng.integers(0, clusters, n)] + rng.normal(0, 2.0, (n, dim))
    rows = np.abs(rows)
    rows[rng.integers(0, n, n // 10)] = rows[0]  # many identical descriptors
    return rows


@pytest.mark.parametrize('seed', range(4))
@pytest.mark.parametrize('k', [1, 2])
def test_index_equals_brute_force(seed, k):
    rng = np.random.default_rng(seed)
    ref = _clustered(rng, 1500)
    query = np.vstack([_clustered(rng, 700), ref[:50], ref[:50] + 1e-13])
    index = DescriptorIndex(ref, workers=2, seed=seed)
    assert len(index.centres) > 1  # the pruning bounds are exercised
    got, dist = index.query(query, k, workers=2)
    np.testing.assert_array_equal(got, _brute(query, ref, k))
    np.testing.assert_allclose(dist, np.linalg.norm(query[:, None, :] - ref[got], axis=2),
                               rtol=1e-12, atol=1e-12)


def test_an_index_on_cells_fitted_to_more_rows_gives_the_same_answers():
    rng = np.random.default_rng(7)
    ref = _clustered(rng, 3000)
    cells = Cells.fit(ref, 500, workers=2)
    assert len(cells.centres) < DescriptorIndex(ref).centres.shape[0]  # sized for a part
    query = np.vstack([_clustered(rng, 500), ref[:20]])
    for keep in (rng.random(len(ref)) < 0.2, np.arange(len(ref)) >= 2990):
        part = ref[keep]
        index = DescriptorIndex.on_cells(cells, keep, ref, np.arange(len(ref)))
        assert index.size == len(part)
        for k in (1, 2):
            got = index.query(query, k, 2)[0]
            np.testing.assert_array_equal(got, _brute(query, part, k))
            np.testing.assert_array_equal(got, DescriptorIndex(part).query(query, k)[0])
        rows = rng.integers(0, len(part), len(query))
        np.testing.assert_array_equal(index.is_nearest(query, rows),
                                      _brute(query, part, 1)[:, 0] == rows)
    # the descriptors read through a map of rows: the cells' rows are rows 5, 6, ... of these
    shifted = np.vstack([np.zeros((5, ref.shape[1])), ref])
    keep = rng.random(len(ref)) < 0.3
    np.testing.assert_array_equal(
        DescriptorIndex.on_cells(cells, keep, shifted, np.arange(len(ref)) + 5).query(query)[0],
        _brute(query, ref[keep], 1))
    with pytest.raises(ValueError):
        DescriptorIndex.on_cells(cells, np.zeros(len(ref), dtype=bool), ref, np.arange(len(ref)))


def test_index_result_independent_of_seed_and_workers():
    rng = np.random.default_rng(7)
    ref, query = _clustered(rng, 3000, dim=8), _clustered(rng, 2000, dim=8)
    a = DescriptorIndex(ref, workers=1, seed=0).query(query, 2, workers=1)[0]
    b = DescriptorIndex(ref, workers=3, seed=99).query(query, 2, workers=3)[0]
    np.testing.assert_array_equal(a, b)
    # cells and principal directions borrowed from another cloud's index: same answer
    c = DescriptorIndex(ref, like=DescriptorIndex(query)).query(query, 2)[0]
    np.testing.assert_array_equal(a, c)


def test_a_search_of_the_nearest_cells_answers_the_nearest_of_their_members():
    rng = np.random.default_rng(5)
    ref, query = _clustered(rng, 3000), _clustered(rng, 400)
    index = DescriptorIndex(ref, workers=2)
    arrays = index.arrays
    exact = index.query(query, 2, 2)[0]
    np.testing.assert_array_equal(index.query(query, 2, 2, cells=len(index.centres))[0], exact)
    for cells in (1, 3):
        for k in (1, 2):
            got, dist = index.query(query, k, 2, cells)
            for i, q in enumerate(query):
                # the cells nearest the query's, as many as asked and enough to hold k rows
                near = np.argsort(((arrays.centres - q) ** 2).sum(axis=1), kind='stable')
                sizes = np.diff(arrays.starts)[near]
                visited = near[:max(cells, int(np.searchsorted(np.cumsum(sizes), k)) + 1)]
                members = np.sort(np.concatenate(
                    [arrays.order[arrays.starts[j]:arrays.starts[j + 1]] for j in visited]))
                np.testing.assert_array_equal(got[i], members[_brute(q[None], ref[members], k)[0]])
            np.testing.assert_allclose(dist, np.linalg.norm(query[:, None] - ref[got], axis=2))
            assert (dist >= index.query(query, k)[1] - 1e-12).all()
        assert (index.query(query, 1, 2, cells)[0] != exact[:, :1]).any()  # approximate
    with pytest.raises(ValueError):
        index.query(query, 1, cells=-1)


def test_index_of_identical_rows_and_tiny_references():
    same = np.ones((300, 5))
    np.testing.assert_array_equal(DescriptorIndex(same).query(same, 2)[0][:, :2],
                                  np.tile([0, 1], (300, 1)))
    one = np.arange(4.0)[None, :]
    assert DescriptorIndex(one).query(np.zeros((3, 4)), 1)[0].ravel().tolist() == [0, 0, 0]
    with pytest.raises(ValueError):
        DescriptorIndex(one).query(np.zeros((1, 4)), 2)
    with pytest.raises(ValueError):
        DescriptorIndex(np.zeros((0, 4)))


def test_match_features_with_a_kept_index_and_a_wrong_one():
    rng = np.random.default_rng(3)
    src, dst = _clustered(rng, 800), _clustered(rng, 900)
    dst[:20] = 0.0  # uninformative rows are left out of the index
    cfg = FrontEndConfig()
    kept = informative_index(dst)
    fresh = match_features(src, dst, cfg)
    again = match_features(src, dst, cfg, target_index=kept)
    for field in ('source_index', 'target_index', 'distance'):
        np.testing.assert_array_equal(getattr(fresh, field), getattr(again, field))
    assert informative_index(np.zeros((5, 33))) is None
    with pytest.raises(ValueError, match='not an index of this target'):
        match_features(src, dst, cfg, target_index=informative_index(src))


def test_index_with_nearly_coincident_cells_stays_exact():
    """Two tight clusters 1e-9 apart: k-means centres nearly coincide; the plane bound holds."""
    rng = np.random.default_rng(11)
    base = rng.random(33) * 100
    ref = np.vstack([base + rng.normal(0, 1e-9, (400, 33)),
                     base + 1e-9 + rng.normal(0, 1e-9, (400, 33)),
                     rng.random((400, 33)) * 100])
    query = np.vstack([base + rng.normal(0, 2e-9, (300, 33)), rng.random((100, 33)) * 100])
    got = DescriptorIndex(ref).query(query, 2)[0]
    np.testing.assert_array_equal(got, _brute(query, ref, 2))


def test_first_and_second_neighbour_equal_scipy():
    rng = np.random.default_rng(4)
    q, r = rng.normal(size=(1000, 33)), rng.normal(size=(3000, 33))
    D = cdist(q, r)
    np.testing.assert_array_equal(_nearest(q, r, 2), np.argsort(D, axis=1)[:, :2])
    np.testing.assert_array_equal(_nearest(r, q, 1)[:, 0], np.argmin(D, axis=0))
    # rows split over threads (as register_clouds does): the same answer
    np.testing.assert_array_equal(_nearest(q, r, 2, workers=3), np.argsort(D, axis=1)[:, :2])
    np.testing.assert_array_equal(_nearest(r, q, 1, workers=2)[:, 0], np.argmin(D, axis=0))


def test_near_ties_are_ranked_by_the_exact_distance():
    """
    Check that the index ranks near-ties by the exact distance.

    Squared norms ~1e5 like FPFH: near-duplicate and exactly duplicated reference rows
    (which also share index cells and sit on their borders) must still be ranked by the
    exact distance, ties to the lower index.
    """
    rng = np.random.default_rng(7)
    base = rng.uniform(0.0, 200.0, size=(400, 33))
    r = np.vstack([base,
                   base[:100] + rng.normal(scale=1e-4, size=(100, 33)),  # near-duplicates
                   base[100:150]])                                       # exact duplicates
    q = np.vstack([base[:300] + rng.normal(scale=1e-5, size=(300, 33)),
                   rng.uniform(0.0, 200.0, size=(300, 33))])
    D = cdist(q, r)
    np.testing.assert_array_equal(_nearest(q, r, 1)[:, 0], np.argmin(D, axis=1))
    np.testing.assert_array_equal(_nearest(q, r, 1, workers=2)[:, 0], np.argmin(D, axis=1))
    # all descriptors identical (every row ties with every row): lowest index, bounded memory
    same = np.full((3000, 33), 60.0)
    np.testing.assert_array_equal(_nearest(same, same, 1)[:, 0], np.zeros(3000))


def test_is_nearest_equals_brute_force_with_ties():
    """is_nearest(q, r) is query(q, 1) == r, for nearest rows, beaten ones and exact ties."""
    rng = np.random.default_rng(5)
    ref = _clustered(rng, 1200)
    query = np.vstack([_clustered(rng, 400), ref[:40], ref[:40] + 1e-13])
    index = DescriptorIndex(ref, seed=1)
    nearest = _brute(query, ref, 1)[:, 0]
    rows = np.where(rng.random(len(query)) < 0.5, nearest, rng.integers(0, len(ref), len(query)))
    tied = np.flatnonzero((ref == ref[0]).all(axis=1))  # identical rows: only the lowest wins
    rows[400:410] = tied[-1]
    query[400:410] = ref[0]
    expected = rows == _brute(query, ref, 1)[:, 0]
    assert expected.any() and not expected.all()
    for workers in (1, 2):
        np.testing.assert_array_equal(index.is_nearest(query, rows, workers), expected)
    with pytest.raises(ValueError):
        index.is_nearest(query[:2], np.array([0, len(ref)]))


@pytest.mark.parametrize('scale', [1e-6, 1e6])
def test_float32_screen_stays_exact_at_any_magnitude(scale):
    """The float32 screen's slack scales with the rows' norms: tiny or huge rows, near-ties."""
    rng = np.random.default_rng(9)
    ref = _clustered(rng, 1200) * scale
    near = ref[:200] * (1.0 + rng.normal(0, 1e-7, (200, ref.shape[1])))  # ~float32 spacing
    query = np.vstack([_clustered(rng, 300) * scale, near, ref[200:260]])
    got = DescriptorIndex(ref, seed=2).query(query, 2)[0]
    np.testing.assert_array_equal(got, _brute(query, ref, 2))
