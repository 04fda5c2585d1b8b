"""auto holds its candidates' images and estimates in float32 through the selection (half the bytes of a
frame's peak stage) and reads them into float64 arithmetic: the same choice as the float64 path, the image
within float32's rounding of it, the pixel mean's own bits where it is chosen."""

from __future__ import annotations

import warnings

import numpy as np
from mcrecon.methods import get_method
from mcrecon.methods.auto import method as auto_method
from mcrecon.methods.auto import passes
from mcrecon.methods.auto.blend import blended
from mcrecon.methods.auto.estimates import sure_filter_bank
from mcrecon.methods.auto.features import Candidate

from helpers import checker_wall_halves


def _select(hv, store, monkeypatch):
    monkeypatch.setattr(passes, "STORE", store)
    m = get_method("auto", candidates="box,gauss,nlm", feature_candidates="dnlm")
    run = m.start(hv.a.count.shape[1], hv.a.count.shape[0])
    stats = hv.merged()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        img, _ = m._select(run, stats, hv)
    return img, run.diagnostics["choice"], stats


def test_the_float32_store_chooses_as_the_float64_one_and_keeps_the_image_within_its_rounding(monkeypatch):
    hv = checker_wall_halves(24, 3)
    ref, ref_choice, _ = _select(hv, np.float64, monkeypatch)
    got, choice, stats = _select(hv, np.float32, monkeypatch)
    assert np.array_equal(choice, ref_choice)
    assert np.max(np.abs(got - ref) / np.maximum(np.abs(ref), 1e-12)) < 2 ** -23
    assert not np.array_equal(got, ref)   # the rounding is real: the test can tell the stores apart
    box = choice == 0
    assert box.any() and np.array_equal(got[box], stats.mean[box])   # the pixel mean's float64 bits


def test_candidates_are_stored_in_float32_from_their_creation():
    hv = checker_wall_halves(16, 4)
    m = get_method("auto", candidates="box,gauss,nlm", feature_candidates="dnlm")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cands, *_ = m._candidates(hv.merged(), hv, "drop")
    assert len(cands) > 5
    for c in cands:
        assert c.image.dtype == np.float32 and c.mse.dtype == np.float32, c.name
        assert c.image.flags.c_contiguous and c.mse.flags.c_contiguous


def test_the_bank_one_scale_at_a_time_is_the_whole_bank(monkeypatch):
    monkeypatch.setattr(passes, "STORE", np.float64)
    hv = checker_wall_halves(16, 5)
    st = hv.merged()
    y, v, count = st.mean, passes._c64(st.m2) / 8.0, st.count
    sig = np.array([0.7, 1.4, 2.8])
    whole = sure_filter_bank(y, v, count, sig)
    got = auto_method._bank(y, v, count, sig, box=True)
    assert [c.name for c in got] == ["box", "gauss0.7", "gauss1.4", "gauss2.8"]
    for c, x, s in zip(got, whole.values, whole.sure):
        assert np.array_equal(c.image, x) and np.array_equal(c.mse, s, equal_nan=True)


def test_a_value_beyond_float32s_range_keeps_its_array_in_float64():
    a = np.ones((4, 4, 3))
    assert passes._stored(a).dtype == np.float32
    a[1, 2, 0] = 1e300
    assert passes._stored(a).dtype == np.float64
    a[1, 2, 0] = np.inf   # infinite either way: float32 keeps it
    assert passes._stored(a).dtype == np.float32


def test_the_blend_of_stored_candidates_is_computed_in_float64():
    rng = np.random.default_rng(0)
    a64, b64 = rng.uniform(0, 1, (2, 8, 8, 3)), rng.uniform(0, 1, (2, 8, 8, 3))
    a = Candidate("gauss1", a64[0].astype(np.float32), a64[1].astype(np.float32))
    b = Candidate("nlm", b64[0].astype(np.float32), b64[1].astype(np.float32))
    w = 0.3
    m = blended(a, b, w)
    ai, bi = a.image.astype(np.float64), b.image.astype(np.float64)
    img = ai * w + (1 - w) * bi
    mse = a.mse.astype(np.float64) * w + (1 - w) * b.mse.astype(np.float64) - w * (1 - w) * (ai - bi) ** 2
    assert m.image.dtype == np.float32
    assert np.array_equal(m.image, img.astype(np.float32))
    assert np.allclose(m.mse, mse, rtol=1e-6, atol=0)


def test_the_kernels_read_stored_arrays_without_a_float64_copy_of_them(monkeypatch):
    seen = []
    real = np.ascontiguousarray

    def spy(a, dtype=None, **kw):
        out = real(a, dtype=dtype, **kw)
        if out is not a and getattr(a, "ndim", 0) == 3 and a.dtype == np.float32:
            seen.append(a.shape)
        return out

    arrays = [np.ones((6, 5, 3), np.float32) for _ in range(3)]
    monkeypatch.setattr(passes.np, "ascontiguousarray", spy)
    out = passes._means(arrays, np.full((6, 5, 3), 2.0))
    assert np.all(out == 0.5) and not seen


def test_the_floored_estimates_read_one_candidate_at_a_time_are_the_stacked_ones():
    from mcrecon.filters.masked import MaskedSmoothing
    from mcrecon.methods.auto.selection import _relative_choice

    rng = np.random.default_rng(1)
    y = rng.uniform(0.2, 0.8, (12, 14, 3))
    sd = rng.uniform(0.01, 0.05, y.shape)
    den = y * y + 0.01
    count = np.full(y.shape[:2], 8)
    count[3, 4] = 0
    cands = [Candidate(f"c{k}", (y + rng.normal(0, 0.05, y.shape)).astype(np.float32),
                       rng.uniform(0, 0.01, y.shape).astype(np.float32)) for k in range(4)]
    cands[2].mse[5, 6, 1] = np.nan
    smoothing = MaskedSmoothing(2.0)
    stack = passes._means([c.mse for c in cands], den)
    for k in range(len(cands)):
        smoothing([stack[k]], out=[stack[k]])
    want = passes._floor_and_choose(stack, [c.image for c in cands], y, sd, den, count > 0, 2.0)
    rel, choice = _relative_choice(cands, den, y, sd, count, smoothing, 2.0)
    assert np.array_equal(choice, want)
    for k in range(len(cands)):
        assert np.array_equal(rel[k], stack[k], equal_nan=True)


def test_the_selection_reads_one_candidates_estimates_at_a_time(monkeypatch):
    from mcrecon.methods.auto import selection

    shapes = []
    for mod in (selection, passes):
        real = mod._means

        def recording(arrays, *a, _real=real, **kw):
            out = _real(arrays, *a, **kw)
            shapes.append(out.shape)
            return out

        monkeypatch.setattr(mod, "_means", recording)
    monkeypatch.setattr(auto_method, "_mean_c", lambda a, den=None: passes._means([a], den)[0])
    hv = checker_wall_halves(16, 7)
    img, _, _ = _select(hv, np.float32, monkeypatch)
    assert np.isfinite(img).all()
    assert shapes and all(s[0] == 1 for s in shapes)   # no (K, H, W) stack of every candidate's map
