"""Compiled kernels of the built-in scenes (numba, nogil): each scene's radiance, expectation, per-sample
features and their expectation at one point, and the loops that drive them by a scene id.

The formulas are documented on the scene classes (:mod:`.catalog`) and in ``docs/scenes.md``.
"""

from __future__ import annotations

import numpy as np

from .base import _box_cover, _box_hit, _box_square_wave, _box_wave, _checker, _njit, _square_wave, _wave
from .textured import (_cd_expected, _cd_feature_expected, _cd_features, _cd_radiance, _cs_expected,
                       _cs_feature_expected, _cs_features, _cs_radiance, _cw_expected, _cw_feature_expected,
                       _cw_features, _cw_radiance)
# --- soft_shadow -------------------------------------------------------------
# The defaults below are the scene's; a scene's parameter array (:mod:`.params`) carries the values its
# kernels read, so that the default parameters reproduce the constants exactly.

_SS_A0 = np.array([0.80, 0.72, 0.55])
_SS_A1 = np.array([0.18, 0.22, 0.32])
_SS_AMBIENT = 0.08
_SS_LIGHT = np.array([1.0, 0.95, 0.85])
_SS_CHECKER = 10.0
# (a, b, c, d): each occluder's shadow core [a, b] x [c, d] in normalised film space.
_SS_OCCLUDERS = np.array([[0.12, 0.48, 0.18, 0.38],
                          [0.30, 0.88, 0.58, 0.70]])
#: penumbra width w(x) = W0 + W1 x
_SS_W0, _SS_W1 = 0.01, 0.11
# parameter array: A0 0:3, A1 3:6, ambient 6, light 7:10, checker 10, W0 11, W1 12, occluders 13:21 (2 x 4)


@_njit
def _ss_width(p, x, y):
    return p[11] + p[12] * x


@_njit
def _ss_shade(p, x, y, vis, out):
    chk = _checker(x, y, p[10])
    for c in range(3):
        albedo = p[c] + (p[3 + c] - p[c]) * chk
        out[c] = albedo * (p[6] + p[7 + c] * vis)


@_njit
def _ss_radiance(p, x, y, u, out):
    w = _ss_width(p, x, y)
    vis = 1.0
    for k in range(2):
        if _box_hit(x, y, w, u[0], u[1], p[13 + 4 * k:17 + 4 * k]):
            vis = 0.0
    _ss_shade(p, x, y, vis, out)


@_njit
def _ss_expected(p, x, y, out):
    w = _ss_width(p, x, y)
    vis = 1.0
    for k in range(2):
        vis -= _box_cover(x, y, w, p[13 + 4 * k:17 + 4 * k])
    _ss_shade(p, x, y, vis, out)


# --- depth_of_field ----------------------------------------------------------

_DOF_RMAX = 1.0 / 16.0
_DOF_BAND, _DOF_RAMP = 0.1, 0.4           # in focus for |y - 1/2| <= band, full blur band + ramp away
_DOF_FREQ = (6.0, 20.0, 3.0, 2.0)         # checker, stripes, wave in s, wave in t (periods per unit)
_DOF_A = np.array([0.60, 0.55, 0.55])
_DOF_B = np.array([0.25, -0.15, 0.20])    # checker q(6s) q(6t)
_DOF_D = np.array([0.12, 0.15, 0.10])     # smooth wave w(3 s + phi)
_DOF_PHI = np.array([0.0, 1.0 / 3.0, 2.0 / 3.0])
_DOF_E = np.array([0.08, 0.05, 0.12])     # smooth wave w(2 t + psi)
_DOF_PSI = np.array([0.25, 0.0, 0.5])
_DOF_F = np.array([0.10, 0.12, -0.08])    # fine stripes q(20 s)
# parameter array: rmax 0, band 1, ramp 2, frequencies 3:7, A 7:10, B 10:13, D 13:16, PHI 16:19, E 19:22,
# PSI 22:25, F 25:28


@_njit
def _dof_r(p, x, y):
    return p[0] * min(1.0, max(0.0, (abs(y - 0.5) - p[1]) / p[2]))


