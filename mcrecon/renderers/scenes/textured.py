"""Kernels of the textured scenes (``checker_wall``, ``checker_spot``, ``checker_dof``): radiance, per-sample
features and their exact expectations (compiled, nogil).

Feature vectors are 7 floats: albedo R, G, B, normal X, Y, Z, depth (see
:data:`mcrecon.renderers.scenes.catalog.FEATURE_LAYOUT`).  The classes and
the formulas' documentation are in :mod:`.catalog` and ``docs/scenes.md``.
"""

from __future__ import annotations

import numba
import numpy as np

from .base import _TINY_WIDTH, _box_cover, _box_hit, _checker, _njit, _square_wave, _triangle

# --- checker_wall ------------------------------------------------------------

#: Coarse checker: squares of 1/8 (16 px at 128 px), two albedos ~12x apart in luminance.
_CW_COARSE = 8.0
_CW_COARSE_ALBEDO = np.array([[0.85, 0.82, 0.75],
                              [0.06, 0.07, 0.10]])
#: Fine checker (squares of 1/32, 4 px at 128 px) in the quadrant x >= 1/2, y >= 1/2.
_CW_FINE = 32.0
_CW_FINE_X, _CW_FINE_Y = 0.5, 0.5
_CW_FINE_ALBEDO = np.array([[0.92, 0.38, 0.22],
                            [0.18, 0.52, 0.90]])
#: Sky (ambient) irradiance, estimated per sample with one uniform number: k 2 u3.
_CW_SKY = 0.25
_CW_LIGHT = np.array([0.80, 0.77, 0.72])
#: The occluder's shadow core [a, b] x [c, d] (normalised film space) and the penumbra width 0.02 + 0.10 x.
_CW_OCC = np.array([0.22, 0.70, 0.28, 0.68])
_CW_DEPTH = 2.0


#: Parameter layout shared by checker_wall and checker_spot: the albedo block 0:16 (coarse squares per unit
#: 0, coarse albedos 1:7, fine squares per unit 7, fine quadrant corner 8, 9, fine albedos 10:16); then
#: checker_wall: sky 16, light 17:20, occluder 20:24, penumbra W0 24, W1 25, depth 26;
#: checker_spot: p 16, sky 17, light 18:21, spot centre 21, 22, s^2 23, occluder 24:28, W0 28, W1 29.
_CW_W0, _CW_W1 = 0.02, 0.10
_CS_W0, _CS_W1 = 0.004, 0.012


@_njit
def _cw_width(p, x):
    return p[24] + p[25] * x


@_njit
def _cw_albedo(p, x, y, f):
    """Albedo at one point into f[0:3] (deterministic: the wall faces the pinhole camera)."""
    if x >= p[8] and y >= p[9]:
        chk = _checker(x, y, p[7])
        for c in range(3):
            f[c] = p[10 + c] + (p[13 + c] - p[10 + c]) * chk
    else:
        chk = _checker(x, y, p[0])
        for c in range(3):
            f[c] = p[1 + c] + (p[4 + c] - p[1 + c]) * chk


@numba.njit(cache=True, nogil=True, inline="always")
def _lit_wall(p, x, y, sky, light, amount, out):
    """The textured wall's colour at one point into out[0:3]: albedo times (sky + light * amount)."""
    _cw_albedo(p, x, y, out)
    for c in range(3):
        out[c] *= sky + light[c] * amount


@_njit
def _cw_radiance(p, x, y, u, out):
    vis = 0.0 if _box_hit(x, y, _cw_width(p, x), u[0], u[1], p[20:24]) else 1.0
    sky = p[16] * 2.0 * u[2]
    _lit_wall(p, x, y, sky, p[17:20], vis, out)


@_njit
def _cw_expected(p, x, y, out):
    vis = 1.0 - _box_cover(x, y, _cw_width(p, x), p[20:24])
    _lit_wall(p, x, y, p[16], p[17:20], vis, out)


@_njit
def _cw_feature_expected(p, x, y, f):
    _cw_albedo(p, x, y, f)
    f[3] = 0.0
    f[4] = 0.0
    f[5] = -1.0
    f[6] = _CW_DEPTH


@_njit
def _cw_features(p, x, y, u, f):
    # The primary hit does not depend on the light or sky samples: the features are exact per point.
    _cw_feature_expected(p, x, y, f)


# --- checker_spot ------------------------------------------------------------

