from cgags_ros.registration.preference import PreferenceLists
import numpy as np


def test_lists_keep_the_b_smallest_residuals():
    rng = np.random.default_rng(0)
    pref = PreferenceLists(n=50, b=5)
    all_res = rng.random((40, 50)).astype(np.float32)
    for chunk in np.array_split(all_res, 7):
        pref.update(chunk)
    expected = np.sort(np.argsort(all_res, axis=0)[:5].T, axis=1)
    assert np.array_equal(np.sort(pref.ids, axis=1), expected)
    assert np.allclose(np.sort(pref.residuals, axis=1), np.sort(all_res, axis=0)[:5].T)


def test_lists_fill_free_slots_then_rank():
    rng = np.random.default_rng(1)
    pref = PreferenceLists(n=50, b=20)
    all_res = rng.random((60, 50)).astype(np.float32)
    seen = 0
    for size in (3, 5, 12, 7, 30, 3):
        pref.update(all_res[seen:seen + size])
        seen += size
        k = min(seen, 20)
        expected = np.sort(np.argsort(all_res[:seen], axis=0, kind='stable')[:k].T, axis=1)
        got = np.sort(pref.ids, axis=1)[:, 20 - k:]  # unfilled slots hold -1
        assert np.array_equal(got, expected)
        assert np.isinf(pref.residuals).sum() == 50 * (20 - k)


def test_intersection_kernel():
    pref = PreferenceLists(n=3, b=4)
    lists = [[0, 1, 2, 3], [2, 3, 4, 5], [6, 7, 8, 9]]
    residuals = np.ones((10, 3), dtype=np.float32)  # hypothesis h's residual at each m
    for m, hypotheses in enumerate(lists):
        residuals[hypotheses, m] = 0.0
    pref.update(residuals)
    assert np.array_equal(np.sort(pref.ids, axis=1), lists)
    K = pref.kernel(np.arange(3))
    assert np.allclose(K, [[0, 0.5, 0], [0.5, 0, 0], [0, 0, 0]])
    assert np.allclose(pref.kernel(np.array([0, 1])), [[0, 0.5], [0.5, 0]])


def test_lists_stay_sorted_and_quality_is_their_median():
    rng = np.random.default_rng(2)
    for b in (1, 4, 5, 20):
        pref = PreferenceLists(n=40, b=b)
        for size in (1, 2, 9, 30, 4):
            pref.update(rng.random((size, 40)).astype(np.float32))
            assert np.array_equal(pref.residuals, np.sort(pref.residuals, axis=1))  # inf last
            assert np.array_equal(pref.quality(), np.median(pref.residuals, axis=1))


def test_intersection_kernel_equals_the_incidence_product():
    rng = np.random.default_rng(3)
    pref = PreferenceLists(n=120, b=6)
    for size in (4, 3, 25):  # the first lists stay partly empty (-1 slots)
        pref.update(rng.random((size, 120)).astype(np.float32))
    members = rng.choice(120, 50, replace=False)
    incidence = np.zeros((50, pref.num_hypotheses), dtype=np.float32)
    rows, slots = np.nonzero(pref.ids[members] >= 0)
    incidence[rows, pref.ids[members][rows, slots]] = 1.0
    expected = incidence @ incidence.T / np.float32(6)
    np.fill_diagonal(expected, 0.0)
    assert np.array_equal(pref.kernel(members), expected)
