"""The patch distances' column sums run down a band (one row in, one out): over many rows, with clamped
outliers beside tiny distances and with NaN, they equal the patch sums taken afresh."""

import numpy as np
import pytest

from mcrecon.filters.nlmeans import DISTANCE_CLAMP, NLM_EPS, offset_distances


def _run(guide, var, dy, dx, i0, i1, f, k=0.7):
    c, h, w = guide.shape
    pd = np.zeros((c, i1 - i0 + 2 * f, w + 2 * f), np.float32)
    vs, hs, ic = (np.zeros(w + 2 * f) for _ in range(3))
    out = np.full((c, i1 - i0, w), np.float32(-7.0))
    offset_distances(guide, var, dy, dx, i0, i1, f, np.float32(k * k), np.float32(NLM_EPS),
                     np.float32(DISTANCE_CLAMP), pd, vs, hs, ic, out)
    return out, pd


def _fresh(pd, guide, dy, dx, i0, i1, f):
    """The patch means from the kernel's own pixel distances ``pd``, each patch summed directly in float64."""
    c, h, w = guide.shape
    out = np.full((c, i1 - i0, w), np.nan)
    p = pd.astype(np.float64)
    for rr in range(i1 - i0):
        i = i0 + rr
        nr = min(i + f + 1, h, h - dy) - max(i - f, 0, -dy)
        for j in range(max(0, -dx), min(w, w - dx)):
            nc = min(j + f + 1, min(w, w - dx)) - max(j - f, max(0, -dx))
            if nr > 0:
                out[:, rr, j] = p[:, rr:rr + 2 * f + 1, j:j + 2 * f + 1].sum(axis=(1, 2)) / (nr * nc)
    return out


def _data(seed, c=2, h=70, w=23):
    rng = np.random.default_rng(seed)
    guide = rng.gamma(2.0, 1.0, size=(c, h, w))
    guide[:, 10:14] *= 1e6            # distances clamped at 1e4 ...
    var = rng.uniform(0.01, 0.5, size=(c, h, w))
    var[:, 30:40] *= 1e-9             # ... and rows of near-noise-free pixels further down
    return guide.astype(np.float32), var.astype(np.float32)


@pytest.mark.parametrize("f", [1, 3, 5])
@pytest.mark.parametrize("dy, dx", [(0, 0), (3, -2), (-5, 4)])
def test_running_column_sums_equal_fresh_patch_sums_down_a_long_band(f, dy, dx):
    guide, var = _data(100 + f + 7 * dy + dx)
    got, pd = _run(guide, var, dy, dx, 0, 70, f)
    want = _fresh(pd, guide, dy, dx, 0, 70, f)
    ok = np.isfinite(want)
    assert ok.sum() > 1000
    # one float32 rounding of the patch mean (the sums themselves are float64: no residue of the clamped rows)
    np.testing.assert_allclose(got[ok], want[ok], rtol=2e-7, atol=1e-12 * DISTANCE_CLAMP)


def test_a_nan_that_leaves_the_patch_leaves_the_running_sum():
    guide, var = _data(5)
    guide[1, 20, 7] = np.nan
    f = 2
    got, pd = _run(guide, var, 0, 0, 0, 70, f)
    bad = np.argwhere(np.isnan(got[1]))
    assert len(bad) and np.isfinite(got[0]).all()
    assert all(abs(i - 20) <= f and abs(j - 7) <= f for i, j in bad)
    want = _fresh(pd, guide, 0, 0, 0, 70, f)
    ok = np.isfinite(want)
    np.testing.assert_allclose(got[ok], want[ok], rtol=2e-7, atol=1e-12 * DISTANCE_CLAMP)