#: The small light is found by the BSDF sample with probability p (else the sample sees only the sky):
#: its contribution is l f(x, y) V / p on a hit, so ~1 sample in 20 carries nearly all the light.
_CS_P = 0.05
_CS_SKY = 0.04
_CS_LIGHT = np.array([0.95, 0.85, 0.65])
#: Spot falloff f = 1 / (1 + |(x, y) - c|^2 / s^2): smooth, deterministic.
_CS_CX, _CS_CY, _CS_S2 = 0.68, 0.30, 0.09
#: The small light's shadow core (normalised film space), penumbra 0.004 + 0.012 x (0.5 to 2 px at 128 px).
_CS_OCC = np.array([0.30, 0.56, 0.46, 0.82])


@_njit
def _cs_width(p, x):
    return p[28] + p[29] * x


@_njit
def _cs_falloff(p, x, y):
    return 1.0 / (1.0 + ((x - p[21]) ** 2 + (y - p[22]) ** 2) / p[23])


@_njit
def _cs_radiance(p, x, y, u, out):
    vis = 0.0
    if u[0] < p[16]:
        vis = 0.0 if _box_hit(x, y, _cs_width(p, x), u[1], u[2], p[24:28]) else 1.0 / p[16]
    light = _cs_falloff(p, x, y) * vis
    sky = p[17] * 2.0 * u[3]
    _lit_wall(p, x, y, sky, p[18:21], light, out)


@_njit
def _cs_expected(p, x, y, out):
    vis = 1.0 - _box_cover(x, y, _cs_width(p, x), p[24:28])
    light = _cs_falloff(p, x, y) * vis
    _lit_wall(p, x, y, p[17], p[18:21], light, out)


@_njit
def _cs_feature_expected(p, x, y, f):
    _cw_feature_expected(p, x, y, f)  # the same wall as checker_wall


@_njit
def _cs_features(p, x, y, u, f):
    _cw_feature_expected(p, x, y, f)


# --- checker_dof -------------------------------------------------------------

#: Thin lens with a square aperture: a point at depth z images to a square of signed side
#: R(z) = a (1/z - 1/z_f) in normalised film units (a lens offset l moves the ray's
#: pinhole projection at depth z by l (1/z - 1/z_f)).
_CD_APERTURE = 1.0 / 8.0
_CD_FOCUS = 2.0


def _cd_blur(z, aperture=_CD_APERTURE, focus=_CD_FOCUS):
    return aperture * (1.0 / z - 1.0 / focus)


def _cd_planes(aperture=_CD_APERTURE, focus=_CD_FOCUS, texture_scale=1.0):
    """Columns: z, R, x0, x1, y0, y1, squares per unit n, A0 (3), A1 (3), irradiance E, normal (3).

    Front to back; the rectangle is in the plane's own pinhole-projected film
    coordinates; the last plane (the wall) is unbounded.  ``aperture`` and
    ``focus`` set each plane's blur R (the scene's parameters), ``texture_scale``
    multiplies the squares per unit.
    """
    inf = np.inf
    rows = [
        # near card, 8 px blur at 128 px, 8 px squares
        (1.0, 2 / 32, 15 / 32, 14 / 32, 30 / 32, 16.0, (0.20, 0.45, 0.85), (0.92, 0.85, 0.35), 1.0,
         (0.0, -0.6, -0.8)),
        # card in focus, 4 px squares
        (2.0, 13 / 32, 30 / 32, 2 / 32, 17 / 32, 32.0, (0.90, 0.25, 0.20), (0.95, 0.92, 0.85), 1.1,
         (-0.6, 0.0, -0.8)),
        # far wall, 2.7 px blur, 16 px squares
        (3.0, -inf, inf, -inf, inf, 8.0, (0.80, 0.76, 0.68), (0.10, 0.12, 0.16), 0.9, (0.0, 0.0, -1.0)),
    ]
    out = np.empty((len(rows), 17))
    for k, (z, x0, x1, y0, y1, n, a0, a1, e, nrm) in enumerate(rows):
        out[k] = (z, _cd_blur(z, aperture, focus), x0, x1, y0, y1, n * texture_scale if texture_scale != 1.0 else n,
                  *a0, *a1, e, *nrm)
    return out


_CD_PLANES = _cd_planes()
_CD_K = _CD_PLANES.shape[0]
# parameter array: the planes' rows (17 numbers each, as _cd_planes) one after the other


@_njit
def _cd_hit(p, x, y, u):
    """(plane index, s, t): the first plane whose rectangle holds the lens ray's projected hit point."""
    for k in range(_CD_K):
        q = p[17 * k:17 * k + 17]
        s = x + q[1] * (u[0] - 0.5)
        t = y + q[1] * (u[1] - 0.5)
        if q[2] <= s < q[3] and q[4] <= t < q[5]:
            return k, s, t
    return _CD_K - 1, s, t  # not reached: the last plane is unbounded