@_njit
def _dof_radiance(p, x, y, u, out):
    r = _dof_r(p, x, y)
    s = x + r * (u[0] - 0.5)
    t = y + r * (u[1] - 0.5)
    qq = _square_wave(p[3] * s) * _square_wave(p[3] * t)
    stripes = _square_wave(p[4] * s)
    for c in range(3):
        out[c] = (p[7 + c] + p[10 + c] * qq + p[13 + c] * _wave(p[5] * s + p[16 + c])
                  + p[19 + c] * _wave(p[6] * t + p[22 + c]) + p[25 + c] * stripes)


@_njit
def _dof_expected(p, x, y, out):
    r = _dof_r(p, x, y)
    # u1 and u2 are independent: the average of q(6s) q(6t) is the product of the averages.
    qq = _box_square_wave(x, p[3], r) * _box_square_wave(y, p[3], r)
    stripes = _box_square_wave(x, p[4], r)
    for c in range(3):
        out[c] = (p[7 + c] + p[10 + c] * qq + p[13 + c] * _box_wave(x, p[5], p[16 + c], r)
                  + p[19 + c] * _box_wave(y, p[6], p[22 + c], r) + p[25 + c] * stripes)


# --- motion_blur -------------------------------------------------------------

_MB_BACKGROUND = np.array([0.30, 0.32, 0.36])
_MB_CHECKER = 16.0
# x0, y0, width, height, vx, vy (per shutter interval), then the colour.
_MB_OBJECTS = np.array([
    [0.05, 0.08, 0.18, 0.18, 0.35, 0.00, 0.95, 0.20, 0.15],    # red square, medium speed
    [0.85, 0.35, 0.04, 0.22, -0.50, 0.00, 0.20, 0.90, 0.25],   # green bar, fast, leftwards
    [0.05, 0.38, 0.10, 0.15, 0.02, 0.00, 0.95, 0.85, 0.20],    # yellow box, almost still
    [0.10, 0.65, 0.12, 0.12, 0.25, 0.15, 0.20, 0.35, 0.95],    # blue square, diagonal
    [0.55, 0.70, 0.08, 0.08, 0.35, 0.00, 0.95, 0.95, 0.95],    # small white square, horizontal
])
_MB_K = _MB_OBJECTS.shape[0]
# parameter array: background 0:3, checker 3, then the objects' rows (9 numbers each) from 4


def _mb_swept_boxes(objects=None):
    o = _MB_OBJECTS if objects is None else objects
    x0, y0, w, h, vx, vy = (o[:, k] for k in range(6))
    return np.stack([np.minimum(x0, x0 + vx), np.maximum(x0, x0 + vx) + w,
                     np.minimum(y0, y0 + vy), np.maximum(y0, y0 + vy) + h], axis=1)


def _mb_overlap(objects=None):
    """The first pair (j, i) of objects whose swept boxes overlap, or None."""
    boxes = _mb_swept_boxes(objects)
    for i in range(len(boxes)):
        for j in range(i):
            a, b = boxes[i], boxes[j]
            if a[0] < b[1] and b[0] < a[1] and a[2] < b[3] and b[2] < a[3]:
                return j, i
    return None


def _mb_check_disjoint():
    pair = _mb_overlap()
    if pair is not None:
        raise AssertionError(f"motion_blur objects {pair[0]} and {pair[1]} overlap in space-time")


# The closed form below assumes no two objects ever cover the same point.
_mb_check_disjoint()


@_njit
def _mb_background(p, x, y, out):
    g = 0.55 + 0.45 * _checker(x, y, p[3])
    for c in range(3):
        out[c] = p[c] * g


@_njit
def _mb_interval(p, p0, size, v):
    """Times t at which p0 + v t <= p < p0 + v t + size, as (lo, hi) (empty if lo >= hi)."""
    if v == 0.0:
        if p0 <= p < p0 + size:
            return -np.inf, np.inf
        return np.inf, -np.inf
    t1 = (p - p0 - size) / v
    t2 = (p - p0) / v
    return min(t1, t2), max(t1, t2)


