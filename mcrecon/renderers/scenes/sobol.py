"""A per-pixel Owen-scrambled Sobol sequence over all of a sample's dimensions (compiled, nogil).

Padded 2-D Owen-scrambled Sobol, after B. Burley, "Practical Hash-based
Owen Scrambling", JCGT 9(4), 2020: the dimensions of a sample (film x, film
y, then the scene's random numbers) are taken in pairs; pair g of sample i
of pixel p is the first two Sobol dimensions (van der Corput and its
Pascal-matrix partner, a (0, 2)-sequence) at the index
``shuffle(i, seed(p, g))``, each coordinate then nested-uniform (Owen)
scrambled with ``seed(p, dimension)``.  Both the shuffle and the scramble
are Burley's hash-based nested uniform scramble (Laine-Karras permutation of
the bit-reversed value); every seed is a 64-bit mix of (pixel, dimension,
run seed).

Why each part:

* the Owen scramble keeps the net property of the sequence: every aligned
  block of 2^k consecutive samples of a pixel, ``[m 2^k, (m + 1) 2^k)``, has
  one point in each elementary interval of area 2^-k in every pair (the
  first 2^k samples in particular, and a round of 8 after a round of 8);
* the shuffle of the index maps aligned blocks to aligned blocks (bit j of
  the shuffled index depends only on bits >= j of the index), so it keeps
  that, and, seeded per pair, decorrelates the pairs (padding);
* the seeds differ per pixel: neighbouring pixels' errors are independent
  (no structured aliasing across the image), as with independent samples.

A sample is a function of (pixel, index, dimension, run seed) alone, so a
pixel's sequence continues across requests from ``first_index`` and
rounds of 8 + 8 + 8 + 8 give the points of one 32-sample render.  Indices
are taken modulo 2^32 (the sequence repeats after 2^32 samples of a pixel).
"""

from __future__ import annotations

import numba
import numpy as np

from ..spec_format import SAMPLERS

__all__ = ["sobol_points", "SAMPLERS"]

_njit = numba.njit(cache=True, nogil=True)

_M32 = np.uint64(0xFFFFFFFF)


@_njit
def _reverse32(x):
    """The 32 low bits of ``x`` (uint64) in reverse order."""
    x = x & np.uint64(0xFFFFFFFF)
    x = ((x >> np.uint64(1)) & np.uint64(0x55555555)) | ((x & np.uint64(0x55555555)) << np.uint64(1))
    x = ((x >> np.uint64(2)) & np.uint64(0x33333333)) | ((x & np.uint64(0x33333333)) << np.uint64(2))
    x = ((x >> np.uint64(4)) & np.uint64(0x0F0F0F0F)) | ((x & np.uint64(0x0F0F0F0F)) << np.uint64(4))
    x = ((x >> np.uint64(8)) & np.uint64(0x00FF00FF)) | ((x & np.uint64(0x00FF00FF)) << np.uint64(8))
    x = ((x >> np.uint64(16)) & np.uint64(0x0000FFFF)) | ((x & np.uint64(0x0000FFFF)) << np.uint64(16))
    return x & np.uint64(0xFFFFFFFF)


@_njit
def _laine_karras(x, seed):
    """Burley's Laine-Karras-style permutation of 32 bits: output bit j depends on input bits <= j only."""
    m = np.uint64(0xFFFFFFFF)
    x = (x + seed) & m
    x ^= (x * np.uint64(0x6C50B47C)) & m
    x ^= (x * np.uint64(0xB82F1E52)) & m
    x ^= (x * np.uint64(0xC7AFE638)) & m
    x ^= (x * np.uint64(0x8D22F6E6)) & m
    return x


@_njit
def _nested_uniform_scramble(x, seed):
    """Owen scramble of a 32-bit fraction: bit j (from the top) flipped by a hash of the bits above it."""
    return _reverse32(_laine_karras(_reverse32(x), seed))


@_njit
def _sobol2(i):
    """The first two Sobol dimensions at index ``i`` (32-bit fractions)."""
    x = _reverse32(i)
    y = np.uint64(0)
    v = np.uint64(0x80000000)
    k = i
    while k:
        if k & np.uint64(1):
            y ^= v
        v ^= v >> np.uint64(1)
        k >>= np.uint64(1)
    return x, y


@_njit
def _mix64(z):
    """SplitMix64's finaliser: a bijective 64-bit hash."""
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


@_njit
def _seed(run_seed, pixel, key):
    """A 32-bit seed from (run seed, pixel, key): one chained 64-bit mix per input."""
    h = _mix64(run_seed + np.uint64(0x9E3779B97F4A7C15))
    h = _mix64(h ^ pixel)
    h = _mix64(h ^ key)
    return h & np.uint64(0xFFFFFFFF)


@_njit
def _points(pixels, indices, n_dims, run_seed, out):
    inv = 1.0 / 4294967296.0
    n_pairs = (n_dims + 1) // 2
    for r in range(pixels.shape[0]):
        p = np.uint64(pixels[r])
        i = np.uint64(indices[r]) & np.uint64(0xFFFFFFFF)
        for g in range(n_pairs):
            j = _nested_uniform_scramble(i, _seed(run_seed, p, np.uint64(0x100000000) + np.uint64(g)))
            x, y = _sobol2(j)
            d = 2 * g
            out[r, d] = float(_nested_uniform_scramble(x, _seed(run_seed, p, np.uint64(d)))) * inv
            if d + 1 < n_dims:
                out[r, d + 1] = float(_nested_uniform_scramble(y, _seed(run_seed, p, np.uint64(d + 1)))) * inv
    return out


def sobol_points(pixels, indices, n_dims: int, *, seed: int = 0) -> np.ndarray:
    """Points of the pixels' own Owen-scrambled Sobol sequences, (N, n_dims) float64 in [0, 1).

    Parameters
    ----------
    pixels : array of int, shape (N,)
        Each row's pixel (``row * width + column``; any non-negative integer).
    indices : array of int, shape (N,)
        Each row's index in its pixel's sequence (modulo 2^32).
    n_dims : int
        Dimensions per sample; dimensions 0 and 1 are a pair (film x and y
        for the scenes), then 2 and 3, ...
    seed : int
        The run seed (>= 0): another seed, another scramble of every pixel.
    """
    pixels = np.ascontiguousarray(pixels, np.int64).ravel()
    indices = np.ascontiguousarray(indices, np.int64).ravel()
    if pixels.shape != indices.shape:
        raise ValueError(f"sobol_points: {pixels.shape[0]} pixels and {indices.shape[0]} indices, expected as many")
    out = np.empty((pixels.shape[0], int(n_dims)), np.float64)
    if pixels.size and n_dims:
        _points(pixels.view(np.uint64), indices.view(np.uint64), int(n_dims),
                np.uint64(int(seed) & 0xFFFFFFFFFFFFFFFF), out)
    return out
