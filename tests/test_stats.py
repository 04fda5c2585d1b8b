"""PixelStats: Welford/Chan numerics, the merge property, subpixels, policies."""


import numpy as np
import pytest

from mcrecon import InputError, McreconWarning, PixelStats


def _samples(rng, n, w, h, c=3, dtype=np.float64):
    pos = rng.random((n, 2)) * [w, h]
    val = rng.normal(2.0, 0.5, (n, c)).astype(dtype)
    return pos, val


def _brute(pos, val, w, h):
    """Per-pixel count, mean, unbiased variance, min, max by grouping (two-pass, float64)."""
    pix = np.floor(pos[:, 1]).astype(int) * w + np.floor(pos[:, 0]).astype(int)
    c = val.shape[1]
    cnt = np.bincount(pix, minlength=w * h)
    mean = np.zeros((w * h, c))
    var = np.full((w * h, c), np.nan)
    mn = np.full((w * h, c), np.inf)
    mx = np.full((w * h, c), -np.inf)
    for p in np.unique(pix):
        v = val[pix == p].astype(np.float64)
        mean[p] = v.mean(0)
        if len(v) > 1:
            var[p] = v.var(0, ddof=1)
        mn[p], mx[p] = v.min(0), v.max(0)
    return cnt.reshape(h, w), mean.reshape(h, w, c), var.reshape(h, w, c), mn.reshape(h, w, c), mx.reshape(h, w, c)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_matches_brute_force(rng, dtype):
    w, h = 7, 5
    pos, val = _samples(rng, 900, w, h, dtype=dtype)
    s = PixelStats.from_samples(pos, val, width=w, height=h)
    cnt, mean, var, mn, mx = _brute(pos, val, w, h)
    np.testing.assert_array_equal(s.count, cnt)
    np.testing.assert_allclose(s.mean, mean, rtol=1e-12)
    np.testing.assert_allclose(s.sample_variance(), var, rtol=1e-10)
    np.testing.assert_array_equal(s.min, mn)
    np.testing.assert_array_equal(s.max, mx)
    np.testing.assert_allclose(s.mean_variance(), var / cnt[..., None], rtol=1e-10)


def test_merge_equals_all_at_once(rng):
    w, h = 11, 6
    pos, val = _samples(rng, 5000, w, h)
    whole = PixelStats.from_samples(pos, val, width=w, height=h, subpixels=4)
    parts = [PixelStats.from_samples(pos[a:b], val[a:b], width=w, height=h, subpixels=4)
             for a, b in [(0, 7), (7, 1000), (1000, 1001), (1001, 5000)]]
    merged = parts[0]
    for p in parts[1:]:
        merged.merge(p)
    np.testing.assert_array_equal(merged.count, whole.count)
    np.testing.assert_allclose(merged.mean, whole.mean, rtol=1e-12)
    np.testing.assert_allclose(merged.m2, whole.m2, rtol=1e-9)
    np.testing.assert_array_equal(merged.min, whole.min)
    np.testing.assert_array_equal(merged.max, whole.max)
    np.testing.assert_array_equal(merged.sub_count, whole.sub_count)
    np.testing.assert_allclose(merged.sub_sum, whole.sub_sum, rtol=1e-12)


def test_merge_with_empty_pixels(rng):
    a = PixelStats.from_samples(np.array([[0.5, 0.5]]), np.array([[1.0]]), width=2, height=1, channels="Y")
    b = PixelStats(2, 1, "Y")
    a.merge(b)
    assert a.count.tolist() == [[1, 0]] and a.mean[0, 0, 0] == 1.0 and a.mean[0, 1, 0] == 0.0


def _numpy_merge(a, b):
    """The reference Chan merge of ``a`` and ``b`` (count, mean, m2, min, max) in NumPy expressions."""
    na = a.count[..., None].astype(np.float64)
    nb = b.count[..., None].astype(np.float64)
    n = na + nb
    with np.errstate(invalid="ignore", divide="ignore"):
        delta = b.mean - a.mean
        wb = np.where(n > 0, nb / n, 0.0)
        m2 = a.m2 + (b.m2 + delta * delta * na * wb)
        mean = a.mean + delta * wb
    if a.min is None:  # a feature's statistics keep no range
        return a.count + b.count, mean, m2
    return a.count + b.count, mean, m2, np.minimum(a.min, b.min), np.maximum(a.max, b.max)


