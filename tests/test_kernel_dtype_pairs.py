"""The kernels that read positions with values (or with features) take the pair in one dtype
(:func:`mcrecon.core.samples.one_float_dtype`): numba compiles each of them for two signatures (float32,
float64), not for every mix of the two, and the widened float32 side is exact, so the sums are those of the
pair as given."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import mcrecon
from mcrecon.core import merge
from mcrecon.core.samples import SampleSet, dispatcher, one_float_dtype
from mcrecon.core.stats import PixelStats
from mcrecon.methods.splat import consistent, gated, outliers


def test_one_float_dtype_keeps_a_shared_dtype_and_widens_a_mix_exactly():
    a32 = np.array([[0.1, 2.5]], np.float32)
    b32 = np.array([[1e-30, 3e38]], np.float32)
    b64 = np.array([[0.1, 1e300]])
    x, y = one_float_dtype(a32, b32)
    assert x is a32 and y is b32
    x, y = one_float_dtype(a32, b64)
    assert x.dtype == y.dtype == np.float64 and y is b64
    np.testing.assert_array_equal(x.astype(np.float32), a32)  # exact: narrows back to the same bits
    assert (x == a32).all()


def _mixed_set(w=12, h=10, spp=8, seed=0):
    rng = np.random.default_rng(seed)
    n = w * h * spp
    pos = np.stack([rng.uniform(0, w, n), rng.uniform(0, h, n)], 1)   # float64
    val = rng.exponential(size=(n, 3)).astype(np.float32)             # float32, as a renderer writes
    alb = rng.uniform(0, 1, (n, 3)).astype(np.float32)
    return SampleSet(pos, val, width=w, height=h, features={"albedo": alb}), pos, val, alb


KERNELS = [(gated, "_splat_gated_runs"), (consistent, "_add_channel_sums"), (consistent, "_add_feature_sums"),
           (consistent, "_split_and_radii"), (outliers, "_count_and_moments")]


def test_a_mixed_pair_compiles_no_mixed_signature_and_gives_the_float64_sums():
    ss, pos, val, alb = _mixed_set()
    wide = SampleSet(pos, val.astype(np.float64), width=ss.width, height=ss.height,
                     features={"albedo": alb.astype(np.float64)})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        got = mcrecon.reconstruct(ss, method="splat")
        want = mcrecon.reconstruct(wide, method="splat")
    np.testing.assert_array_equal(got, want)
    st = PixelStats.from_source(ss, features=("albedo",))
    st_wide = PixelStats.from_source(wide, features=("albedo",))
    np.testing.assert_array_equal(st.mean, st_wide.mean)
    np.testing.assert_array_equal(st.features["albedo"].mean, st_wide.features["albedo"].mean)
    assert st.dtype == np.float32  # the values' dtype as given is what the statistics report
    for mod, name in KERNELS + [(merge, "_accumulate")]:
        sigs = dispatcher(getattr(mod, name)).signatures
        assert sigs, name  # the case ran the kernel
        pairs = {(s[0].dtype, s[1].dtype) for s in sigs}
        assert all(p == q for p, q in pairs), (name, pairs)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_a_shared_dtype_reaches_the_kernels_as_given(dtype):
    ss, pos, val, alb = _mixed_set(seed=1)
    same = SampleSet(pos.astype(dtype), val.astype(dtype), width=ss.width, height=ss.height,
                     features={"albedo": alb.astype(dtype)})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        mcrecon.reconstruct(same, method="splat")
    sigs = dispatcher(gated._splat_gated_runs).signatures
    assert any(s[0].dtype == s[1].dtype == numba_dtype(dtype) for s in sigs)


def numba_dtype(dtype):
    from numba import from_dtype

    return from_dtype(np.dtype(dtype))
