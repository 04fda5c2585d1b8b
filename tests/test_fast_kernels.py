"""The shared patch-distance kernel of NL-means and the regression against brute force, and its precision.

``offset_distances`` serves every NL-means filter and the regression's
weights, so a faster rewrite of it must keep these: the patch mean over the
pairs inside the image for every patch radius (the unrolled radii 0..3 and
the general loop), zero pairs where the offset leaves the film, a NaN
distance confined to the patches that contain it, and column sums that run
down a long band (one row in, one out) equal to the patch sums taken afresh,
beside clamped outliers and after a NaN has left the patch.
"""

import numpy as np
import pytest

from mcrecon.filters.nlmeans import DISTANCE_CLAMP, NLM_EPS, offset_distances


def _distances(guide, var, dy, dx, i0, i1, f, k=0.7):
    """The kernel's patch means and the pixel distances ``pd`` they were summed from."""
    c, h, w = guide.shape
    pd = np.zeros((c, i1 - i0 + 2 * f, w + 2 * f), np.float32)
    vs, ic = (np.zeros(w + 2 * f) for _ in range(2))
    out = np.full((c, i1 - i0, w), np.float32(-7.0))
    offset_distances(guide, var, dy, dx, i0, i1, f, np.float32(k * k), np.float32(NLM_EPS),
                     np.float32(DISTANCE_CLAMP), pd, vs, ic, out)
    return out, pd


def _brute(guide, var, dy, dx, i0, i1, f, k):
    """Patch mean, in float64, of the float32 pixel distances of the pairs (s, s + o) inside the image;
    NaN-free where no pair exists (those entries are not compared)."""
    c, h, w = guide.shape
    out = np.full((c, i1 - i0, w), np.nan)
    for i in range(i0, i1):
        for j in range(w):
            if not (0 <= i + dy < h and 0 <= j + dx < w):
                continue
            ds = []
            for si in range(i - f, i + f + 1):
                for sj in range(j - f, j + f + 1):
                    if 0 <= si < h and 0 <= sj < w and 0 <= si + dy < h and 0 <= sj + dx < w:
                        # the kernel's pixel distance is float32 arithmetic
                        d = ((guide[:, si, sj] - guide[:, si + dy, sj + dx]) ** 2 - (var[:, si, sj] + np.minimum(
                            var[:, si, sj], var[:, si + dy, sj + dx]))) / (np.float32(NLM_EPS) + np.float32(k * k) * (
                                var[:, si, sj] + var[:, si + dy, sj + dx]))
                        ds.append(np.minimum(d.astype(np.float64), DISTANCE_CLAMP))
            out[:, i - i0, j] = np.mean(ds, axis=0)
    return out


def _data(seed, c=3, h=13, w=17):
    rng = np.random.default_rng(seed)
    guide = (rng.gamma(2.0, 1.0, size=(c, h, w)) * np.where(rng.uniform(size=(1, h, w)) < 0.3, 9.0, 1.0))
    var = rng.uniform(0.01, 0.5, size=(c, h, w))
    return guide.astype(np.float32), var.astype(np.float32)


@pytest.mark.parametrize("f", [0, 1, 2, 3, 4])
@pytest.mark.parametrize("dy, dx", [(0, 0), (2, -3), (-4, 5), (6, 1)])
@pytest.mark.parametrize("i0, i1", [(0, 5), (4, 13)])
def test_patch_distances_match_brute_force(f, dy, dx, i0, i1):
    """rtol 1e-5 of the patch's sum of |d|: the pixel distances are float32, and so are their patch sums
    (numba keeps ``float(x)`` of a float32 in float32), each rounding ~6e-8 of the running sum."""
    guide, var = _data(100 + f + 10 * dy + dx)
    got, _ = _distances(guide, var, dy, dx, i0, i1, f, 0.7)
    want = _brute(guide, var, dy, dx, i0, i1, f, 0.7)
    inside = np.isfinite(want)
    assert inside.any()
    scale = np.abs(want[inside]).max()
    np.testing.assert_allclose(got[inside], want[inside], rtol=1e-5, atol=1e-6 * scale)


def test_an_offset_wider_than_the_film_compares_no_pair():
    guide, var = _data(3, w=5)
    got, _ = _distances(guide, var, 1, 6, 0, 13, 1, 1.0)
    assert (got == np.float32(-7.0)).all()  # nothing written: the callers skip those pairs


def test_a_nan_distance_stays_in_the_patches_that_contain_it():
    guide, var = _data(4)
    var[1, 6, 8] = np.inf  # inf / inf: a NaN pixel distance at (6, 8) and at the pairs reaching it
    f = 1
    got, _ = _distances(guide, var, 0, 2, 0, 13, f, 0.7)
    bad = np.argwhere(np.isnan(got[1]))
    assert len(bad) and np.isfinite(got[[0, 2]]).all()
    # a NaN only where the patch covers (6, 8) or (6, 8) - o
    for i, j in bad:
        assert abs(i - 6) <= f and (abs(j - 8) <= f or abs(j + 2 - 8) <= f)


# ------------------------------------------------------------------ the running column sums down a band
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


def _band_data(seed, c=2, h=70, w=23):
    rng = np.random.default_rng(seed)
    guide = rng.gamma(2.0, 1.0, size=(c, h, w))
    guide[:, 10:14] *= 1e6            # distances clamped at 1e4 ...
    var = rng.uniform(0.01, 0.5, size=(c, h, w))
    var[:, 30:40] *= 1e-9             # ... and rows of near-noise-free pixels further down
    return guide.astype(np.float32), var.astype(np.float32)


@pytest.mark.parametrize("f", [1, 3, 5])
@pytest.mark.parametrize("dy, dx", [(0, 0), (3, -2), (-5, 4)])
def test_running_column_sums_equal_fresh_patch_sums_down_a_long_band(f, dy, dx):
    guide, var = _band_data(100 + f + 7 * dy + dx)
    got, pd = _distances(guide, var, dy, dx, 0, 70, f)
    want = _fresh(pd, guide, dy, dx, 0, 70, f)
    ok = np.isfinite(want)
    assert ok.sum() > 1000
    # one float32 rounding of the patch mean (the sums themselves are float64: no residue of the clamped rows)
    np.testing.assert_allclose(got[ok], want[ok], rtol=2e-7, atol=1e-12 * DISTANCE_CLAMP)


def test_a_nan_that_leaves_the_patch_leaves_the_running_sum():
    guide, var = _band_data(5)
    guide[1, 20, 7] = np.nan
    f = 2
    got, pd = _distances(guide, var, 0, 0, 0, 70, f)
    bad = np.argwhere(np.isnan(got[1]))
    assert len(bad) and np.isfinite(got[0]).all()
    assert all(abs(i - 20) <= f and abs(j - 7) <= f for i, j in bad)
    want = _fresh(pd, guide, 0, 0, 0, 70, f)
    ok = np.isfinite(want)
    np.testing.assert_allclose(got[ok], want[ok], rtol=2e-7, atol=1e-12 * DISTANCE_CLAMP)