def test_compiled_merge_is_the_numpy_merge_bit_for_bit(rng):
    """merge (in place) and merged (new statistics, inputs unchanged) give bit for bit the NumPy
    expressions, features and subpixel sums included: empty pixels, values at 1e6 with a small spread,
    unknown ranges (NaN min/max of from_moments statistics), signed zeros (of two equal values the
    second is kept, as np.minimum/np.maximum do)."""
    w, h = 70, 150  # more rows than one task of the thread pool
    lay = {"albedo": 3, "depth": 1}

    def stats(seed, n):
        r = np.random.default_rng(seed)
        pos = r.random((n, 2)) * [w, h]
        val = 1e6 + r.normal(0, 1e-3, (n, 3))
        val[::7] = r.choice([0.0, -0.0], size=(val[::7].shape))
        feats = {"albedo": r.random((n, 3)).astype(np.float32), "depth": r.random(n)}
        return PixelStats.from_samples(pos, val, width=w, height=h, subpixels=2, features=feats)

    a, b = stats(1, 20000), stats(2, 3000)
    a.min[0, :3] = np.nan  # unknown ranges in some pixels of one side
    b.max[1, :2] = np.nan
    keep = {k: v.copy() for k, v in a.__dict__.items() if isinstance(v, np.ndarray)}
    pairs = [(a, b)] + [(a.features[k], b.features[k]) for k in lay]
    want = [_numpy_merge(x, y) for x, y in pairs]
    new = a.merged(b)
    for k, v in keep.items():
        np.testing.assert_array_equal(getattr(a, k), v)
    a.merge(b)
    for got in (new, a):
        for st, ref in zip([got] + [got.features[k] for k in lay], want):
            for f, r in zip(("count", "mean", "m2", "min", "max"), ref):
                g = getattr(st, f)
                assert g.dtype == r.dtype and np.array_equal(g, r, equal_nan=True), f
                assert np.array_equal(np.signbit(g), np.signbit(r)), f
        np.testing.assert_array_equal(got.sub_count, keep["sub_count"] + b.sub_count)
        np.testing.assert_array_equal(got.sub_sum, keep["sub_sum"] + b.sub_sum)
        assert got.n_samples == 23000 and got.dtype == np.float64


def test_welford_stable_at_large_offset(rng):
    # 1e6 + spread 1e-3: a naive sum of squares in float64 loses all digits
    # (1e12 * eps ~ 1e-4 > the 1e-6 variance), Welford keeps them.
    n = 4000
    x = 1e6 + rng.uniform(-1e-3, 1e-3, n)
    pos = np.column_stack([rng.random(n), rng.random(n)])
    s = PixelStats.from_samples(pos, x[:, None], width=1, height=1, channels="Y")
    exact = np.var(x - 1e6, ddof=1)
    assert s.sample_variance()[0, 0, 0] == pytest.approx(exact, rel=1e-6)
    naive = (np.sum(x * x) - n * np.mean(x) ** 2) / (n - 1)
    assert abs(naive - exact) / exact > 1e-3  # the alternative really fails here
    # merging rounds at the same offset stays stable too
    a = PixelStats.from_samples(pos[:1500], x[:1500, None], width=1, height=1, channels="Y")
    a.merge(PixelStats.from_samples(pos[1500:], x[1500:, None], width=1, height=1, channels="Y"))
    assert a.sample_variance()[0, 0, 0] == pytest.approx(exact, rel=1e-6)