@_njit
def _mb_radiance(p, x, y, u, out):
    t = u[0]
    _mb_background(p, x, y, out)
    for k in range(_MB_K):
        o = p[4 + 9 * k:13 + 9 * k]
        ox = o[0] + o[4] * t
        oy = o[1] + o[5] * t
        if ox <= x < ox + o[2] and oy <= y < oy + o[3]:
            for c in range(3):
                out[c] = o[6 + c]


@_njit
def _mb_expected(p, x, y, out):
    _mb_background(p, x, y, out)
    b0, b1, b2 = out[0], out[1], out[2]
    for k in range(_MB_K):
        o = p[4 + 9 * k:13 + 9 * k]
        lx, hx = _mb_interval(x, o[0], o[2], o[4])
        ly, hy = _mb_interval(y, o[1], o[3], o[5])
        frac = min(hx, hy, 1.0) - max(lx, ly, 0.0)
        if frac > 0.0:
            out[0] += frac * (o[6] - b0)
            out[1] += frac * (o[7] - b1)
            out[2] += frac * (o[8] - b2)


# --- caustic -----------------------------------------------------------------

_CA_P = 0.03
_CA_CX, _CA_CY = 0.5, 0.45
_CA_COLOUR = np.array([1.0, 0.85, 0.5])
_CA_GLOW = 0.02
_CA_HALF_WIDTH = 0.02
_CA_TABLE_TOP = 0.85
_CA_TABLE = np.array([0.05, 0.035, 0.02])
_CA_RADIUS, _CA_ECC = 0.28, 0.3
# parameter array: p 0, cx 1, cy 2, colour 3:6, glow 6, half width 7, radius 8, eccentricity 9


@_njit
def _ca_parts(p, x, y):
    """(caustic intensity C / colour, table background g / colour) at one point."""
    dx = x - p[1]
    dy = y - p[2]
    r = np.sqrt(dx * dx + dy * dy)
    cos_t = dx / r if r > 0.0 else 1.0        # any direction at the centre
    r0 = p[8] * (1.0 - p[9] * cos_t)
    z = (r - r0) / p[7]
    bump = (1.0 - z * z) ** 2 if abs(z) < 1.0 else 0.0
    inner = max(0.0, 1.0 - r / r0) ** 2
    caustic = (3.0 + 1.5 * cos_t) * bump + p[6] * inner
    table = 0.0
    if y > _CA_TABLE_TOP:
        table = (y - _CA_TABLE_TOP) / (1.0 - _CA_TABLE_TOP) * (1.0 + 0.5 * np.sin(6.0 * np.pi * x))
    return caustic, table


@_njit
def _ca_radiance(p, x, y, u, out):
    caustic, table = _ca_parts(p, x, y)
    hit = caustic / p[0] if u[0] < p[0] else 0.0
    noise = 2.0 * u[1]
    for c in range(3):
        out[c] = _CA_TABLE[c] * table * noise + p[3 + c] * hit


@_njit
def _ca_expected(p, x, y, out):
    caustic, table = _ca_parts(p, x, y)
    for c in range(3):
        out[c] = _CA_TABLE[c] * table + p[3 + c] * caustic


# --- hdr ---------------------------------------------------------------------

_HD_CX, _HD_CY, _HD_R = 0.3, 0.3, 0.14
_HD_POWER = 500.0
_HD_EMIT = np.array([1.0, 0.9, 0.75])
_HD_MID_LEFT = 0.62
_HD_MID = np.array([1.0, 0.95, 0.9])
_HD_DIM = np.array([1.0, 0.8, 0.6])
_HD_DIM_LEVEL = 1e-3
_HD_CHECKER = 12.0
_HD_OCC = (0.12, 0.42, 0.62, 0.78)
_HD_W0, _HD_W1 = 0.02, 0.1
#: the dim surfaces' albedo over their base value (albedo 0.8 d (1/2 + checker/2))
_HD_DIM_ALBEDO = 800.0
# parameter array: cx 0, cy 1, r 2, power 3, dim level 4, checker 5, occluder 6:10, W0 10, W1 11,
# dim albedo factor 12


