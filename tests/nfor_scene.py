"""A synthetic textured scene with per-sample features and an exact reference (tests/test_nfor.py, benchmarks).

Colour = albedo x shading x E, E ~ Exponential(1) per sample (Monte Carlo
noise of relative standard deviation 1 per sample, mean exactly 1):

* albedo: a checkerboard of ``square``-pixel squares (two strongly
  different colours), constant inside each pixel, so the reference's
  texture is sharp and a colour-only filter blurs it;
* shading: a smooth function of the film position, exact per sample;
* a "defocused" band (``x >= 2 W / 3``): every sample looks up albedo,
  shading *and its features* at its position jittered by a Gaussian of
  ``blur`` pixels (a thin lens' circle of confusion), so there the
  features are noisy and blurred exactly where the colour is.

Features per sample: ``albedo`` (3), ``normal`` (3: a smooth bump),
``depth`` (1: a tilted plane).  The reference is the pixel average of the
expected colour: 8 x 8 subpixel quadrature of the shading (smooth: error
below 1e-5 of the value, measured against 16 x 16) and, in the band,
16-point Gauss-Hermite quadrature per axis of the jitter.
"""

from __future__ import annotations

import numpy as np

from mcrecon.core.samples import SampleSet

COLOURS = np.array([[0.85, 0.7, 0.3], [0.08, 0.15, 0.4]])


def _albedo(x, y, square):
    return COLOURS[((np.floor(x / square) + np.floor(y / square)) % 2).astype(int)]


def _shading(x, y, w, h):
    return 0.4 + 2.0 * np.exp(-((x - 0.3 * w) ** 2 + (y - 0.4 * h) ** 2) / (0.35 * w) ** 2)


def _normal(x, y, w, h):
    n = np.stack([np.sin(2 * np.pi * x / w) * 0.3, np.cos(2 * np.pi * y / h) * 0.3, np.ones_like(x)], axis=-1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def _depth(x, y, w, h):
    return 2.0 + 3.0 * x / w + 0.5 * y / h


def _colour(x, y, w, h, square):
    return _albedo(x, y, square) * _shading(x, y, w, h)[..., None]


def scene_samples(width=64, height=64, spp=16, seed=0, *, square=8, blur=2.5):
    """A :class:`SampleSet` with features (``spp`` jittered samples per pixel) of the scene."""
    rng = np.random.default_rng(seed)
    n = width * height * spp
    pix = np.repeat(np.arange(width * height), spp)
    pos = np.stack([pix % width + rng.random(n), pix // width + rng.random(n)], axis=1)
    val, feats = scene_values(pos, rng, width, height, square=square, blur=blur)
    return SampleSet(pos, val, width=width, height=height, features=feats)


def scene_values(pos, rng, width, height, *, square=8, blur=2.5):
    """Values (n, 3) and features of samples at film positions ``pos`` (n, 2)."""
    n = len(pos)
    look = pos.copy()
    band = pos[:, 0] >= 2 * width / 3
    look[band] += rng.normal(0.0, blur, size=(int(band.sum()), 2))
    x, y = look[:, 0], look[:, 1]
    val = _colour(x, y, width, height, square) * rng.exponential(1.0, size=(n, 1))
    feats = {"albedo": _albedo(x, y, square), "normal": _normal(x, y, width, height),
             "depth": _depth(x, y, width, height)}
    return val, feats


def scene_reference(width=64, height=64, *, square=8, blur=2.5, sub=8, gh=16):
    """The exact pixel averages of the expected colour (H, W, 3)."""
    u = (np.arange(sub) + 0.5) / sub
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float64)
    ref = np.zeros((height, width, 3))
    for uy in u:
        for ux in u:
            ref += _colour(xx + ux, yy + uy, width, height, square)
    ref /= sub * sub
    cols = slice(int(np.ceil(2 * width / 3)), width)
    t, wt = np.polynomial.hermite_e.hermegauss(gh)  # nodes and weights for exp(-t^2 / 2)
    wt = wt / wt.sum()
    band = np.zeros((height, width - cols.start, 3))
    bx, by = xx[:, cols], yy[:, cols]
    u4 = (np.arange(4) + 0.5) / 4  # the jitter smooths the checker edges: 4 x 4 pixel positions suffice
    for uy in u4:
        for ux in u4:
            for ty, wy in zip(t, wt):
                for tx, wx in zip(t, wt):
                    band += wy * wx * _colour(bx + ux + blur * tx, by + uy + blur * ty, width, height, square)
    ref[:, cols] = band / 16
    return ref
