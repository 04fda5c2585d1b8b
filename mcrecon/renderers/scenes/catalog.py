"""The built-in procedural scenes: the Scene base class and each scene's class (its formulas); the
compiled kernels are in :mod:`.kernels` (the older scenes) and :mod:`.textured` (the textured ones).
"""

from __future__ import annotations


import numpy as np

from ...errors import InputError
from .base import _as_xy
# the constants are re-exported: tests and users read them as catalog attributes
from .kernels import (_CA_CX, _CA_CY, _CA_P, _CA_TABLE_TOP, _DOF_RMAX, _HD_CX, _HD_CY, _HD_R,  # noqa: F401
                      _MB_BACKGROUND, _MB_OBJECTS, _SS_A0, _SS_A1, _SS_AMBIENT, _SS_LIGHT, _SS_OCCLUDERS,
                      _expected_loop, _feature_expected_loop, _feature_reference_loop, _features_loop,
                      _mb_swept_boxes, _radiance_loop, _reference_loop)
from .textured import _CD_APERTURE, _CD_FOCUS, _CD_PLANES, _CS_OCC, _CS_P, _CW_OCC
from .params import PARAMS, check_params, pack

__all__ = ['SCENES', 'FEATURE_LAYOUT', 'Scene', 'SoftShadowScene', 'DepthOfFieldScene', 'MotionBlurScene',
           'CausticScene', 'HDRScene', 'FlatScene', 'CheckerWallScene', 'CheckerSpotScene', 'CheckerDofScene']

#: The built-in scenes' per-sample features of the primary hit, in the order of the kernels' 7-float
#: feature vector: name -> components (mcrecon.core.features.CANONICAL_FEATURES).
FEATURE_LAYOUT = {"albedo": 3, "normal": 3, "depth": 1}
_N_FEATURES = 7


