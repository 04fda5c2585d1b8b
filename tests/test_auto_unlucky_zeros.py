"""auto fills a pixel whose samples all missed a light its neighbours found, and keeps exact black black.

An indirectly lit wall at 32 spp: each sample carries the light with
probability 1/25, so about a quarter of the pixels drew none of it.  Their
sample variance is 0; where most of their 3 x 3 neighbours drew none
either, the pooled variance is 0 too, the pixel mean's error estimate 0,
and the clamp's interval a point: the pixel stayed black beside lit ones.
"""

from __future__ import annotations

import warnings

import numpy as np

import mcrecon
from mcrecon.core.samples import SampleSet
from mcrecon.methods.auto.method import agreeing_variance


def _wall(seed, size=64, spp=32, p=0.04, black_box=None):
    rng = np.random.default_rng(seed)
    iy, ix = np.mgrid[0:size, 0:size]
    mu = (0.3 + 0.2 * np.sin(ix / 9.0) * np.cos(iy / 13.0))[..., None] * np.array([1.0, 0.8, 0.6])
    if black_box is not None:
        mu[black_box] = 0.0
    pix = np.repeat(np.arange(size * size), spp)
    pos = np.stack([pix % size + rng.random(pix.size), pix // size + rng.random(pix.size)], 1)
    hit = rng.random(pix.size) < p
    vals = np.where(hit[:, None], mu.reshape(-1, 3)[pix] / p, 0.0)
    return SampleSet(pos, vals, width=size, height=size), mu


def _rel(x, mu):
    return float(np.mean((x - mu) ** 2 / (mu ** 2 + 0.01)))


def test_auto_leaves_no_black_pixels_under_lit_neighbours():
    ss, mu = _wall(0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        box = mcrecon.reconstruct(ss, method="box")
        img = mcrecon.reconstruct(ss, method="auto")
    zero = box.max(axis=2) == 0
    assert zero.sum() > 1000   # ~27 % of the pixels drew none of the light
    black = zero & (img.max(axis=2) == 0)
    # measured 5 black pixels (159 with the 3 x 3 pooled variance alone), auto 0.030 of the mean's error (0.078)
    assert black.sum() <= 20
    assert _rel(img, mu) <= 0.045 * _rel(box, mu)


def test_agreeing_variance_floors_only_lone_agreeing_pixels():
    v = np.full((9, 9, 1), 0.5)
    count = np.full((9, 9), 8)
    v[4, 4, 0] = 0.0            # an unlucky pixel among noisy ones
    v[:, :3, 0] = 0.0           # an exactly black band three pixels wide... beside noisy ones
    v[0:9, 0, 0] = 0.0
    out = agreeing_variance(v, count)
    assert out[4, 4, 0] == 0.5                  # the 5 x 5 median of its noisy neighbourhood
    assert (out[:, 0, 0] == 0).all()            # most of its 5 x 5 neighbours agree too: it keeps 0
    assert (out[v > 0] == v[v > 0]).all()       # pixels with a variance keep theirs
    empty = count.copy()
    empty[4, 4] = 0
    assert agreeing_variance(v, empty)[4, 4, 0] == 0.0   # no samples: no interval to build


def test_an_exactly_black_region_stays_black():
    ss, mu = _wall(1, black_box=(slice(20, 44), slice(20, 44)))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        img = mcrecon.reconstruct(ss, method="auto")
    inner = img[23:41, 23:41]
    assert (inner == 0).all()