def test_variance_policy_for_n_le_1():
    s = PixelStats.from_samples(np.array([[0.5, 0.5], [1.5, 0.5], [1.5, 0.7]]),
                                np.array([[1.0], [2.0], [4.0]]), width=3, height=1, channels="Y")
    v = s.sample_variance()
    assert np.isnan(v[0, 0, 0]) and np.isnan(v[0, 2, 0]) and v[0, 1, 0] == pytest.approx(2.0)
    assert s.sample_variance(undefined=0.0)[0, 0, 0] == 0.0


def test_subpixels(rng):
    w, h, s_ = 3, 2, 4
    pos, val = _samples(rng, 3000, w, h)
    s = PixelStats.from_samples(pos, val, width=w, height=h, subpixels=s_)
    sx = np.floor(pos[:, 0] * s_).astype(int)
    sy = np.floor(pos[:, 1] * s_).astype(int)
    cnt = np.zeros((h * s_, w * s_), int)
    np.add.at(cnt, (sy, sx), 1)
    np.testing.assert_array_equal(s.sub_count, cnt)
    # subpixel sums add up to the pixel sums
    pix_sum = s.sub_sum.reshape(h, s_, w, s_, 3).sum(axis=(1, 3))
    np.testing.assert_allclose(pix_sum, s.mean * s.count[..., None], rtol=1e-12)
    # empty subpixels take their pixel's mean
    s2 = PixelStats.from_samples(np.array([[0.1, 0.1]]), np.array([[3.0, 2.0, 1.0]]), width=1, height=1, subpixels=4)
    m = s2.subpixel_means()
    assert m.shape == (4, 4, 3) and np.all(m == np.array([3.0, 2.0, 1.0]))


def test_position_at_pixel_edge_in_float32_stays_inside():
    x = np.nextafter(np.float32(3.0), np.float32(0))
    s = PixelStats.from_samples(np.array([[x, 0.0]], np.float32), np.array([[1.0]]), width=3, height=1,
                                channels="Y", subpixels=4)
    assert s.count[0, 2] == 1 and s.sub_count[0, 11] == 1


@pytest.mark.parametrize("policy", ["drop", "zero", "raise"])
def test_nonfinite_policies(policy):
    pos = np.array([[0.5, 0.5], [0.5, 0.5], [0.5, 0.5]])
    val = np.array([[1.0], [np.nan], [np.inf]])
    s = PixelStats(1, 1, "Y")
    if policy == "raise":
        with pytest.raises(InputError, match="NaN or Inf"):
            s.add(pos, val, nonfinite="raise")
        assert s.n_samples == 0  # unchanged
        return
    with pytest.warns(McreconWarning, match="2 sample"):
        s.add(pos, val, nonfinite=policy)
    if policy == "drop":
        assert s.count[0, 0] == 1 and s.mean[0, 0, 0] == 1.0 and s.n_dropped == 2
    else:
        assert s.count[0, 0] == 3 and s.mean[0, 0, 0] == pytest.approx(1 / 3) and s.n_zeroed == 2
    assert np.isfinite(s.mean).all() and np.isfinite(s.m2).all()


def test_bad_inputs():
    s = PixelStats(4, 3)
    with pytest.raises(InputError, match="off the film"):
        s.add(np.array([[4.0, 0.0]]), np.ones((1, 3)))
    with pytest.raises(InputError, match="off the film"):
        s.add(np.array([[np.nan, 0.0]]), np.ones((1, 3)))
    with pytest.raises(InputError, match="expected \\(N, 3\\)"):
        s.add(np.zeros((2, 2)), np.ones((2, 4)))
    with pytest.raises(InputError, match="expected \\(N, 2\\)"):
        s.add(np.zeros((2, 3)), np.ones((2, 3)))
    with pytest.raises(InputError, match="unknown policy"):
        s.add(np.zeros((1, 2)), np.ones((1, 3)), nonfinite="keep")
    with pytest.raises(InputError, match="dtype"):
        s.add(np.zeros((1, 2)), np.array([["a", "b", "c"]]))
    with pytest.raises(InputError):
        PixelStats(0, 3)
    with pytest.raises(InputError, match="subpixels"):
        s.subpixel_means()
    assert s.n_samples == 0


