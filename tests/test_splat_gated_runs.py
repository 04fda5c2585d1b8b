"""The default's gated splat by runs of a pixel's samples against the per-sample loop it replaces."""

from __future__ import annotations

import numpy as np
import pytest

from mcrecon.core.requests import jittered_positions
from mcrecon.methods.splat.consistent import edge_radius, gate_k, pixel_moments
from mcrecon.methods.splat.gated import GATE_SIDE, _splat_gated_runs, lattice_tables
from mcrecon.methods.splat.kernels import _add_widths, _splat_gated_loop


def _case(w, h, spp, seed, shuffle, rmax=5.0):
    """A round of a noisy step with a feature, the gate's statistics, radii up to ``rmax`` px (some <= 0)."""
    rng = np.random.default_rng(seed)
    pos = jittered_positions(np.full((h, w), spp), rng)
    lum = np.where(pos[:, 0] < w / 2, 0.5, 0.8) * (0.5 + rng.random(len(pos)))
    val = lum[:, None] * np.array([1.0, 0.7, 0.4])
    if shuffle:
        o = rng.permutation(len(pos))
        pos, val = pos[o], val[o]
    pix = np.floor(pos[:, 1]).astype(int) * w + np.floor(pos[:, 0]).astype(int)
    counts = np.bincount(pix, minlength=w * h).reshape(h, w)
    c1 = np.zeros((h * w, 3))
    c2 = np.zeros((h * w, 3))
    np.add.at(c1, pix, val)
    np.add.at(c2, pix, val * val)
    gs = pixel_moments(counts, c1.reshape(h, w, 3), c2.reshape(h, w, 3))
    k = gate_k(0.05, 3)
    r_edge = edge_radius(gs, k)
    fmean = np.where(np.arange(w) < w // 2, 0.2, 0.9)[None, :].repeat(h, 0)
    fs = np.zeros((h, w, 1, 5))
    fs[..., 0, 0] = fmean
    fs[..., 0, 1] = 1e-6
    radius = rng.uniform(0.3, rmax, len(pos))
    radius[rng.random(len(pos)) < 0.2] = -1.0
    frac = np.where(rng.random(len(pos)) < 0.1, rng.random(len(pos)), 0.0)
    inv = 1.0 / counts
    return pos, val, 0.5, inv, frac, radius, r_edge, gs, fs, k * k


def _memo(w, h):
    return np.zeros((w * h, GATE_SIDE * GATE_SIDE), np.int8)


@pytest.mark.parametrize("w, h, spp, mode, shuffle, rmax", [
    (12, 10, 8, 0, False, 5.0), (12, 10, 8, 0, True, 5.0), (12, 10, 8, 2, False, 5.0), (3, 9, 8, 0, False, 5.0),
    (9, 2, 8, 2, True, 5.0), (4, 3, 150, 0, False, 5.0), (16, 14, 8, 0, False, 11.0)])
def test_runs_equal_the_per_sample_loop(w, h, spp, mode, shuffle, rmax):
    """The same deposits to rounding, in bands of rows too (the samples of every band's reach, the gate's
    answers shared between the bands), films narrower than the footprints (mirrored more than once),
    samples shuffled (runs of one sample), the none boundary (energy lost off the film alike), runs longer
    than the kernel's first buffers, footprints wider than its first table of squared offsets (r^2 > 64)."""
    args = _case(w, h, spp, 3, shuffle, rmax)
    n = len(args[0])
    ref = np.zeros((h, w, 3))
    _splat_gated_loop(*args, mode, ref, 0, n, 0, h)
    # the outliers' radii (some samples), the default diameter's half: the widths the pass adds
    orad = np.where(np.random.default_rng(4).random(n) < 0.1, 2.5, -1.0)
    ref_ws, ref_wn = np.zeros((h, w)), np.zeros((h, w), np.int64)
    _add_widths(args[0], orad, args[5], 0.5, ref_ws, ref_wn, 0, n, 0, h)
    got = np.zeros((h, w, 3))
    ws, wn = np.zeros((h, w)), np.zeros((h, w), np.int64)
    assert _splat_gated_runs(*args, mode, got, _memo(w, h), orad, 0.5, ws, wn, 0, n, 0, h) == 0
    np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-15)
    np.testing.assert_array_equal(ws, ref_ws)  # the same sums, in the same order: the same bits
    np.testing.assert_array_equal(wn, ref_wn)
    assert wn.sum() == n  # every sample has a diameter (the default where it has no radius)
    banded = np.zeros((h, w, 3))
    memo = _memo(w, h)
    bws, bwn = np.zeros((h, w)), np.zeros((h, w), np.int64)
    for j0, j1 in ((0, 1), (1, h // 2), (h // 2, h)):
        _splat_gated_runs(*args, mode, banded, memo, orad, 0.5, bws, bwn, 0, n, j0, j1)
    np.testing.assert_array_equal(banded, got)
    np.testing.assert_array_equal(bws, ws)
    np.testing.assert_array_equal(bwn, wn)
    total = (args[1] * (args[2] * args[3][np.floor(args[0][:, 1]).astype(int), np.floor(args[0][:, 0]).astype(int)]
                        * (1 - args[4]))[:, None]).sum(axis=0)
    if mode == 0:
        np.testing.assert_allclose(got.sum(axis=(0, 1)), total, rtol=1e-12)


def test_lattice_tables_count_the_footprint():
    """The weight sum of a footprint from the tables equals the sum over its centres."""
    cnt, sq = lattice_tables(40)
    for r in (0.6, 1.0, 1.5, np.sqrt(5.0) + 1e-9, 3.3, 6.0):
        o = np.arange(-7, 8)
        d2 = (o[:, None] ** 2 + o[None, :] ** 2).astype(float)
        brute = np.where(d2 < r * r, 1.0 - d2 / (r * r), 0.0).sum()
        lim = int(np.ceil(r * r)) - 1
        assert cnt[lim] - sq[lim] / (r * r) == pytest.approx(brute, rel=1e-13)
