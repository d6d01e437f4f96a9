"""cores/segmentation/stats.py: numpy's percentile and median, to the last bit."""
import numpy as np
import pytest

from cores.segmentation import stats


def _same(x, y) -> bool:
    x, y = np.asarray(x), np.asarray(y)
    return x.dtype == y.dtype and x.shape == y.shape and bool(np.array_equal(x, y))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_percentile_and_median_match_numpy(dtype):
    rng = np.random.default_rng(1)
    for n in [1, 2, 3, 4, 5, 7, 10, 33, 100, 101, 999, 1500, 3001]:
        a = (rng.standard_normal(n) * 10 ** rng.uniform(-2, 2)).astype(dtype)
        if n > 4:
            a[: n // 3] = a[0]  # ties
        for q in [2, 5, 50, 95, 98, 100, 0, 2.5, 97.5]:
            assert _same(stats.percentile(a, q), np.percentile(a, q)), (n, q)
        for qs in [[2, 98], [5, 95], [10, 90], [0, 100], [50]]:
            assert _same(stats.percentile(a, qs), np.percentile(a, qs)), (n, qs)
            pts = rng.standard_normal((n, 3)).astype(dtype)
            assert _same(stats.percentile(pts, qs), np.percentile(pts, qs, axis=0)), (n, qs)
        assert _same(stats.median(a), np.median(a)), n
        before = a.copy()
        stats.median(a)
        stats.percentile(a, [2, 98])
        assert np.array_equal(a, before)  # the input is left as it was


def test_label_order_is_numpys_stable_argsort():
    from cores.segmentation.layers import _label_order

    rng = np.random.default_rng(2)
    for top in [1, 7, 300, 1 << 16, 1 << 20]:  # 16-bit keys and wider ones
        lab = rng.integers(0, top, 5000).astype(np.int32)
        lab[100:900] = lab[100]  # long runs of one label, as objects give
        assert np.array_equal(_label_order(lab), np.argsort(lab, kind="stable")), top
    assert _label_order(np.zeros(0, np.int32)).size == 0


def test_mean0_is_numpys_mean_down_axis_0():
    rng = np.random.default_rng(3)
    for n in [1, 2, 3, 17, 256, 1000, 4097, 30000]:
        for k in [2, 3]:
            a = rng.standard_normal((n, k)) * 10 ** rng.uniform(-3, 3) + rng.uniform(-50, 50)
            assert _same(stats.mean0(a), a.mean(0)), (n, k)
            b = a[::2]  # a strided view, as a subsample is
            assert _same(stats.mean0(b), b.mean(0)), (n, k)