def test_one_by_one_and_negative_values():
    s = PixelStats.from_samples(np.array([[0.2, 0.9], [0.7, 0.1]]), np.array([[-1.0], [1.0]]),
                                width=1, height=1, channels="Y")
    assert s.mean[0, 0, 0] == 0.0 and s.sample_variance()[0, 0, 0] == pytest.approx(2.0)


def test_quick_screen_is_exact_on_non_square_films():
    from mcrecon.core.samples import _quick_check

    ok = np.ones((1, 3), np.float32)
    assert _quick_check(np.array([[3.9, 0.5]], np.float32), ok, 4, 2) == (True, True)   # x above the short side
    assert _quick_check(np.array([[0.5, 3.9]], np.float32), ok, 2, 4) == (True, True)
    assert _quick_check(np.array([[1.0, 2.5]], np.float32), ok, 4, 2)[0] is False        # y off the film
    assert _quick_check(np.array([[1.0, 1.5]]), np.array([[1.0, np.inf, 1.0]]), 4, 2)[1] is False


# ------------------------------------------------------------------ the one fill-in policy
def test_fill_from_neighbours_policy():
    from mcrecon.core.fill import fill_from_neighbours
    v = np.zeros((4, 5, 2))
    defined = np.zeros((4, 5), bool)
    v[0, 0], defined[0, 0] = (4.0, 40.0), True
    v[1, 1], defined[1, 1] = (2.0, 20.0), True
    v[3, 4], defined[3, 4] = (9.0, 90.0), True
    out = fill_from_neighbours(v, defined)
    np.testing.assert_array_equal(out[defined], v[defined])            # defined pixels keep their value
    # mean of the defined pixels of the 3x3 neighbourhood inside the image: on the top edge
    # (0,1) sees (0,0) and (1,1) once each -> 3 (edge replication would count (0,0) twice: 3.33)
    np.testing.assert_allclose(out[0, 1], [3.0, 30.0])
    np.testing.assert_allclose(out[1, 0], [3.0, 30.0])
    np.testing.assert_allclose(out[2, 2], [2.0, 20.0])   # only (1,1) is defined around (2,2)
    # no defined neighbour: the channel's image-wide mean of defined pixels
    np.testing.assert_allclose(out[3, 0], v[defined].mean(axis=0))
    # fill only where asked
    only = np.zeros((4, 5), bool)
    only[3, 0] = True
    kept = fill_from_neighbours(v, defined, only)
    assert kept[0, 1, 0] == 0.0 and kept[3, 0, 0] == pytest.approx(5.0)
    # nothing defined: the fallback, a callable evaluated only then
    calls = []
    fb = fill_from_neighbours(v, np.zeros((4, 5), bool), fallback=lambda: calls.append(1) or 7.0)
    assert (fb == 7.0).all() and calls == [1]
    fill_from_neighbours(v, defined, fallback=lambda: calls.append(2))
    assert calls == [1]


def test_gem_and_awr_use_the_same_fill_in():
    """Pixels with one sample get the same neighbourhood estimate in both methods (sample variance)."""
    from mcrecon.methods.awr.reconstruction import functional_variance
    from mcrecon.core.fill import mean_variance_policy
    rng = np.random.default_rng(3)
    counts = rng.integers(1, 4, (9, 11))
    from mcrecon.core.requests import jittered_positions
    pos = jittered_positions(counts, rng)
    st = PixelStats.from_samples(pos, rng.random((len(pos), 3)), width=11, height=9)
    gem_var = mean_variance_policy(st) * st.count[..., None]
    awr_var = functional_variance(st, "sample")
    one = st.count == 1
    np.testing.assert_allclose(gem_var[one], awr_var[one], rtol=1e-12)


def test_range_estimators_refuse_statistics_without_a_range():
    from mcrecon.errors import InputError
    from mcrecon.methods.awr.reconstruction import functional_variance
    st = PixelStats.from_moments(np.ones((4, 4, 3)), np.full((4, 4, 3), 0.1), 8)
    for est in ("range", "contrast"):
        with pytest.raises(InputError, match="variance='sample'"):
            functional_variance(st, est)
    assert np.isfinite(functional_variance(st, "sample")).all()


