"""Per-sample features end to end: accumulated per pixel like the colour.

Every check is against a brute-force computation over the same samples
(per-pixel mean and unbiased variance of each feature component), or an
invariant of the half-buffer split (the halves' merge equals the whole).
"""

import numpy as np
import pytest

import mcrecon
from mcrecon.core.features import check_features, feature_components, feature_layout
from mcrecon.core.halves import split_halves
from mcrecon.core.samples import SampleSet
from mcrecon.core.stats import PixelStats
from mcrecon.errors import InputError, McreconWarning

from helpers import feature_samples, jittered_renderer

W, H = 7, 5


def _samples(n=3000, seed=3):
    return feature_samples(n, seed, width=W, height=H)


def _brute(pos, f):
    """Per-pixel mean, unbiased variance and count of ``f`` ((n, k)) by explicit loops over pixels."""
    f = f.reshape(len(f), -1)
    px = np.floor(pos).astype(int)
    mean = np.zeros((H, W, f.shape[1]))
    var = np.full((H, W, f.shape[1]), np.nan)
    cnt = np.zeros((H, W), int)
    for y in range(H):
        for x in range(W):
            sel = (px[:, 0] == x) & (px[:, 1] == y)
            cnt[y, x] = sel.sum()
            if sel.any():
                mean[y, x] = f[sel].mean(axis=0)
            if sel.sum() > 1:
                var[y, x] = f[sel].var(axis=0, ddof=1)
    return mean, var, cnt


