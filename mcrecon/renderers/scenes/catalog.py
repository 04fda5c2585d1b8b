"""The built-in procedural scenes: the Scene base class, each scene's radiance and exact
expectation.
"""

from __future__ import annotations


import numpy as np

from ...errors import InputError
from .base import _as_xy, _box_square_wave, _box_wave, _checker, _njit, _overlap_fraction, _square_wave, _wave

__all__ = ['SCENES', 'Scene', 'SoftShadowScene', 'DepthOfFieldScene', 'MotionBlurScene', 'CausticScene',
           'HDRScene', 'FlatScene']

# ----------------------------------------------------------------------------
# Scenes
# ----------------------------------------------------------------------------

class Scene:
    """A procedural scene: radiance L(x, y, u) with an exact expectation.

    Attributes
    ----------
    name : str
        Registry name.
    description : str
        One line for ``mcrecon scenes``.
    channels : tuple of str
        ("R", "G", "B").
    n_dims : int
        Random numbers per sample (columns of ``u``).

    Notes
    -----
    ``x`` and ``y`` are normalised film coordinates (x = column / width,
    y = row / height), so a scene renders at any resolution.  ``u`` holds
    independent U[0, 1) numbers.  :meth:`expected` is E_u[L(x, y, u)] in
    closed form.  The built-in scenes are scalar numba functions selected
    by ``_kernel`` (see :func:`_point_radiance`); a user's subclass may
    instead override ``_radiance(x, y, u)`` and ``_expected(x, y)`` with
    vectorised numpy code (``_kernel = 0``).
    """

    name: str = ""
    description: str = ""
    channels: tuple = ("R", "G", "B")
    n_dims: int = 0
    _kernel: int = 0

    def radiance(self, x, y, u) -> np.ndarray:
        """Sample values (N, 3) float64 at normalised positions, ``u`` (N, n_dims) in [0, 1)."""
        x, y = _as_xy(self.name, x, y)
        u = np.asarray(u, dtype=np.float64)
        if u.ndim == 1 and self.n_dims == 1:
            u = u[:, None]
        if u.shape != (x.size, self.n_dims):
            raise InputError(f"scene {self.name!r}", "u",
                             f"shape {u.shape}, expected ({x.size}, {self.n_dims}): one row of "
                             f"{self.n_dims} uniform numbers per point")
        return self._radiance(x, y, np.ascontiguousarray(u))

    def expected(self, x, y) -> np.ndarray:
        """E_u[radiance(x, y, u)] (N, 3) float64, in closed form."""
        x, y = _as_xy(self.name, x, y)
        return self._expected(x, y)

    def _radiance(self, x, y, u):
        if not self._kernel:
            raise NotImplementedError(f"{type(self).__name__} must override _radiance(x, y, u) or set _kernel")
        out = np.empty((x.size, len(self.channels)))
        _radiance_loop(self._kernel, x, y, u, out)
        return out

    def _expected(self, x, y):
        if not self._kernel:
            raise NotImplementedError(f"{type(self).__name__} must override _expected(x, y) or set _kernel")
        out = np.empty((x.size, len(self.channels)))
        _expected_loop(self._kernel, x, y, out)
        return out

    def _reference(self, width, height, quadrature):
        out = np.empty((height, width, len(self.channels)))
        if self._kernel:
            _reference_loop(self._kernel, width, height, quadrature, out)
            return out
        # Pure-numpy scenes: the same midpoint rule, a block of rows at a time.
        q = quadrature
        off = (np.arange(q) + 0.5) / q
        xs = ((np.arange(width)[:, None] + off[None, :]) / width).ravel()
        rows = max(1, (1 << 19) // (width * q * q))
        for j0 in range(0, height, rows):
            j1 = min(height, j0 + rows)
            ys = ((np.arange(j0, j1)[:, None] + off[None, :]) / height).ravel()
            yy, xx = np.meshgrid(ys, xs, indexing="ij")
            vals = self.expected(xx.ravel(), yy.ravel()).reshape(j1 - j0, q, width, q, -1)
            out[j0:j1] = vals.mean(axis=(1, 3))
        return out

    def __repr__(self) -> str:
        return f"{type(self).__name__}()"


# --- soft_shadow -------------------------------------------------------------

_SS_A0 = np.array([0.80, 0.72, 0.55])
_SS_A1 = np.array([0.18, 0.22, 0.32])
_SS_AMBIENT = 0.08
_SS_LIGHT = np.array([1.0, 0.95, 0.85])
_SS_CHECKER = 10.0
# (a, b, c, d): each occluder's shadow core [a, b] x [c, d] in normalised film space.
_SS_OCCLUDERS = np.array([[0.12, 0.48, 0.18, 0.38],
                          [0.30, 0.88, 0.58, 0.70]])


@_njit
def _ss_width(x, y):
    return 0.01 + 0.11 * x


@_njit
def _ss_shade(x, y, vis, out):
    chk = _checker(x, y, _SS_CHECKER)
    for c in range(3):
        albedo = _SS_A0[c] + (_SS_A1[c] - _SS_A0[c]) * chk
        out[c] = albedo * (_SS_AMBIENT + _SS_LIGHT[c] * vis)


@_njit
def _ss_radiance(x, y, u, out):
    w = _ss_width(x, y)
    sx = x + w * (u[0] - 0.5)
    sy = y + w * (u[1] - 0.5)
    vis = 1.0
    for k in range(_SS_OCCLUDERS.shape[0]):
        o = _SS_OCCLUDERS[k]
        if o[0] <= sx <= o[1] and o[2] <= sy <= o[3]:
            vis = 0.0
    _ss_shade(x, y, vis, out)


@_njit
def _ss_expected(x, y, out):
    w = _ss_width(x, y)
    vis = 1.0
    for k in range(_SS_OCCLUDERS.shape[0]):
        o = _SS_OCCLUDERS[k]
        vis -= (_overlap_fraction(x - 0.5 * w, x + 0.5 * w, o[0], o[1])
                * _overlap_fraction(y - 0.5 * w, y + 0.5 * w, o[2], o[3]))
    _ss_shade(x, y, vis, out)


class SoftShadowScene(Scene):
    r"""Checkerboard ground plane under a square area light, two occluders.

    .. math::

        L_c(x, y, u) = a_c(x, y)\,\bigl(k + \ell_c\, V(x, y, u_1, u_2)\bigr)

    with the albedo ``a`` a checkerboard of 10 x 10 squares (colours
    ``A0 = (0.80, 0.72, 0.55)``, ``A1 = (0.18, 0.22, 0.32)``: sharp edges
    that no blur may touch), ambient ``k = 0.08``, light colour
    ``l = (1, 0.95, 0.85)`` and the visibility of a square light whose
    penumbra width ``w(x) = 0.01 + 0.11 x`` grows from left to right (1.3
    to 15 pixels at 128 px):

    .. math::

        V = 1 - \sum_k [x + w(u_1 - \tfrac12) \in [a_k, b_k]]\,
                       [y + w(u_2 - \tfrac12) \in [c_k, d_k]]

    with occluders ``[0.12, 0.48] x [0.18, 0.38]`` and
    ``[0.30, 0.88] x [0.58, 0.70]``.  Their penumbra regions are disjoint
    (the y ranges are 0.2 apart, wider than any penumbra), so at most one
    term is non-zero, and u1, u2 being independent,

    .. math::

        E_u[V] = 1 - \sum_k P_k^x P_k^y,\qquad
        P_k^x = |[x - w/2, x + w/2] \cap [a_k, b_k]| / w

    (likewise in y).  ``n_dims = 2``.
    """

    name = "soft_shadow"
    description = "checkerboard under an area light: sharp albedo edges beside soft penumbrae (2 dims)"
    n_dims = 2
    occluders = _SS_OCCLUDERS
    _kernel = 1

    @staticmethod
    def penumbra_width(x):
        """Penumbra width w(x) = 0.01 + 0.11 x (normalised film units)."""
        return 0.01 + 0.11 * np.asarray(x, dtype=np.float64)


# --- depth_of_field ----------------------------------------------------------

_DOF_RMAX = 1.0 / 16.0
_DOF_A = np.array([0.60, 0.55, 0.55])
_DOF_B = np.array([0.25, -0.15, 0.20])    # checker q(6s) q(6t)
_DOF_D = np.array([0.12, 0.15, 0.10])     # smooth wave w(3 s + phi)
_DOF_PHI = np.array([0.0, 1.0 / 3.0, 2.0 / 3.0])
_DOF_E = np.array([0.08, 0.05, 0.12])     # smooth wave w(2 t + psi)
_DOF_PSI = np.array([0.25, 0.0, 0.5])
_DOF_F = np.array([0.10, 0.12, -0.08])    # fine stripes q(20 s)


@_njit
def _dof_r(x, y):
    return _DOF_RMAX * min(1.0, max(0.0, (abs(y - 0.5) - 0.1) / 0.4))


@_njit
def _dof_radiance(x, y, u, out):
    r = _dof_r(x, y)
    s = x + r * (u[0] - 0.5)
    t = y + r * (u[1] - 0.5)
    qq = _square_wave(6.0 * s) * _square_wave(6.0 * t)
    stripes = _square_wave(20.0 * s)
    for c in range(3):
        out[c] = (_DOF_A[c] + _DOF_B[c] * qq + _DOF_D[c] * _wave(3.0 * s + _DOF_PHI[c])
                  + _DOF_E[c] * _wave(2.0 * t + _DOF_PSI[c]) + _DOF_F[c] * stripes)


@_njit
def _dof_expected(x, y, out):
    r = _dof_r(x, y)
    # u1 and u2 are independent: the average of q(6s) q(6t) is the product of the averages.
    qq = _box_square_wave(x, 6.0, r) * _box_square_wave(y, 6.0, r)
    stripes = _box_square_wave(x, 20.0, r)
    for c in range(3):
        out[c] = (_DOF_A[c] + _DOF_B[c] * qq + _DOF_D[c] * _box_wave(x, 3.0, _DOF_PHI[c], r)
                  + _DOF_E[c] * _box_wave(y, 2.0, _DOF_PSI[c], r) + _DOF_F[c] * stripes)


class DepthOfFieldScene(Scene):
    r"""A colourful textured plane seen through a thin lens with a square aperture.

    .. math::

        L_c(x, y, u) = t_c\bigl(x + R(y)(u_1 - \tfrac12),\; y + R(y)(u_2 - \tfrac12)\bigr)

    The circle of confusion is a square (so the blur is a separable box)
    of side ``R(y) = R_max clip((|y - 1/2| - 0.1) / 0.4, 0, 1)``,
    ``R_max = 1/16`` (8 pixels at 128 px): in focus in the band
    ``|y - 1/2| <= 0.1``, increasingly blurred towards the top and bottom.
    The texture is a sum of separable terms,

    .. math::

        t_c(s, t) = A_c + B_c\,q(6s)\,q(6t) + D_c\,w(3s + \phi_c)
                    + E_c\,w(2t + \psi_c) + F_c\,q(20 s),

    with ``q`` the +-1 square wave of period 1 (sharp edges) and ``w`` a
    smooth sine-like wave of period 1 (``w = 16 f (1/2 - f)`` on
    ``f = frac < 1/2``, mirrored negative on the other half; C^1, zero
    mean).  The box average of a periodic zero-mean ``g(n s + phi)`` over
    ``[z - R/2, z + R/2]`` is ``[G(n(z + R/2) + phi) - G(n(z - R/2) +
    phi)] / (n R)`` with ``G`` its periodic antiderivative: the triangle
    wave ``1/2 - |frac - 1/2|`` for ``q``, the piecewise cubic ``4 f^2 -
    16 f^3 / 3`` (and ``1/3 - `` that, shifted, on the second half) for
    ``w``.  u1 and u2 being independent, the average of a product of a
    function of s and one of t is the product of their averages, so
    E_u[L] is exact.  ``n_dims = 2``.
    """

    name = "depth_of_field"
    description = "thin lens, square aperture: in focus in the middle, 8 px blur at top/bottom at 128 px (2 dims)"
    n_dims = 2
    r_max = _DOF_RMAX
    _kernel = 2

    @staticmethod
    def blur_width(y):
        """Side R(y) of the square circle of confusion (normalised film units)."""
        return _DOF_RMAX * np.clip((np.abs(np.asarray(y, dtype=np.float64) - 0.5) - 0.1) / 0.4, 0.0, 1.0)


# --- motion_blur -------------------------------------------------------------

_MB_BACKGROUND = np.array([0.30, 0.32, 0.36])
# x0, y0, width, height, vx, vy (per shutter interval), then the colour.
_MB_OBJECTS = np.array([
    [0.05, 0.08, 0.18, 0.18, 0.35, 0.00, 0.95, 0.20, 0.15],    # red square, medium speed
    [0.85, 0.35, 0.04, 0.22, -0.50, 0.00, 0.20, 0.90, 0.25],   # green bar, fast, leftwards
    [0.05, 0.38, 0.10, 0.15, 0.02, 0.00, 0.95, 0.85, 0.20],    # yellow box, almost still
    [0.10, 0.65, 0.12, 0.12, 0.25, 0.15, 0.20, 0.35, 0.95],    # blue square, diagonal
    [0.55, 0.70, 0.08, 0.08, 0.35, 0.00, 0.95, 0.95, 0.95],    # small white square, horizontal
])


def _mb_swept_boxes():
    o = _MB_OBJECTS
    x0, y0, w, h, vx, vy = (o[:, k] for k in range(6))
    return np.stack([np.minimum(x0, x0 + vx), np.maximum(x0, x0 + vx) + w,
                     np.minimum(y0, y0 + vy), np.maximum(y0, y0 + vy) + h], axis=1)


def _mb_check_disjoint():
    boxes = _mb_swept_boxes()
    for i in range(len(boxes)):
        for j in range(i):
            a, b = boxes[i], boxes[j]
            if a[0] < b[1] and b[0] < a[1] and a[2] < b[3] and b[2] < a[3]:
                raise AssertionError(f"motion_blur objects {j} and {i} overlap in space-time")


# The closed form below assumes no two objects ever cover the same point.
_mb_check_disjoint()


@_njit
def _mb_background(x, y, out):
    g = 0.55 + 0.45 * _checker(x, y, 16.0)
    for c in range(3):
        out[c] = _MB_BACKGROUND[c] * g


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
def _mb_radiance(x, y, u, out):
    t = u[0]
    _mb_background(x, y, out)
    for k in range(_MB_OBJECTS.shape[0]):
        o = _MB_OBJECTS[k]
        ox = o[0] + o[4] * t
        oy = o[1] + o[5] * t
        if ox <= x < ox + o[2] and oy <= y < oy + o[3]:
            for c in range(3):
                out[c] = o[6 + c]


@_njit
def _mb_expected(x, y, out):
    _mb_background(x, y, out)
    b0, b1, b2 = out[0], out[1], out[2]
    for k in range(_MB_OBJECTS.shape[0]):
        o = _MB_OBJECTS[k]
        lx, hx = _mb_interval(x, o[0], o[2], o[4])
        ly, hy = _mb_interval(y, o[1], o[3], o[5])
        frac = min(hx, hy, 1.0) - max(lx, ly, 0.0)
        if frac > 0.0:
            out[0] += frac * (o[6] - b0)
            out[1] += frac * (o[7] - b1)
            out[2] += frac * (o[8] - b2)


class MotionBlurScene(Scene):
    r"""Coloured boxes moving during the shutter interval over a static checkerboard.

    .. math::

        L(x, y, t) = b(x, y) + \sum_k [\,(x, y) \in O_k(t)\,]\,(c_k - b(x, y))

    with ``t = u_1`` the time in the shutter interval [0, 1), the object
    ``O_k(t) = [x_k + v^x_k t, x_k + v^x_k t + w_k) x [y_k + v^y_k t,
    y_k + v^y_k t + h_k)`` (five boxes: fast, slow, almost still, diagonal)
    and the background ``b = (0.30, 0.32, 0.36) (0.55 + 0.45
    checker_16(x, y))``.  The set of times at which (x, y) is inside O_k
    is an interval ``T_k``, the intersection of the x- and y-constraint
    intervals (for v^x > 0: ``t in ((x - x_k - w_k) / v^x, (x - x_k) /
    v^x]``; for v^x = 0 all or no t).  The objects' swept boxes are
    disjoint (checked at import), so at most one object covers a point at
    any time and

    .. math::

        E_t[L] = b + \sum_k |T_k(x, y) \cap [0, 1)|\,(c_k - b).

    ``n_dims = 1``.
    """

    name = "motion_blur"
    description = "coloured boxes moving at different speeds over a sharp static checkerboard (1 dim)"
    n_dims = 1
    objects = _MB_OBJECTS
    _kernel = 3

    @staticmethod
    def swept_boxes() -> np.ndarray:
        """(K, 4) array of [x_min, x_max, y_min, y_max] covered by each object during the shutter."""
        return _mb_swept_boxes()


# --- caustic -----------------------------------------------------------------

_CA_P = 0.03
_CA_CX, _CA_CY = 0.5, 0.45
_CA_COLOUR = np.array([1.0, 0.85, 0.5])
_CA_GLOW = 0.02
_CA_HALF_WIDTH = 0.02
_CA_TABLE_TOP = 0.85
_CA_TABLE = np.array([0.05, 0.035, 0.02])


@_njit
def _ca_parts(x, y):
    """(caustic intensity C / colour, table background g / colour) at one point."""
    dx = x - _CA_CX
    dy = y - _CA_CY
    r = np.sqrt(dx * dx + dy * dy)
    cos_t = dx / r if r > 0.0 else 1.0        # any direction at the centre
    r0 = 0.28 * (1.0 - 0.3 * cos_t)
    z = (r - r0) / _CA_HALF_WIDTH
    bump = (1.0 - z * z) ** 2 if abs(z) < 1.0 else 0.0
    inner = max(0.0, 1.0 - r / r0) ** 2
    caustic = (3.0 + 1.5 * cos_t) * bump + _CA_GLOW * inner
    table = 0.0
    if y > _CA_TABLE_TOP:
        table = (y - _CA_TABLE_TOP) / (1.0 - _CA_TABLE_TOP) * (1.0 + 0.5 * np.sin(6.0 * np.pi * x))
    return caustic, table


@_njit
def _ca_radiance(x, y, u, out):
    caustic, table = _ca_parts(x, y)
    hit = caustic / _CA_P if u[0] < _CA_P else 0.0
    noise = 2.0 * u[1]
    for c in range(3):
        out[c] = _CA_TABLE[c] * table * noise + _CA_COLOUR[c] * hit


@_njit
def _ca_expected(x, y, out):
    caustic, table = _ca_parts(x, y)
    for c in range(3):
        out[c] = _CA_TABLE[c] * table + _CA_COLOUR[c] * caustic


class CausticScene(Scene):
    r"""A caustic ring sampled with probability 3 %: 97 % zero samples, rare huge ones.

    .. math::

        L_c(x, y, u) = T_c\, g(x, y)\, 2u_2 + [u_1 < p]\; k_c\, C(x, y) / p,\qquad p = 0.03,

    so ``E_u[L_c] = T_c g + k_c C``.  The caustic is a curved ring around
    ``(0.5, 0.45)``: in polar coordinates ``(r, theta)`` about that centre
    the ring radius is ``r0(theta) = 0.28 (1 - 0.3 cos theta)``,
    ``z = (r - r0) / 0.02``,

    .. math::

        C = (3 + 1.5 \cos\theta)\,\beta(z) + 0.02\,\max(0, 1 - r / r_0)^2,
        \qquad \beta(z) = (1 - z^2)^2 [|z| < 1],

    a C^1 ring of peak 1.5 .. 4.5 (colour ``k = (1, 0.85, 0.5)``) with a
    faint glow inside.  The background is a dim table top,
    ``g = (y - 0.85)/0.15 (1 + 0.5 sin 6 pi x)`` for y > 0.85 (colour
    ``T = (0.05, 0.035, 0.02)``, uniform multiplicative noise), exactly 0
    elsewhere.  Above the table a sample is exactly zero with probability
    0.97 inside the ring and 1 outside it; a non-zero one is worth C/p (up
    to 150).  ``n_dims = 2``.
    """

    name = "caustic"
    description = "caustic ring hit with probability 3%: 97% zero samples and rare huge ones (2 dims)"
    n_dims = 2
    p = _CA_P
    centre = (_CA_CX, _CA_CY)
    table_top = _CA_TABLE_TOP
    _kernel = 4


# --- hdr ---------------------------------------------------------------------

_HD_CX, _HD_CY, _HD_R = 0.3, 0.3, 0.14
_HD_POWER = 500.0
_HD_EMIT = np.array([1.0, 0.9, 0.75])
_HD_MID_LEFT = 0.62
_HD_MID = np.array([1.0, 0.95, 0.9])
_HD_DIM = np.array([1.0, 0.8, 0.6])
_HD_OCC = (0.12, 0.42, 0.62, 0.78)


@_njit
def _hd_base(x, y):
    """(region, base value): region 0 emitter, 1 mid panel, 2 dim surface."""
    rho2 = ((x - _HD_CX) ** 2 + (y - _HD_CY) ** 2) / (_HD_R * _HD_R)
    if rho2 < 1.0:
        return 0, _HD_POWER * (1.0 - 0.2 * rho2)
    if x >= _HD_MID_LEFT:
        return 1, 0.5 * (0.8 + 0.2 * _square_wave(8.0 * y))
    return 2, 1e-3 * (0.5 + 0.5 * _checker(x, y, 12.0))


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
def _hd_radiance(x, y, u, out):
    region, base = _hd_base(x, y)
    w = 0.02 + 0.1 * x
    sx = x + w * (u[1] - 0.5)
    sy = y + w * (u[2] - 0.5)
    blocked = _HD_OCC[0] <= sx <= _HD_OCC[1] and _HD_OCC[2] <= sy <= _HD_OCC[3]
    _hd_write(region, base, 0.5 + u[0], 0.0 if blocked else 1.0, out)


@_njit
def _hd_expected(x, y, out):
    region, base = _hd_base(x, y)
    w = 0.02 + 0.1 * x
    vis = 1.0 - (_overlap_fraction(x - 0.5 * w, x + 0.5 * w, _HD_OCC[0], _HD_OCC[1])
                 * _overlap_fraction(y - 0.5 * w, y + 0.5 * w, _HD_OCC[2], _HD_OCC[3]))
    _hd_write(region, base, 1.0, vis, out)


class HDRScene(Scene):
    r"""A bright emitter (~500) beside dim surfaces (1e-3 .. 1e-2) and a mid-grey panel.

    Three regions, in priority order:

    * emitter, the disc ``rho = |(x, y) - (0.3, 0.3)| / 0.14 < 1``:
      ``L_c = 500 e_c (1 - 0.2 rho^2)(1/2 + u_1)``, ``e = (1, 0.9, 0.75)``;
      ``E = 500 e_c (1 - 0.2 rho^2)``.  Pixels on its rim see ~500 or
      ~1e-3: bimodal.
    * mid panel, ``x >= 0.62``: ``L_c = 0.5 m_c (0.8 + 0.2 q(8 y))
      (1/2 + u_1)``, ``m = (1, 0.95, 0.9)``, q the +-1 square wave.
    * dim surfaces elsewhere: ``L_c = 1e-3 d_c (1/2 + checker_12/2)
      (1 + 9 V)``, ``d = (1, 0.8, 0.6)``, with V the soft-shadow visibility
      of :class:`SoftShadowScene` for the occluder ``[0.12, 0.42] x
      [0.62, 0.78]``, penumbra width ``w = 0.02 + 0.1 x`` and light sample
      ``(u_2, u_3)``, so ``E = 1e-3 d_c (1/2 + checker/2)(1 + 9 (1 -
      P^x P^y))``.

    Expected values range from 3e-4 to 500.  ``n_dims = 3``.
    """

    name = "hdr"
    description = "bright emitter (~500) beside dim surfaces (1e-3..1e-2) and a mid-grey panel (3 dims)"
    n_dims = 3
    emitter = (_HD_CX, _HD_CY, _HD_R)
    _kernel = 5


# --- drivers -----------------------------------------------------------------
# One loop for all scenes, selecting the scalar functions by an integer id:
# numba's on-disk cache cannot store loops that take jitted functions as
# arguments (it fails to pickle the function type), and the id test is
# loop-invariant (hoisted by the compiler, or a perfectly predicted branch).

@_njit
def _point_radiance(kernel, x, y, u, out):
    if kernel == 1:
        _ss_radiance(x, y, u, out)
    elif kernel == 2:
        _dof_radiance(x, y, u, out)
    elif kernel == 3:
        _mb_radiance(x, y, u, out)
    elif kernel == 4:
        _ca_radiance(x, y, u, out)
    elif kernel == 5:
        _hd_radiance(x, y, u, out)


@_njit
def _point_expected(kernel, x, y, out):
    if kernel == 1:
        _ss_expected(x, y, out)
    elif kernel == 2:
        _dof_expected(x, y, out)
    elif kernel == 3:
        _mb_expected(x, y, out)
    elif kernel == 4:
        _ca_expected(x, y, out)
    elif kernel == 5:
        _hd_expected(x, y, out)


@_njit
def _radiance_loop(kernel, x, y, u, out):
    for i in range(x.shape[0]):
        _point_radiance(kernel, x[i], y[i], u[i], out[i])


@_njit
def _expected_loop(kernel, x, y, out):
    for i in range(x.shape[0]):
        _point_expected(kernel, x[i], y[i], out[i])


@_njit
def _reference_loop(kernel, width, height, q, out):
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
                    _point_expected(kernel, xx, yy, buf)
                    for c in range(acc.shape[0]):
                        acc[c] += buf[c]
            for c in range(acc.shape[0]):
                out[j, i, c] = acc[c] * inv


# --- flat --------------------------------------------------------------------

class FlatScene(Scene):
    r"""Flat noise: ``L_c(x, y, u) = u_c``, i.e. 0.5 plus uniform noise of half-width 0.5.

    ``E = (0.5, 0.5, 0.5)`` everywhere, per-sample variance 1/12 per
    channel, channels independent.  ``n_dims = 3``.
    """

    name = "flat"
    description = "constant 0.5 with uniform noise in [0, 1) per channel (3 dims)"
    n_dims = 3

    def _radiance(self, x, y, u):
        return u.copy()

    def _expected(self, x, y):
        return np.full((x.size, 3), 0.5)

    def _reference(self, width, height, quadrature):
        return np.full((height, width, 3), 0.5)


#: Registry: scene name -> class (calling it gives a Scene).
SCENES: dict = {cls.name: cls for cls in (SoftShadowScene, DepthOfFieldScene, MotionBlurScene,
                                         CausticScene, HDRScene, FlatScene)}