def test_fill_from_neighbours_stays_in_the_range_of_the_defined_values():
    """The 3x3 average of defined values lies within their range; uniform_filter's running sums left it by
    rounding (-1.1e-14 from non-negative inputs with seed 15 below; a negative variance made an adaptive
    awr run at initial_spp=1 refuse its own statistics)."""
    from mcrecon.core.fill import fill_from_neighbours

    for seed in (15, 16, 17):
        rng = np.random.default_rng(seed)
        v = rng.random((20, 16, 3)) ** 6 * 10 ** rng.uniform(-3, 3, (20, 16, 3))
        d = rng.random((20, 16)) < 0.4
        out = fill_from_neighbours(v, d)
        assert out.min() >= v[d].min() and out.max() <= v[d].max()
        np.testing.assert_array_equal(out[d], v[d])


def test_crop_is_the_statistics_of_the_window_and_a_row_view_shares_memory():
    from mcrecon import InputError

    rng = np.random.default_rng(7)
    pos = rng.random((4000, 2)) * [10, 8]
    val = rng.random((4000, 3))
    st = PixelStats.from_samples(pos, val, width=10, height=8, subpixels=2)
    c = st.crop(2, 6, 3, 9)
    inside = (pos[:, 0] >= 3) & (pos[:, 0] < 9) & (pos[:, 1] >= 2) & (pos[:, 1] < 6)
    direct = PixelStats.from_samples(pos[inside] - [3, 2], val[inside], width=6, height=4, subpixels=2)
    assert (c.width, c.height) == (6, 4)
    np.testing.assert_array_equal(c.count, direct.count)
    np.testing.assert_allclose(c.mean, direct.mean, rtol=1e-12)
    np.testing.assert_allclose(c.m2, direct.m2, rtol=1e-9, atol=1e-12)
    np.testing.assert_array_equal(c.sub_count, direct.sub_count)
    assert not np.shares_memory(c.mean, st.mean)
    rows = st.crop(1, 3, view=True)
    assert np.shares_memory(rows.mean, st.mean) and rows.height == 2
    arrays, fields = st.to_arrays()
    back = PixelStats.from_arrays(arrays, fields)
    assert back.mean is st.mean and back.width == 10
    with pytest.raises(InputError, match="window"):
        st.crop(0, 9)
    with pytest.raises(InputError, match="whole rows"):
        st.crop(0, 2, 1, 5, view=True)


def test_features_keep_no_range_and_their_colour_keeps_its_own():
    """A feature's statistics hold count, mean and m2 only (no method reads a feature's extremes: 16 bytes a
    pixel and component saved in every copy, halves and merge included); the colour keeps its range, and
    crops and merges of statistics with features work on what is kept."""
    rng = np.random.default_rng(3)
    pos = rng.random((500, 2)) * [6, 5]
    val = rng.random((500, 3))
    feats = {"albedo": rng.random((500, 3)), "depth": rng.random(500)}
    st = PixelStats.from_samples(pos, val, width=6, height=5, features=feats)
    whole = PixelStats.from_samples(pos, val, width=6, height=5)
    np.testing.assert_array_equal(st.min, whole.min)
    np.testing.assert_array_equal(st.max, whole.max)
    for name in ("albedo", "depth"):
        f = st.features[name]
        assert f.min is None and f.max is None and not f.has_range
        ref = PixelStats.from_samples(pos, feats[name].reshape(500, -1), width=6, height=5,
                                      channels=f.channels)
        for field in ("count", "mean", "m2"):
            np.testing.assert_array_equal(getattr(f, field), getattr(ref, field))
    crop = st.crop(1, 4, 2, 5)
    assert crop.features["albedo"].min is None and crop.min.shape == (3, 3, 3)
    both = st.merged(st)
    assert both.features["depth"].min is None
    np.testing.assert_array_equal(both.features["depth"].count, 2 * st.count)
