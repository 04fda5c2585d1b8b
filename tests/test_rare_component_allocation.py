"""Adaptive allocation under a rare bright component: the pixels whose few samples all missed a light their
neighbours found keep their share of samples (gem, awr; auto plans with gem's selection)."""

import numpy as np
import pytest

import mcrecon
from mcrecon.core.safeguard import rare_component_variance
from mcrecon.core.stats import PixelStats


def _spot(w=24, h=20, spp=16, p=0.05, light=40.0, seed=0, lit=True):
    """Sky 0.5 with a little noise; inside the disc a light found by a fraction p of the samples."""
    rng = np.random.default_rng(seed)
    iy, ix = np.divmod(np.tile(np.arange(w * h), spp), w)
    pos = np.stack([ix + rng.random(ix.size), iy + rng.random(iy.size)], axis=1)
    val = 0.5 + 0.02 * rng.standard_normal(ix.size)
    inside = (ix - w / 2) ** 2 + (iy - h / 2) ** 2 < (0.4 * h) ** 2
    if lit:
        val = val + np.where(inside & (rng.random(ix.size) < p), light, 0.0)
    vals = np.repeat(val[:, None], 3, axis=1)
    st = PixelStats.from_samples(pos, vals, width=w, height=h)
    return st, inside.reshape(spp, h, w)[0]


def _mean_var(st):
    return st.sample_variance(undefined=0.0) / np.maximum(st.count, 1)[..., None]


def test_missed_pixels_take_their_neighbourhoods_variance():
    st, inside = _spot()
    v = _mean_var(st)
    out = rare_component_variance(v, st.mean, st.count)
    missed = inside & (st.mean[..., 0] < 1.0)          # none of the 16 samples found the light
    core = missed.copy()
    core[:4], core[-4:], core[:, :6], core[:, -6:] = False, False, False, False
    assert core.sum() > 20
    # own variance: the sky's noise (4e-4 / 16); floored: the light's share, thousands of times more
    assert np.median(v[core, 0]) < 1e-3 and np.median(out[core, 0]) > 1.0
    assert (out >= v).all()


def test_no_rare_component_leaves_the_variance_alone():
    st, _ = _spot(lit=False)
    v = _mean_var(st)
    assert np.array_equal(rare_component_variance(v, st.mean, st.count), v)
    # an edge between two flat regions: each pixel keeps its own
    w, h, spp = 16, 8, 8
    rng = np.random.default_rng(1)
    iy, ix = np.divmod(np.tile(np.arange(w * h), spp), w)
    pos = np.stack([ix + rng.random(ix.size), iy + rng.random(iy.size)], axis=1)
    val = np.where(pos[:, 0] < 8.5, 0.1, 2.0) + 0.05 * rng.standard_normal(ix.size)
    st = PixelStats.from_samples(pos, np.repeat(val[:, None], 3, axis=1), width=w, height=h)
    v = _mean_var(st)
    assert np.array_equal(rare_component_variance(v, st.mean, st.count), v)


def test_rare_component_variance_validates_shapes():
    st, _ = _spot()
    with pytest.raises(ValueError, match="rare_component_variance"):
        rare_component_variance(_mean_var(st), st.mean[..., :1], st.count)


def test_gem_prioritises_the_missed_pixels():
    st, inside = _spot(w=32, h=28)
    missed = inside & (st.mean[..., 0] < 1.0)
    hit = inside & (st.mean[..., 0] > 2.0)
    share = {}
    for floor in (0, 1):
        m = mcrecon.get_method("gem", rare_light_floor=floor)
        sel = m.select(m.start(32, 28), st, final=False, want_mse=True)
        mse = sel.mse.sum(axis=2)
        share[floor] = np.median(mse[missed]) / np.median(mse[hit])
    # without the floor a missed pixel's estimated error is its sky noise: nothing next to a hit's
    assert share[0] < 0.01 and share[1] > 0.05


def test_awr_sampler_reaches_the_missed_pixels():
    from mcrecon.methods.awr.sampling import plan_awr_positions

    st, inside = _spot(w=32, h=32)
    missed = inside & (st.mean[..., 0] < 1.0)
    got = {}
    for floor in (False, True):
        counts, _ = plan_awr_positions(st, 4 * 32 * 32, np.random.default_rng(0), levels=3, per_coefficient=4,
                                       as_counts=True, rare_light_floor=floor)
        got[floor] = counts[missed].mean() / counts[inside].mean()
    assert got[False] < 0.93 and got[True] > 0.98      # missed pixels: their share of the disc's samples
