"""gem's adaptive floor under a rare bright component gates at a per-sample relative variance of 3 for
independent samples and 5 for a stratified sampler (``rare_threshold`` None follows the renderer): one hit
in a pixel's 4 initial samples reads 4, which a gate of 5 misses."""

from __future__ import annotations

import numpy as np

import mcrecon
from mcrecon.core.stats import PixelStats
from mcrecon.methods import get_method

from helpers import jittered_renderer


def _spot_stats(w=24, h=20, spp=4, p=0.15, light=40.0, seed=3):
    """Sky 0.5; inside a disc a light found by a fraction p of the samples; 4 samples per pixel."""
    rng = np.random.default_rng(seed)
    iy, ix = np.divmod(np.tile(np.arange(w * h), spp), w)
    pos = np.stack([ix + rng.random(ix.size), iy + rng.random(iy.size)], axis=1)
    inside = (ix - w / 2) ** 2 + (iy - h / 2) ** 2 < (0.4 * h) ** 2
    val = 0.5 + 0.02 * rng.standard_normal(ix.size) + np.where(inside & (rng.random(ix.size) < p), light, 0.0)
    st = PixelStats.from_samples(pos, np.repeat(val[:, None], 3, axis=1), width=w, height=h)
    return st, inside.reshape(spp, h, w)[0]


def test_a_gate_of_3_reaches_pixels_next_to_one_hit_in_4():
    st, inside = _spot_stats()
    missed = inside & (st.mean[..., 0] < 1.0)
    hit = inside & (st.mean[..., 0] > 2.0)
    assert missed.sum() > 20 and hit.sum() > 20
    assert (st.count[hit] == 4).all()
    m = get_method("gem")
    share = {}
    for thr in (5.0, 3.0):
        mse = m.select(m.start(24, 20), st, final=False, want_mse=True, rare_threshold=thr).mse.sum(axis=2)
        share[thr] = np.median(mse[missed]) / np.median(mse[hit])
    assert share[5.0] < 0.01 and share[3.0] > 0.05


def _spot(sampler):
    """A renderer of a light found by 15 % of the samples inside a disc, declaring ``sampler``."""
    def shade(pos, rng, req):
        inside = (pos[:, 0] - 12) ** 2 + (pos[:, 1] - 10) ** 2 < 8 ** 2
        v = 0.5 + 0.02 * rng.standard_normal(len(pos)) + np.where(inside & (rng.random(len(pos)) < 0.15), 40.0, 0.0)
        return np.repeat(v[:, None], 3, axis=1)

    film = jittered_renderer(shade, width=24, height=20)
    film.sampler = sampler
    return film


def _counts(sampler, **opts):
    return mcrecon.adapt(_spot(sampler), get_method("gem", **opts), spp=16, seed=2, progress=False,
                         track_error=False).stats.count


def test_the_gate_follows_the_renderer():
    indep, sobol = _counts("independent"), _counts("sobol")
    assert np.array_equal(indep, _counts("independent", rare_threshold=3.0))
    assert np.array_equal(sobol, _counts("sobol", rare_threshold=5.0))
    assert not np.array_equal(indep, _counts("independent", rare_threshold=5.0))