@_njit
def _hd_base(p, x, y):
    """(region, base value): region 0 emitter, 1 mid panel, 2 dim surface."""
    rho2 = ((x - p[0]) ** 2 + (y - p[1]) ** 2) / (p[2] * p[2])
    if rho2 < 1.0:
        return 0, p[3] * (1.0 - 0.2 * rho2)
    if x >= _HD_MID_LEFT:
        return 1, 0.5 * (0.8 + 0.2 * _square_wave(8.0 * y))
    return 2, p[4] * (0.5 + 0.5 * _checker(x, y, p[5]))


@_njit
def _hd_write(region, base, scale, vis, out):
    for c in range(3):
        if region == 0:
            out[c] = base * scale * _HD_EMIT[c]
        elif region == 1:
            out[c] = base * scale * _HD_MID[c]
        else:
            out[c] = base * (1.0 + 9.0 * vis) * _HD_DIM[c]


@_njit
def _hd_radiance(p, x, y, u, out):
    region, base = _hd_base(p, x, y)
    blocked = _box_hit(x, y, p[10] + p[11] * x, u[1], u[2], p[6:10])
    _hd_write(region, base, 0.5 + u[0], 0.0 if blocked else 1.0, out)


@_njit
def _hd_expected(p, x, y, out):
    region, base = _hd_base(p, x, y)
    vis = 1.0 - _box_cover(x, y, p[10] + p[11] * x, p[6:10])
    _hd_write(region, base, 1.0, vis, out)


# --- features of the primary hit (albedo 0:3, normal 3:6, depth 6) ----------
# Camera space: X right (film columns), Y down (film rows), Z forward, the
# depth the hit's Z; normals face the camera (n_Z < 0).  Each scene's colour is
# albedo x shading (+ emission): the formulas are in docs/scenes.md.

@_njit
def _set_normal_depth(f, nx, ny, nz, depth):
    f[3] = nx
    f[4] = ny
    f[5] = nz
    f[6] = depth


@_njit
def _ss_feature_expected(p, x, y, f):
    # a ground plane seen from straight above; colour = albedo (ambient + l V)
    chk = _checker(x, y, p[10])
    for c in range(3):
        f[c] = p[c] + (p[3 + c] - p[c]) * chk
    _set_normal_depth(f, 0.0, 0.0, -1.0, 1.0)


@_njit
def _ss_features(p, x, y, u, f):
    _ss_feature_expected(p, x, y, f)  # the light sample does not move the primary hit


#: depth_of_field: colour = albedo x this irradiance (keeps the albedo <= 0.92).
_DOF_IRRADIANCE = 1.25
#: its plane recedes towards the bottom of the image: depth 2 + 2 (t - 1/2) at the hit's projected row t
_DOF_NORMAL = np.array([0.0, -1.0, -2.0]) / np.sqrt(5.0)


@_njit
def _dof_features(p, x, y, u, f):
    _dof_radiance(p, x, y, u, f)   # the texture at the lens ray's hit point (s, t)
    for c in range(3):
        f[c] /= _DOF_IRRADIANCE
    t = y + _dof_r(p, x, y) * (u[1] - 0.5)
    _set_normal_depth(f, _DOF_NORMAL[0], _DOF_NORMAL[1], _DOF_NORMAL[2], 2.0 + 2.0 * (t - 0.5))


@_njit
def _dof_feature_expected(p, x, y, f):
    _dof_expected(p, x, y, f)
    for c in range(3):
        f[c] /= _DOF_IRRADIANCE
    # depth is linear in t and E[t] = y (u2 - 1/2 has mean 0)
    _set_normal_depth(f, _DOF_NORMAL[0], _DOF_NORMAL[1], _DOF_NORMAL[2], 2.0 + 2.0 * (y - 0.5))


#: motion_blur: colour = albedo (unit irradiance); the wall at depth 3, object k at depth 1 + 0.25 k,
#: all facing the camera.
_MB_WALL_DEPTH = 3.0


@_njit
def _mb_features(p, x, y, u, f):
    t = u[0]
    _mb_background(p, x, y, f)
    _set_normal_depth(f, 0.0, 0.0, -1.0, _MB_WALL_DEPTH)
    for k in range(_MB_K):
        o = p[4 + 9 * k:13 + 9 * k]
        ox = o[0] + o[4] * t
        oy = o[1] + o[5] * t
        if ox <= x < ox + o[2] and oy <= y < oy + o[3]:
            for c in range(3):
                f[c] = o[6 + c]
            f[6] = 1.0 + 0.25 * k