def split_features(arr) -> dict:
    """``{name: view}`` of a (..., 7) feature array in :data:`FEATURE_LAYOUT` order (depth keeps a last axis of 1)."""
    out, k = {}, 0
    for name, n in FEATURE_LAYOUT.items():
        out[name] = arr[..., k:k + n]
        k += n
    return out

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

    A built-in scene takes parameters (:data:`.params.PARAMS`: light size and
    power, texture scale and contrast, the lens, the motion, ``exposure``...),
    as keywords or a ``params`` dict; ``params`` holds those that differ
    from the defaults, so a default scene has ``params == {}`` and renders
    exactly as the constants say.  The class attributes that describe a
    scene's geometry (``occluders``, ``emitter``, ``planes``...) and its
    static helpers are those of the default parameters.

    Features (``feature_names``, the built-in scenes: ``albedo``, ``normal``,
    ``depth``, see :data:`FEATURE_LAYOUT` and ``docs/scenes.md``) are those
    of the primary hit of the same sample: a function of the same ``(x, y,
    u)`` as its colour, so that asking for them draws no extra random
    numbers and leaves the colour unchanged.  :meth:`expected_features` is
    their exact expectation over ``u``.  A numpy subclass with features
    overrides ``_features(x, y, u)`` and ``_expected_features(x, y)``,
    each returning an (N, 7) array in :data:`FEATURE_LAYOUT` order.
    """

    name: str = ""
    description: str = ""
    channels: tuple = ("R", "G", "B")
    n_dims: int = 0
    #: Names of the per-sample features :meth:`features` gives (empty: the scene has none).
    feature_names: tuple = ()
    #: Whether :class:`SceneRenderer` and :func:`write_scene_log` send the features unless told otherwise.
    features_default: bool = False
    _kernel: int = 0
    #: The parameters that differ from the defaults (a user's subclass that skips ``__init__`` has none).
    params: dict = {}
    _prm = np.empty(0)
    _exposure = 1.0

    def __init__(self, params: dict | None = None, **kwargs):
        where = f"scene {self.name!r}"
        if params is not None and not isinstance(params, dict):
            raise InputError(where, "params", f"{type(params).__name__}, expected a dict of parameter values")
        given = {**(params or {}), **kwargs}
        if self.name in PARAMS and type(self) is SCENES.get(self.name):
            self.params = check_params(self.name, given)
            self._prm = pack(self.name, self.params)
        else:  # a user's own scene: no parameters
            if given:
                raise InputError(where, f"params.{sorted(given)[0]}", "this scene takes no parameters")
            self.params = {}
            self._prm = np.empty(0)
        self._exposure = self.params.get("exposure", 1.0)

    @property
    def param_key(self) -> tuple:
        """``params`` as a sorted tuple of (name, value) pairs (hashable: a cache key)."""
        return tuple(sorted(self.params.items()))

    def _expose(self, out):
        """``out`` times the ``exposure`` parameter, in place (untouched at the default 1)."""
        if self._exposure != 1.0:
            out *= self._exposure
        return out

    def radiance(self, x, y, u) -> np.ndarray:
        """Sample values (N, 3) float64 at normalised positions, ``u`` (N, n_dims) in [0, 1)."""
        x, y = _as_xy(self.name, x, y)
        return self._expose(self._radiance(x, y, self._check_u(x, u)))

    def expected(self, x, y) -> np.ndarray:
        """E_u[radiance(x, y, u)] (N, 3) float64, in closed form."""
        x, y = _as_xy(self.name, x, y)
        return self._expose(self._expected(x, y))

    def _radiance(self, x, y, u):
        return self._run_kernel(_radiance_loop, "_radiance(x, y, u)", len(self.channels), x, y, u)

    def _expected(self, x, y):
        return self._run_kernel(_expected_loop, "_expected(x, y)", len(self.channels), x, y)

    def _run_kernel(self, loop, method: str, columns: int, x, *args):
        """``loop`` over the points of this scene's compiled kernel into a fresh (N, columns) array; a scene
        without one (``_kernel = 0``) must override ``method``."""
        if not self._kernel:
            raise NotImplementedError(f"{type(self).__name__} must override {method} or set _kernel")
        out = np.empty((x.size, columns))
        loop(self._kernel, self._prm, x, *args, out)
        return out

    def features(self, x, y, u) -> dict:
        """Per-sample features of the primary hit: ``{"albedo": (N, 3), "normal": (N, 3), "depth": (N, 1)}``.

        The same arguments as :meth:`radiance`; row i of each array belongs to
        the sample whose colour is row i of ``radiance(x, y, u)``.

        Raises
        ------
        InputError
            For a scene without features (``feature_names`` empty).
        """
        self._check_has_features("features")
        x, y = _as_xy(self.name, x, y)
        u = self._check_u(x, u)
        return {k: np.ascontiguousarray(v) for k, v in split_features(self._features(x, y, u)).items()}

    def expected_features(self, x, y) -> dict:
        """E_u of :meth:`features` at each point, in closed form (same dict layout)."""
        self._check_has_features("expected_features")
        x, y = _as_xy(self.name, x, y)
        return {k: np.ascontiguousarray(v) for k, v in split_features(self._expected_features(x, y)).items()}

    def _check_has_features(self, what):
        if not self.feature_names:
            raise InputError(f"scene {self.name!r}", "features",
                             f"{what}: this scene has no per-sample features; the built-in scenes do")

    def _check_u(self, x, u):
        u = np.asarray(u, dtype=np.float64)
        if u.ndim == 1 and self.n_dims == 1:
            u = u[:, None]
        if u.shape != (x.size, self.n_dims):
            raise InputError(f"scene {self.name!r}", "u",
                             f"shape {u.shape}, expected ({x.size}, {self.n_dims}): one row of "
                             f"{self.n_dims} uniform numbers per point")
        return np.ascontiguousarray(u)

    def _features(self, x, y, u):
        return self._run_kernel(_features_loop, "_features(x, y, u)", _N_FEATURES, x, y, u)

    def _expected_features(self, x, y):
        return self._run_kernel(_feature_expected_loop, "_expected_features(x, y)", _N_FEATURES, x, y)

    def _reference(self, width, height, quadrature):
        """(H, W, C) pixel averages of the expected colour before ``exposure`` (the caller applies it)."""
        out = np.empty((height, width, len(self.channels)))
        if self._kernel:
            _reference_loop(self._kernel, self._prm, width, height, quadrature, out)
            return out
        return self._midpoint(lambda x, y: self._expected(*_as_xy(self.name, x, y)), out, width, height,
                              quadrature)

    def _feature_reference(self, width, height, quadrature):
        """(H, W, 7) pixel averages of :meth:`_expected_features` (midpoint rule, as :meth:`_reference`)."""
        out = np.empty((height, width, _N_FEATURES))
        if self._kernel:
            _feature_reference_loop(self._kernel, self._prm, width, height, quadrature, out)
            return out
        return self._midpoint(lambda x, y: self._expected_features(*_as_xy(self.name, x, y)), out, width,
                              height, quadrature)

    @staticmethod
    def _midpoint(expected, out, width, height, quadrature):
        # Pure-numpy scenes: the same midpoint rule, a block of rows at a time.
        q = quadrature
        off = (np.arange(q) + 0.5) / q
        xs = ((np.arange(width)[:, None] + off[None, :]) / width).ravel()
        rows = max(1, (1 << 19) // (width * q * q))
        for j0 in range(0, height, rows):
            j1 = min(height, j0 + rows)
            ys = ((np.arange(j0, j1)[:, None] + off[None, :]) / height).ravel()
            yy, xx = np.meshgrid(ys, xs, indexing="ij")
            vals = expected(xx.ravel(), yy.ravel()).reshape(j1 - j0, q, width, q, -1)
            out[j0:j1] = vals.mean(axis=(1, 3))
        return out

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.params!r})" if self.params else f"{type(self).__name__}()"


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
    feature_names = tuple(FEATURE_LAYOUT)  # opt-in: features_default False keeps old outputs
    occluders = _SS_OCCLUDERS
    _kernel = 1

    @staticmethod
    def penumbra_width(x):
        """Penumbra width w(x) = 0.01 + 0.11 x (normalised film units)."""
        return 0.01 + 0.11 * np.asarray(x, dtype=np.float64)


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
    feature_names = tuple(FEATURE_LAYOUT)  # opt-in: features_default False keeps old outputs
    r_max = _DOF_RMAX
    _kernel = 2

    @staticmethod
    def blur_width(y):
        """Side R(y) of the square circle of confusion (normalised film units)."""
        return _DOF_RMAX * np.clip((np.abs(np.asarray(y, dtype=np.float64) - 0.5) - 0.1) / 0.4, 0.0, 1.0)


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
    feature_names = tuple(FEATURE_LAYOUT)  # opt-in: features_default False keeps old outputs
    objects = _MB_OBJECTS
    _kernel = 3

    @staticmethod
    def swept_boxes() -> np.ndarray:
        """(K, 4) array of [x_min, x_max, y_min, y_max] covered by each object during the shutter."""
        return _mb_swept_boxes()


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
    feature_names = tuple(FEATURE_LAYOUT)  # opt-in: features_default False keeps old outputs
    p = _CA_P
    centre = (_CA_CX, _CA_CY)
    table_top = _CA_TABLE_TOP
    _kernel = 4


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
    feature_names = tuple(FEATURE_LAYOUT)  # opt-in: features_default False keeps old outputs
    emitter = (_HD_CX, _HD_CY, _HD_R)
    _kernel = 5


# --- checker_wall, checker_dof (kernels in .textured) ---------------------------

class CheckerWallScene(Scene):
    r"""A checkerboard-textured wall under an area light's soft shadow and a sky: texture the albedo explains.

    .. math::

        L_c(x, y, u) = a_c(x, y)\,\bigl(2 k u_3 + \ell_c\, V(x, y, u_1, u_2)\bigr)

    The albedo ``a`` is a checkerboard of squares 1/8 (16 px at 128 px),
    ``(0.85, 0.82, 0.75)`` / ``(0.06, 0.07, 0.10)``, except in the quadrant
    ``x >= 1/2, y >= 1/2``: squares 1/32 (4 px), ``(0.92, 0.38, 0.22)`` /
    ``(0.18, 0.52, 0.90)``.  The sky term ``k = 0.25`` is estimated with one
    uniform number (``2 k u3``, mean ``k``), so every pixel is noisy; the
    light ``l = (0.80, 0.77, 0.72)`` is a square area light whose visibility
    ``V`` is that of :class:`SoftShadowScene` for one occluder with shadow
    core ``[0.22, 0.70] x [0.28, 0.68]`` and penumbra ``w(x) = 0.02 + 0.10 x``
    (2.6 to 15 px at 128 px).  The albedo being deterministic,

    .. math::

        E_u[L_c] = a_c\,\bigl(k + \ell_c (1 - P^x P^y)\bigr)

    with ``P^x``, ``P^y`` the overlap fractions of :class:`SoftShadowScene`.
    Features: ``albedo = a`` (noise-free), ``normal = (0, 0, -1)``, ``depth = 2``.
    ``n_dims = 3``.
    """

    name = "checker_wall"
    description = "checkerboard wall (16 px and 4 px squares) under a soft shadow and a noisy sky (3 dims)"
    n_dims = 3
    feature_names = tuple(FEATURE_LAYOUT)
    features_default = True
    occluder = _CW_OCC
    _kernel = 6

    @staticmethod
    def penumbra_width(x):
        """Penumbra width w(x) = 0.02 + 0.10 x (normalised film units)."""
        return 0.02 + 0.10 * np.asarray(x, dtype=np.float64)


class CheckerSpotScene(Scene):
    r"""checker_wall's textured wall lit by a small light that a sample finds rarely: high variance.

    .. math::

        L_c(x, y, u) = a_c(x, y)\,\Bigl(2 k u_4 + \ell_c\, f(x, y)\,
                       \frac{[u_1 < p]}{p}\, V(x, y, u_2, u_3)\Bigr),\qquad p = 0.05

    The albedo ``a`` is :class:`CheckerWallScene`'s (same features); the sky
    ``k = 0.04``; the small light ``l = (0.95, 0.85, 0.65)`` with the smooth
    spot falloff ``f = 1 / (1 + ((x - 0.68)^2 + (y - 0.30)^2) / 0.09)`` is
    reached by one sample in 20, worth ``1/p = 20`` times its share (values
    up to ~18 beside a mean below 1); its shadow has core ``[0.30, 0.56] x
    [0.46, 0.82]`` and a narrow penumbra ``0.004 + 0.012 x`` (0.5 to 2 px at
    128 px).  ``u1`` being independent of the light position,

    .. math::

        E_u[L_c] = a_c\,\bigl(k + \ell_c f (1 - P^x P^y)\bigr).

    ``n_dims = 4``.
    """

    name = "checker_spot"
    description = "checker_wall's texture under a small light found 1 sample in 20: high variance (4 dims)"
    n_dims = 4
    feature_names = tuple(FEATURE_LAYOUT)
    features_default = True
    p = _CS_P
    occluder = _CS_OCC
    _kernel = 8


class CheckerDofScene(Scene):
    r"""Three checkerboard-textured planes at different depths through a thin lens (depth of field).

    A ray from film point ``(x, y)`` through the square lens aperture at
    offset ``(u1 - 1/2, u2 - 1/2)`` meets the plane at depth ``z`` at the
    projected film point ``(x + R(z)(u1 - 1/2), y + R(z)(u2 - 1/2))``,
    ``R(z) = a (1/z - 1/z_f)``, ``a = 1/8``, focus ``z_f = 2``.  Front to back:

    * a near card, ``z = 1`` (``R = 1/16``: 8 px blur at 128 px), rectangle
      ``[2/32, 15/32] x [14/32, 30/32]``, squares 1/16;
    * a card in focus, ``z = 2``, ``[13/32, 30/32] x [2/32, 17/32]``, squares
      1/32 (4 px), partly behind the near card;
    * a wall, ``z = 3`` (``R = -1/48``, 2.7 px), everywhere, squares 1/8.

    The sample sees the first plane whose rectangle holds its projected
    point; colour = albedo x ``E_k (1/2 + u3)`` (irradiance ``E`` = 1.0, 1.1,
    0.9; u3 an independent light sample).  Each hit event is a box in
    ``(u1, u2)`` minus the boxes of the planes in front; expanded by
    inclusion-exclusion into signed boxes, the checker ``(A0 + A1)/2 -
    (A1 - A0)/2 q(n s/2) q(n t/2)`` integrates over each exactly (products
    of triangle-wave differences), so E_u[L] and the features' expectations
    are exact.  Features: the hit plane's albedo, its normal (near card
    ``(0, -0.6, -0.8)``, card in focus ``(-0.6, 0, -0.8)``, wall ``(0, 0,
    -1)``) and depth ``z``: noisy and blurred where the colour is.
    ``n_dims = 3``.
    """

    name = "checker_dof"
    description = "checkered cards at 3 depths through a thin lens: features blurred and noisy off focus (3 dims)"
    n_dims = 3
    feature_names = tuple(FEATURE_LAYOUT)
    features_default = True
    planes = _CD_PLANES
    aperture = _CD_APERTURE
    focus = _CD_FOCUS
    _kernel = 7


# --- flat --------------------------------------------------------------------

class FlatScene(Scene):
    r"""Flat noise: ``L_c(x, y, u) = u_c``, i.e. 0.5 plus uniform noise of half-width 0.5.

    ``E = (0.5, 0.5, 0.5)`` everywhere, per-sample variance 1/12 per
    channel, channels independent.  ``n_dims = 3``.
    """

    name = "flat"
    description = "constant 0.5 with uniform noise in [0, 1) per channel (3 dims)"
    n_dims = 3
    feature_names = tuple(FEATURE_LAYOUT)  # opt-in: features_default False keeps old outputs

    def _radiance(self, x, y, u):
        return u.copy()

    def _expected(self, x, y):
        return np.full((x.size, 3), 0.5)

    def _reference(self, width, height, quadrature):
        return np.full((height, width, 3), 0.5)

    def _features(self, x, y, u):
        # a grey card facing the camera at depth 1: colour = albedo x (2 u_c), mean 1
        return np.tile(_FLAT_FEATURES, (x.size, 1))

    def _expected_features(self, x, y):
        return np.tile(_FLAT_FEATURES, (x.size, 1))

    def _feature_reference(self, width, height, quadrature):
        return np.tile(_FLAT_FEATURES, (height, width, 1))


_FLAT_FEATURES = np.array([0.5, 0.5, 0.5, 0.0, 0.0, -1.0, 1.0])


#: Registry: scene name -> class (calling it gives a Scene).
SCENES: dict = {cls.name: cls for cls in (SoftShadowScene, DepthOfFieldScene, MotionBlurScene,
                                         CausticScene, HDRScene, FlatScene, CheckerWallScene, CheckerSpotScene,
                                         CheckerDofScene)}