@_njit
def _cd_albedo(p, k, s, t, f):
    q = p[17 * k:17 * k + 17]
    chk = _checker(s, t, q[6])
    for c in range(3):
        f[c] = q[7 + c] + (q[10 + c] - q[7 + c]) * chk


@_njit
def _cd_radiance(p, x, y, u, out):
    k, s, t = _cd_hit(p, x, y, u)
    _cd_albedo(p, k, s, t, out)
    # per-sample irradiance estimate with mean E_k (u3 independent of the lens sample)
    e = p[17 * k + 13] * (0.5 + u[2])
    for c in range(3):
        out[c] *= e


@_njit
def _cd_features(p, x, y, u, f):
    k, s, t = _cd_hit(p, x, y, u)
    _cd_albedo(p, k, s, t, f)
    for c in range(3):
        f[3 + c] = p[17 * k + 14 + c]
    f[6] = p[17 * k]


@_njit
def _cd_interval(z, r, a, b):
    """The u in [0, 1] with z + r (u - 1/2) in [a, b), as (lo, hi) (empty when hi <= lo)."""
    if r == 0.0:
        return (0.0, 1.0) if a <= z < b else (0.0, 0.0)
    lo = 0.5 + (a - z) / r
    hi = 0.5 + (b - z) / r
    if r < 0.0:
        lo, hi = hi, lo
    return max(lo, 0.0), min(hi, 1.0)


@_njit
def _cd_square_integral(z, r, m, lo, hi):
    """Integral of q(m (z + r (u - 1/2))) over u in [lo, hi]: [T(m s_hi) - T(m s_lo)] / (m r), T the triangle
    wave (the antiderivative of q); the midpoint value times the length for a (near) zero blur."""
    if hi <= lo:
        return 0.0
    if abs(r) * (hi - lo) < _TINY_WIDTH:
        return _square_wave(m * (z + r * (0.5 * (lo + hi) - 0.5))) * (hi - lo)
    return (_triangle(m * (z + r * (hi - 0.5))) - _triangle(m * (z + r * (lo - 0.5)))) / (m * r)


@_njit
def _cd_expect(pa, x, y, out, features):
    """E_u of the colour (out[0:3]) or, with ``features``, of the 7 features, at one film point.

    Plane k is hit when its rectangle holds its projected point and no plane
    in front holds its own: 1{B_k} prod_{j<k} (1 - 1{B_j}), each B a box in
    (u1, u2).  Expanded by inclusion-exclusion it is a signed sum of
    indicators of box intersections (boxes again), over which the separable
    texture (A0 + A1)/2 - (A1 - A0)/2 q(n s/2) q(n t/2) integrates exactly.
    """
    n_out = 7 if features else 3
    for c in range(n_out):
        out[c] = 0.0
    for k in range(_CD_K):
        p = pa[17 * k:17 * k + 17]
        bx0, bx1 = _cd_interval(x, p[1], p[2], p[3])
        by0, by1 = _cd_interval(y, p[1], p[4], p[5])
        if bx1 <= bx0 or by1 <= by0:
            continue
        m = 0.5 * p[6]
        for mask in range(1 << k):
            lx, hx, ly, hy = bx0, bx1, by0, by1
            sign = 1.0
            for j in range(k):
                if (mask >> j) & 1:
                    q = pa[17 * j:17 * j + 17]
                    jx0, jx1 = _cd_interval(x, q[1], q[2], q[3])
                    jy0, jy1 = _cd_interval(y, q[1], q[4], q[5])
                    lx, hx = max(lx, jx0), min(hx, jx1)
                    ly, hy = max(ly, jy0), min(hy, jy1)
                    sign = -sign
            if hx <= lx or hy <= ly:
                continue
            area = (hx - lx) * (hy - ly)
            qq = _cd_square_integral(x, p[1], m, lx, hx) * _cd_square_integral(y, p[1], m, ly, hy)
            scale = 1.0 if features else p[13]
            for c in range(3):
                mid = 0.5 * (p[7 + c] + p[10 + c])
                half = 0.5 * (p[10 + c] - p[7 + c])
                out[c] += sign * scale * (mid * area - half * qq)
            if features:
                for c in range(3):
                    out[3 + c] += sign * area * p[14 + c]
                out[6] += sign * area * p[0]


@_njit
def _cd_expected(p, x, y, out):
    _cd_expect(p, x, y, out, False)


@_njit
def _cd_feature_expected(p, x, y, f):
    _cd_expect(p, x, y, f, True)