@_njit
def _mb_feature_expected(p, x, y, f):
    _mb_background(p, x, y, f)
    _set_normal_depth(f, 0.0, 0.0, -1.0, _MB_WALL_DEPTH)
    b0, b1, b2 = f[0], f[1], f[2]
    for k in range(_MB_K):
        o = p[4 + 9 * k:13 + 9 * k]
        lx, hx = _mb_interval(x, o[0], o[2], o[4])
        ly, hy = _mb_interval(y, o[1], o[3], o[5])
        frac = min(hx, hy, 1.0) - max(lx, ly, 0.0)
        if frac > 0.0:
            f[0] += frac * (o[6] - b0)
            f[1] += frac * (o[7] - b1)
            f[2] += frac * (o[8] - b2)
            f[6] += frac * (1.0 + 0.25 * k - _MB_WALL_DEPTH)


#: caustic: a grey floor (the caustic's colour is the light's) seen obliquely, farther at the top; the
#: table top (y > 0.85) has albedo 10 T (its radiance T g 2 u2 is that albedo under a dim irradiance).
_CA_FLOOR_ALBEDO = 0.7
_CA_NORMAL = (0.0, -0.8, -0.6)


@_njit
def _ca_feature_expected(p, x, y, f):
    if y > _CA_TABLE_TOP:
        for c in range(3):
            f[c] = 10.0 * _CA_TABLE[c]
        depth = 0.8
    else:
        for c in range(3):
            f[c] = _CA_FLOOR_ALBEDO
        depth = 3.0 - 2.0 * y
    _set_normal_depth(f, _CA_NORMAL[0], _CA_NORMAL[1], _CA_NORMAL[2], depth)


@_njit
def _ca_features(p, x, y, u, f):
    _ca_feature_expected(p, x, y, f)  # the path choices do not move the primary hit


#: hdr: the emitter has albedo 0 (pure emission); the mid panel albedo 0.5 m (0.8 + 0.2 q(8y)) under
#: irradiance (1/2 + u1), tilted towards the left; the dim surfaces albedo 0.8 d (1/2 + checker/2) under
#: (dim level / 0.8) (1 + 9 V).
_HD_PANEL_NORMAL = (-0.6, 0.0, -0.8)


@_njit
def _hd_feature_expected(p, x, y, f):
    region, base = _hd_base(p, x, y)
    for c in range(3):
        if region == 0:
            f[c] = 0.0
        elif region == 1:
            f[c] = base * _HD_MID[c]
        else:
            f[c] = p[12] * base * _HD_DIM[c]
    if region == 0:
        _set_normal_depth(f, 0.0, 0.0, -1.0, 1.5)
    elif region == 1:
        _set_normal_depth(f, _HD_PANEL_NORMAL[0], _HD_PANEL_NORMAL[1], _HD_PANEL_NORMAL[2], 2.0)
    else:
        _set_normal_depth(f, 0.0, 0.0, -1.0, 2.5)


@_njit
def _hd_features(p, x, y, u, f):
    _hd_feature_expected(p, x, y, f)


# --- drivers -----------------------------------------------------------------
# One loop for all scenes, selecting the scalar functions by an integer id:
# numba's on-disk cache cannot store loops that take jitted functions as
# arguments (it fails to pickle the function type), and the id test is
# loop-invariant (hoisted by the compiler, or a perfectly predicted branch).

@_njit
def _point_radiance(kernel, p, x, y, u, out):
    if kernel == 1:
        _ss_radiance(p, x, y, u, out)
    elif kernel == 2:
        _dof_radiance(p, x, y, u, out)
    elif kernel == 3:
        _mb_radiance(p, x, y, u, out)
    elif kernel == 4:
        _ca_radiance(p, x, y, u, out)
    elif kernel == 5:
        _hd_radiance(p, x, y, u, out)
    elif kernel == 6:
        _cw_radiance(p, x, y, u, out)
    elif kernel == 7:
        _cd_radiance(p, x, y, u, out)
    elif kernel == 8:
        _cs_radiance(p, x, y, u, out)


