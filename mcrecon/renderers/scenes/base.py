"""The exact box-filter integrals the built-in scenes are built from (compiled, nogil).
"""

from __future__ import annotations


import numba
import numpy as np

from ...errors import InputError

# ----------------------------------------------------------------------------
# Scalar building blocks (numba): 1-D functions with analytic box averages
# ----------------------------------------------------------------------------
# Every scene is written as two scalar functions, radiance at one point and
# its expectation at one point, compiled with numba and driven by the generic
# loops below.  Per-point scalar code avoids numpy's (N, 3) temporaries: the
# reference image needs ~17 M expectation evaluations at 128^2 and q = 32.

_njit = numba.njit(cache=True, nogil=True)


@_njit
def _overlap_fraction(lo, hi, a, b):
    """Fraction of [lo, hi] (hi > lo) inside [a, b]: P(lo + (hi - lo) v in [a, b]), v ~ U[0, 1)."""
    v = min(hi, b) - max(lo, a)
    return v / (hi - lo) if v > 0.0 else 0.0


@_njit
def _box_cover(x, y, w, o):
    """Fraction of the w x w square centred on (x, y) inside the box o = [a, b] x [c, d]: the share of an
    area light (the square) that the occluder with shadow core o hides from the point."""
    return (_overlap_fraction(x - 0.5 * w, x + 0.5 * w, o[0], o[1])
            * _overlap_fraction(y - 0.5 * w, y + 0.5 * w, o[2], o[3]))


@_njit
def _box_hit(x, y, w, u1, u2, o):
    """Whether the light sample (u1, u2) of that square, (x + w (u1 - 1/2), y + w (u2 - 1/2)), is in box o."""
    sx = x + w * (u1 - 0.5)
    sy = y + w * (u2 - 0.5)
    return o[0] <= sx <= o[1] and o[2] <= sy <= o[3]


@_njit
def _checker(x, y, n):
    """0/1 checkerboard with n squares per unit: (floor(n x) + floor(n y)) mod 2."""
    return float((int(np.floor(n * x)) + int(np.floor(n * y))) & 1)


@_njit
def _square_wave(z):
    """Square wave of period 1: +1 where frac(z) < 1/2, -1 elsewhere."""
    return 1.0 if z - np.floor(z) < 0.5 else -1.0


@_njit
def _triangle(z):
    """Antiderivative of the square wave, zero at integers: 1/2 - |frac(z) - 1/2|."""
    return 0.5 - abs(z - np.floor(z) - 0.5)


# Below this box width the box average is replaced by the point value: the
# difference quotient of the triangle wave loses ~1e-16/width to rounding
# (1e-7 at width 1e-9), while the true change of the average is O(width).
_TINY_WIDTH = 1e-9


@_njit
def _box_square_wave(z, n, width):
    """Average of square_wave(n s) over s in [z - width/2, z + width/2].

    = [T(n (z + width/2)) - T(n (z - width/2))] / (n width), T the triangle
    wave; the point value for a (near) zero width.
    """
    if width < _TINY_WIDTH:
        return _square_wave(n * z)
    return (_triangle(n * (z + 0.5 * width)) - _triangle(n * (z - 0.5 * width))) / (n * width)


def _as_xy(name, x, y):
    x = np.ascontiguousarray(np.asarray(x, dtype=np.float64).reshape(-1))
    y = np.ascontiguousarray(np.asarray(y, dtype=np.float64).reshape(-1))
    if x.shape != y.shape:
        raise InputError(f"scene {name!r}", "x, y", f"shapes {x.shape} and {y.shape} differ: "
                         "pass one x and one y per point")
    return x, y


@_njit
def _wave(z):
    """Smooth (C^1) sine-like wave of period 1: 16 f (1/2 - f) on f = frac(z) < 1/2, then mirrored negative.

    Used instead of a sinusoid: its box average is exact with a few
    multiplications, while a libm sin/cos costs ~30 ns here.
    """
    f = z - np.floor(z)
    if f < 0.5:
        return 16.0 * f * (0.5 - f)
    g = f - 0.5
    return -16.0 * g * (0.5 - g)


@_njit
def _wave_integral(z):
    """Antiderivative of :func:`_wave`, periodic (the wave has zero mean):
    V(f) = 4 f^2 - 16 f^3 / 3 on f < 1/2, 1/3 - V(f - 1/2) on f >= 1/2."""
    f = z - np.floor(z)
    if f < 0.5:
        return f * f * (4.0 - 16.0 * f / 3.0)
    g = f - 0.5
    return 1.0 / 3.0 - g * g * (4.0 - 16.0 * g / 3.0)


@_njit
def _box_wave(z, n, phase, width):
    """Average of wave(n s + phase) over s in [z - width/2, z + width/2] (point value at width ~ 0)."""
    if width < _TINY_WIDTH:
        return _wave(n * z + phase)
    return (_wave_integral(n * (z + 0.5 * width) + phase)
            - _wave_integral(n * (z - 0.5 * width) + phase)) / (n * width)