def test_feature_statistics_match_brute_force_means_and_variances():
    pos, val, feats = _samples()
    st = PixelStats.from_samples(pos, val, width=W, height=H, features=feats)
    assert st.feature_names == ("albedo", "normal", "depth")
    assert st.features["albedo"].channels == ("R", "G", "B")
    assert st.features["depth"].channels == ("Z",)
    for name, f in feats.items():
        mean, var, cnt = _brute(pos, f)
        fst = st.features[name]
        np.testing.assert_array_equal(fst.count, cnt)
        np.testing.assert_allclose(fst.mean, mean, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(fst.sample_variance(), var, rtol=1e-9)
    # the colour is what it is without features
    plain = PixelStats.from_samples(pos, val, width=W, height=H)
    np.testing.assert_array_equal(st.mean, plain.mean)
    np.testing.assert_array_equal(st.m2, plain.m2)


def test_batches_merge_and_copies_keep_features():
    pos, val, feats = _samples()
    whole = PixelStats.from_samples(pos, val, width=W, height=H, features=feats)
    a = PixelStats(W, H, features={"albedo": 3, "normal": 3, "depth": 1})
    b = PixelStats(W, H, features=["albedo", "normal", "depth"])
    cut = 1234
    a.add(pos[:cut], val[:cut], features={k: v[:cut] for k, v in feats.items()})
    b.add(pos[cut:], val[cut:], features={k: v[cut:] for k, v in feats.items()})
    a.merge(b)  # Chan
    for name in feats:
        np.testing.assert_allclose(a.features[name].mean, whole.features[name].mean, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(a.features[name].m2, whole.features[name].m2, rtol=1e-9, atol=1e-12)
    c = whole.copy()
    c.features["depth"].mean[0, 0] += 1
    assert c.features["depth"].mean[0, 0] != whole.features["depth"].mean[0, 0]
    crop = whole.crop(1, 4, 2, 6)
    np.testing.assert_array_equal(crop.features["normal"].mean, whole.features["normal"].mean[1:4, 2:6])
    arrays, fields = whole.to_arrays()
    back = PixelStats.from_arrays(arrays, fields)
    np.testing.assert_array_equal(back.features["albedo"].m2, whole.features["albedo"].m2)
    assert whole.without_features().feature_names == ()


def test_merging_statistics_with_different_features_is_refused():
    pos, val, feats = _samples(200)
    a = PixelStats.from_samples(pos, val, width=W, height=H, features=feats)
    b = PixelStats.from_samples(pos, val, width=W, height=H, features={"depth": feats["depth"]})
    with pytest.raises(InputError, match="features must match"):
        a.merge(b)


def test_halves_split_features_with_the_colour_and_merge_to_the_whole():
    pos, val, feats = _samples(4000)
    ss = SampleSet(pos, val, width=W, height=H, features=feats)
    h = split_halves(ss, features="all")
    whole = PixelStats.from_source(ss, features="all")
    for name in feats:
        fa, fb = h.a.features[name], h.b.features[name]
        # each half's feature counts are its colour counts: one label per sample
        np.testing.assert_array_equal(fa.count, h.a.count)
        np.testing.assert_array_equal(fb.count, h.b.count)
        merged = fa.copy().merge(fb)
        np.testing.assert_allclose(merged.mean, whole.features[name].mean, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(merged.m2, whole.features[name].m2, rtol=1e-9, atol=1e-12)
    # the halves hold the same samples' features as their colour: brute force on each half, from the
    # labels of the reference split (split_labels, stream order), in the one-pass and the parallel path
    from mcrecon.core.halves import split_labels

    lab = split_labels(pos, W, H, np.zeros(W * H, np.int64))
    for half, st in ((0, h.a), (1, h.b)):
        sel = lab == half
        for name, f in feats.items():
            mean, var, cnt = _brute(pos[sel], f[sel])
            np.testing.assert_array_equal(st.features[name].count, cnt)
            np.testing.assert_allclose(st.features[name].mean, mean, rtol=1e-12, atol=1e-12)
            np.testing.assert_allclose(st.features[name].sample_variance(), var, rtol=1e-9)


def test_nonfinite_features_are_zeroed_counted_and_warned_and_dropped_samples_lose_their_features():
    pos, val, feats = _samples(500)
    feats["depth"] = feats["depth"].copy()
    feats["depth"][:7] = np.inf  # rays that left the scene
    val = val.copy()
    val[10] = np.nan  # the colour's drop policy drops this sample, features included
    with pytest.warns(McreconWarning, match="7 sample"), pytest.warns(McreconWarning, match=r"1 sample\(s\).*dropped"):
        st = PixelStats.from_samples(pos, val, width=W, height=H, features=feats, nonfinite="drop")
    assert st.n_feature_zeroed == 7 and st.n_dropped == 1
    keep = np.isfinite(val).all(axis=1)
    d = np.where(np.isfinite(feats["depth"]), feats["depth"], 0.0)[keep]
    mean, _, cnt = _brute(pos[keep], d)
    np.testing.assert_array_equal(st.features["depth"].count, cnt)
    np.testing.assert_allclose(st.features["depth"].mean, mean, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("bad, match", [
    ({"albedo": np.zeros((9, 3))}, r"features/albedo.*shape"),
    ({"albedo": np.array(["a"] * 500)}, r"features/albedo.*dtype"),
])
def test_malformed_features_are_refused_naming_the_field(bad, match):
    pos, val, _ = _samples(500)
    with pytest.raises(InputError, match=match):
        SampleSet(pos, val, width=W, height=H, features=bad)


def test_statistics_that_keep_a_feature_refuse_a_batch_without_it():
    pos, val, feats = _samples(100)
    st = PixelStats(W, H, features=["albedo", "depth"])
    with pytest.raises(InputError, match=r"features/depth.*missing"):
        st.add(pos, val, features={"albedo": feats["albedo"]})
    assert st.n_samples == 0  # unchanged when it raises


def test_feature_layout_and_components():
    assert feature_layout(["albedo", "depth"]) == {"albedo": 3, "depth": 1}
    assert feature_components("normal", 3) == ("X", "Y", "Z")
    assert feature_components("uv", 2) == ("0", "1")
    with pytest.raises(InputError, match="must be one of"):
        feature_layout(["visibility"])
    out, n = check_features({"d": np.array([1, 2], np.int32)}, 2)
    assert out["d"].dtype == np.float64 and out["d"].shape == (2, 1) and n == 0


def test_from_moments_carries_feature_images():
    rng = np.random.default_rng(0)
    mean = rng.uniform(size=(H, W, 3))
    var = rng.uniform(size=(H, W, 3))
    count = np.full((H, W), 8)
    alb = rng.uniform(size=(H, W, 3))
    depth = rng.uniform(size=(H, W))
    st = PixelStats.from_moments(mean, var, count, features={"albedo": (alb, None), "depth": (depth, 0.5 * depth)})
    np.testing.assert_array_equal(st.features["albedo"].mean, alb)
    np.testing.assert_allclose(st.features["albedo"].sample_variance(), 0.0)
    np.testing.assert_allclose(st.features["depth"].sample_variance()[..., 0], 0.5 * depth)
    np.testing.assert_array_equal(st.features["depth"].count, count)
    with pytest.raises(InputError, match="features/depth"):
        PixelStats.from_moments(mean, var, count, features={"depth": (np.zeros((2, 2)), None)})


def test_features_round_trip_through_a_sample_log(tmp_path):
    pos, val, feats = _samples(2500)
    path = tmp_path / "f.h5"
    mcrecon.write_log(path, pos, val, width=W, height=H, features=feats)
    log = mcrecon.read_log(path)
    assert set(log.feature_names) == set(feats)
    st = PixelStats.from_log(log, features="all", chunk_size=700)  # several chunks: Chan between them
    plain = PixelStats.from_log(log)
    with pytest.raises(InputError, match="no feature 'visibility'"):
        PixelStats.from_log(log, features=["visibility"])
    assert plain.feature_names == ()
    for name, f in feats.items():
        mean, var, _ = _brute(pos, f)
        np.testing.assert_allclose(st.features[name].mean, mean, rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(st.features[name].sample_variance(), var, rtol=1e-4, atol=1e-6)


def test_methods_that_read_no_features_give_identical_images_with_and_without_them(tmp_path):
    pos, val, feats = _samples(3000)
    with_f = SampleSet(pos, val, width=W, height=H, features=feats)
    without = SampleSet(pos, val, width=W, height=H)
    for name in ("box", "awr"):
        a = mcrecon.reconstruct(with_f, method=name)
        b = mcrecon.reconstruct(without, method=name)
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_the_parallel_split_keeps_features_with_their_samples():
    """Past 65536 samples the split runs in parallel parts: the features still follow their samples."""
    pos, val, feats = _samples(70_000, seed=9)
    h = split_halves(SampleSet(pos, val, width=W, height=H, features=feats), features="all")
    from mcrecon.core.halves import split_labels

    lab = split_labels(pos, W, H, np.zeros(W * H, np.int64))
    for half, st in ((0, h.a), (1, h.b)):
        mean, _, cnt = _brute(pos[lab == half], feats["albedo"][lab == half])
        np.testing.assert_array_equal(st.features["albedo"].count, cnt)
        np.testing.assert_allclose(st.features["albedo"].mean, mean, rtol=1e-12, atol=1e-12)


def test_samples_with_a_non_finite_entry_in_any_feature_are_counted_once():
    pos, val, feats = _samples(300)
    feats["depth"] = feats["depth"].copy()
    feats["depth"][:3] = np.inf
    feats["normal"] = feats["normal"].copy()
    feats["normal"][3:6] = np.nan
    feats["normal"][0] = np.nan  # a sample bad in two features counts once
    with pytest.warns(McreconWarning):
        ss = SampleSet(pos, val, width=W, height=H, features=feats)
    assert ss.n_feature_zeroed == 6


@pytest.mark.parametrize("bad, match", [
    ({"a": 1.0}, r"features/a: shape \(\)"),
    (["albedo"], r"features: got list, expected a mapping"),
    ({"e": np.zeros((300, 0))}, r"features/e: shape \(300, 0\): no component"),
])
def test_from_samples_refuses_malformed_features_with_one_clear_error(bad, match):
    pos, val, _ = _samples(300)
    with pytest.raises(InputError, match=match):
        PixelStats.from_samples(pos, val, width=W, height=H, features=bad)


def test_a_log_with_a_mask_and_a_matrix_feature_opens_and_methods_use_what_they_can(tmp_path):
    """bool features are 0/1; a per-sample (2, 2) matrix cannot be accumulated per pixel: methods whose
    features are optional leave it out instead of refusing the log."""
    pos, val, feats = _samples(3000)
    feats["mask"] = np.arange(3000) % 2 == 0
    feats["mat"] = np.ones((3000, 2, 2))
    path = tmp_path / "odd.h5"
    mcrecon.write_log(path, pos, val, width=W, height=H, features=feats)
    log = mcrecon.read_log(path)
    st = PixelStats.from_log(log, features=["mask"])
    mean, _, _ = _brute(pos, feats["mask"].astype(np.float64))
    np.testing.assert_allclose(st.features["mask"].mean, mean, rtol=1e-6, atol=1e-7)
    for m in ("box", "auto", "nfor"):
        img = mcrecon.reconstruct(log, method=m)
        assert np.isfinite(img).all()


def test_half_buffer_pairs_with_the_same_features_in_another_order_are_accepted():
    pos, val, feats = _samples(4000)
    h = split_halves(SampleSet(pos, val, width=W, height=H, features=feats), features="all")
    rev = {name: feats[name] for name in reversed(list(feats))}
    h2 = split_halves(SampleSet(pos, val, width=W, height=H, features=rev), features="all")
    assert h.b.feature_names != h2.b.feature_names
    a = mcrecon.reconstruct((h.a, h.b), method="auto")
    b = mcrecon.reconstruct((h.a, h2.b), method="auto")
    np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-14)
    with pytest.raises(InputError, match="halves differ in features"):
        mcrecon.reconstruct((h.a, h.b.without_features()), method="auto")


# ------------------------------------------------- features as files and C writers give them
def _wall_log(tmp_path, name, convert=None, extra=None, size=16, spp=4):
    """A checker_wall log whose features pass through ``convert`` (dtype, byte order, sentinels)."""
    from mcrecon.io import write_log
    from mcrecon.renderers import scenes as S

    b = S.render_uniform("checker_wall", width=size, height=size, spp=spp, seed=2, features=True)
    feats = {k: (convert(k, np.asarray(v)) if convert else np.asarray(v)) for k, v in b.features.items()}
    feats.update(extra or {})
    return write_log(tmp_path / name, b.positions, b.values, width=size, height=size, features=feats)


def test_check_features_gives_native_floats_and_zeroes_sentinels():
    n = 6
    big = (np.arange(n * 3, dtype=">f8") / 32).reshape(n, 3)  # an albedo: reflectances in [0, 1]
    half = np.arange(n, dtype=np.float16)
    sentinel = np.array([1.0, 2.0, np.finfo(np.float64).max, -1e200, 3.0, 1e29])
    out, n_zeroed = check_features({"albedo": big, "depth": half, "z": sentinel}, n)
    assert out["albedo"].dtype == np.dtype("<f8") and out["albedo"].dtype.isnative
    np.testing.assert_array_equal(out["albedo"], big.astype("<f8"))
    assert out["depth"].dtype == np.float32
    np.testing.assert_array_equal(out["z"][:, 0], [1.0, 2.0, 0.0, 0.0, 3.0, 1e29])  # beyond 1e30: as Inf
    flt = check_features({"d": np.array([1.0, np.finfo(np.float32).max], np.float32)}, 2)
    assert flt[1] == 1 and flt[0]["d"][1, 0] == 0  # a float32 writer's FLT_MAX sentinel too
    assert n_zeroed == 2
    with pytest.raises(InputError, match=r"features/depth.*4096 components, at most 64"):
        check_features({"depth": np.zeros((4096, 4096), np.float32)}, 4096)


def test_logs_with_odd_feature_dtypes_reconstruct_as_their_values(tmp_path):
    # float16 (documented as accepted) and big-endian features crashed splat, nfor and auto in numba
    # with a traceback; an (N, 2, 2) extra made splat count "11 components, earlier rounds 8"
    plain = _wall_log(tmp_path, "plain.h5", convert=lambda k, v: v.astype(np.float16).astype(np.float32))
    half = _wall_log(tmp_path, "half.h5", convert=lambda k, v: v.astype(np.float16))
    swapped = _wall_log(tmp_path, "be.h5", convert=lambda k, v: v.astype(np.float16).astype(">f4"),
                        extra={"mat": np.zeros((16 * 16 * 4, 2, 2), np.float32)})
    for method in ("splat", "nfor", "auto"):
        want = mcrecon.reconstruct(str(plain), method=method)
        for path in (half, swapped):
            np.testing.assert_array_equal(mcrecon.reconstruct(str(path), method=method), want, err_msg=method)


def test_huge_feature_sentinels_do_not_make_nan_images(tmp_path):
    # a DBL_MAX "no hit" depth on 30 % of the samples: nfor wrote an EXR of NaN with exit status 0
    rng = np.random.default_rng(0)

    def sentinel(k, v):
        v = v.astype(np.float64)
        if k == "depth":
            v = v.copy()
            v[rng.random(v.shape[0]) < 0.3] = np.finfo(np.float64).max
        return v

    path = _wall_log(tmp_path, "sent.h5", convert=sentinel)
    for method in ("nfor", "auto", "splat"):
        with pytest.warns(McreconWarning, match=r"beyond \+-1e\+30 feature values set to 0"):
            img = mcrecon.reconstruct(str(path), method=method)
        assert np.isfinite(img).all(), method


def test_log_feature_groups_and_shapes_are_checked_on_opening(tmp_path):
    import h5py

    from mcrecon.io import read_log

    path = _wall_log(tmp_path, "ds.h5", size=4, spp=1)
    with h5py.File(path, "r+") as f:
        del f["features"]
        f["features"] = np.zeros(16)
    with pytest.raises(InputError, match=r"/features: a dataset, expected a group"):
        read_log(path)
    # a feature of more components than any method regresses on: the log stays readable (box needs no
    # feature); a method that reads features leaves it out, or refuses it in one line, never hangs
    wide = _wall_log(tmp_path, "wide.h5", size=4, spp=1, extra={"z": np.zeros((16, 100), np.float32)})
    assert read_log(wide).feature_shapes["z"] == (100,)
    assert np.isfinite(mcrecon.reconstruct(str(wide), method="box")).all()
    for method in ("nfor", "auto", "splat"):
        try:
            img = mcrecon.reconstruct(str(wide), method=method)
        except InputError as exc:
            assert "features/z" in str(exc) and "at most 64" in str(exc), method
        else:
            assert np.isfinite(img).all(), method


def test_from_moments_refuses_text_images_naming_the_field():
    text = np.full((2, 2), "a")
    with pytest.raises(InputError, match=r"features/albedo mean: dtype <U1, expected a numeric image"):
        PixelStats.from_moments(np.ones((2, 2, 3)), np.zeros((2, 2, 3)), 4, features={"albedo": (text, None)})
    with pytest.raises(InputError, match=r"from_moments: variance: dtype"):
        PixelStats.from_moments(np.ones((2, 2)), text, 4)
    with pytest.raises(InputError, match=r"from_moments: mean: not an array: nested lists of unequal"):
        PixelStats.from_moments([[1.0, 2.0], [3.0]], np.zeros((2, 2)), 4)


def test_a_reply_sentinel_is_zeroed_once_and_stored_as_zero(tmp_path):
    # a DBL_MAX depth in a renderer's reply is warned about once per run (not per round, nor twice a
    # round: validation, then commit), and the log stores 0, as the warning says
    import warnings

    from mcrecon.adaptive.run import adapt
    from mcrecon.core.requests import SampleBatch
    from mcrecon.io import read_log

    def shade(pos, rng, req):
        depth = np.ones(pos.shape[0])
        depth[::3] = np.finfo(np.float64).max
        return SampleBatch(pos, np.ones((pos.shape[0], 3)), {"depth": depth})

    r = jittered_renderer(shade, width=4, height=4, stream=lambda req: req.round_index)
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        res = adapt(r, "box", spp=4, log=str(tmp_path / "s.h5"), progress=False, pipeline=False)
    zeroed = [w for w in rec if "feature values set to 0" in str(w.message)]
    assert len(res.rounds) > 1 and len(zeroed) == 1
    depth = read_log(tmp_path / "s.h5").read_feature("depth")
    assert depth.max() == 1.0 and (depth == 0).sum() > 0