@_njit
def _point_expected(kernel, p, x, y, out):
    if kernel == 1:
        _ss_expected(p, x, y, out)
    elif kernel == 2:
        _dof_expected(p, x, y, out)
    elif kernel == 3:
        _mb_expected(p, x, y, out)
    elif kernel == 4:
        _ca_expected(p, x, y, out)
    elif kernel == 5:
        _hd_expected(p, x, y, out)
    elif kernel == 6:
        _cw_expected(p, x, y, out)
    elif kernel == 7:
        _cd_expected(p, x, y, out)
    elif kernel == 8:
        _cs_expected(p, x, y, out)


@_njit
def _point_features(kernel, p, x, y, u, f):
    if kernel == 1:
        _ss_features(p, x, y, u, f)
    elif kernel == 2:
        _dof_features(p, x, y, u, f)
    elif kernel == 3:
        _mb_features(p, x, y, u, f)
    elif kernel == 4:
        _ca_features(p, x, y, u, f)
    elif kernel == 5:
        _hd_features(p, x, y, u, f)
    elif kernel == 6:
        _cw_features(p, x, y, u, f)
    elif kernel == 7:
        _cd_features(p, x, y, u, f)
    elif kernel == 8:
        _cs_features(p, x, y, u, f)


@_njit
def _point_feature_expected(kernel, p, x, y, f):
    if kernel == 1:
        _ss_feature_expected(p, x, y, f)
    elif kernel == 2:
        _dof_feature_expected(p, x, y, f)
    elif kernel == 3:
        _mb_feature_expected(p, x, y, f)
    elif kernel == 4:
        _ca_feature_expected(p, x, y, f)
    elif kernel == 5:
        _hd_feature_expected(p, x, y, f)
    elif kernel == 6:
        _cw_feature_expected(p, x, y, f)
    elif kernel == 7:
        _cd_feature_expected(p, x, y, f)
    elif kernel == 8:
        _cs_feature_expected(p, x, y, f)


@_njit
def _radiance_loop(kernel, p, x, y, u, out):
    for i in range(x.shape[0]):
        _point_radiance(kernel, p, x[i], y[i], u[i], out[i])


@_njit
def _expected_loop(kernel, p, x, y, out):
    for i in range(x.shape[0]):
        _point_expected(kernel, p, x[i], y[i], out[i])


@_njit
def _features_loop(kernel, p, x, y, u, out):
    for i in range(x.shape[0]):
        _point_features(kernel, p, x[i], y[i], u[i], out[i])


@_njit
def _feature_expected_loop(kernel, p, x, y, out):
    for i in range(x.shape[0]):
        _point_feature_expected(kernel, p, x[i], y[i], out[i])


@_njit
def _feature_reference_loop(kernel, p, width, height, q, out):
    """Midpoint rule, q x q points per pixel, of the expected features of scene ``kernel`` (as below)."""
    buf = np.empty(out.shape[2])
    inv = 1.0 / (q * q)
    for j in range(height):
        for i in range(width):
            out[j, i, :] = 0.0
            for b in range(q):
                yy = (j + (b + 0.5) / q) / height
                for a in range(q):
                    xx = (i + (a + 0.5) / q) / width
                    _point_feature_expected(kernel, p, xx, yy, buf)
                    for c in range(buf.shape[0]):
                        out[j, i, c] += buf[c]
            for c in range(buf.shape[0]):
                out[j, i, c] *= inv


@_njit
def _reference_loop(kernel, p, width, height, q, out):
    """Midpoint rule, q x q points per pixel, of the expectation of scene ``kernel``."""
    buf = np.empty(out.shape[2])
    acc = np.empty(out.shape[2])
    inv = 1.0 / (q * q)
    for j in range(height):
        for i in range(width):
            acc[:] = 0.0
            for b in range(q):
                yy = (j + (b + 0.5) / q) / height
                for a in range(q):
                    xx = (i + (a + 0.5) / q) / width
                    _point_expected(kernel, p, xx, yy, buf)
                    for c in range(acc.shape[0]):
                        acc[c] += buf[c]
            for c in range(acc.shape[0]):
                out[j, i, c] = acc[c] * inv
