"""The built-in scenes' parameters: names, defaults, valid ranges, and the float64 array the kernels read.

Each scene family has a few parameters (light size and power, texture scale
and contrast, the hdr emitter's power, the lens aperture and focus, the
motion speed, the caustic's power and hit probability...).  A scene keeps
its parameters as a dict and hands its kernels one flat float64 array
(:func:`pack`), laid out as the comments in :mod:`.kernels` and
:mod:`.textured` say.  With every parameter at its default the array holds
the module constants themselves (a factor of 1 is never applied), so the
default scenes' samples and references are bit for bit those of the
constant kernels.  Every parameter keeps the expectation exact: each one
only changes a number inside a closed form.

``exposure`` (every scene) multiplies the colour (not the features):
with ``relMSE``'s ``eps`` it moves a scene along the dim-to-bright axis.
"""

from __future__ import annotations

import math

import numpy as np

from ...errors import InputError
from . import kernels as K
from . import textured as T

#: name -> (default, low, high, what it does); every scene also has ``exposure``.
_EXPOSURE = {"exposure": (1.0, 1e-4, 1e4, "multiplies the colour (not the features)")}

PARAMS: dict[str, dict[str, tuple]] = {
    "soft_shadow": {
        "light_power": (1.0, 0.0, 100.0, "multiplies the area light's colour"),
        "light_size": (1.0, 1e-3, 1.6, "multiplies the penumbra width 0.01 + 0.11 x (the light's size)"),
        "ambient": (K._SS_AMBIENT, 0.0, 10.0, "ambient irradiance k"),
        "texture_scale": (1.0, 0.1, 20.0, "multiplies the checkerboard's squares per unit (10)"),
        "contrast": (1.0, 0.0, 1.5, "scales the two albedos about their mean"),
        "occluder_shift": (0.0, -0.1, 0.1, "moves both occluders along x"),
    },
    "depth_of_field": {
        "aperture": (1.0, 0.0, 4.0, "multiplies the largest blur R_max = 1/16"),
        "focus_band": (K._DOF_BAND, 0.0, 0.45, "half-height of the band in focus about y = 1/2"),
        "texture_scale": (1.0, 0.1, 10.0, "multiplies every texture frequency"),
        "contrast": (1.0, 0.0, 1.05, "scales the texture's terms about its mean (colour stays positive)"),
    },
    "motion_blur": {
        "speed": (1.0, 0.0, 1.4, "multiplies every object's velocity (swept boxes must stay disjoint)"),
        "texture_scale": (1.0, 0.1, 10.0, "multiplies the background checker's squares per unit (16)"),
    },
    "caustic": {
        "hit_probability": (K._CA_P, 1e-4, 1.0, "probability p that a sample finds the caustic"),
        "power": (1.0, 0.0, 1e4, "multiplies the caustic's colour"),
        "ring_width": (1.0, 0.05, 10.0, "multiplies the ring's half-width 0.02"),
        "ring_radius": (K._CA_RADIUS, 0.05, 0.4, "the ring's mean radius"),
    },
    "hdr": {
        "power": (K._HD_POWER, 0.0, 1e6, "the emitter's radiance scale (500)"),
        "emitter_radius": (K._HD_R, 0.01, 0.28, "the emitter disc's radius"),
        "dim_level": (K._HD_DIM_LEVEL, 1e-6, 1.0, "the dim surfaces' radiance scale"),
        "light_size": (1.0, 1e-3, 4.0, "multiplies the dim surfaces' penumbra width 0.02 + 0.1 x"),
        "texture_scale": (1.0, 0.1, 10.0, "multiplies the dim checker's squares per unit (12)"),
    },
    "flat": {},
    "checker_wall": {
        "texture_scale": (1.0, 0.1, 8.0, "multiplies both checkers' squares per unit (8 and 32)"),
        "contrast": (1.0, 0.0, 1.0, "scales each checker's two albedos about their mean"),
        "sky": (T._CW_SKY, 0.0, 10.0, "sky irradiance k"),
        "light_power": (1.0, 0.0, 100.0, "multiplies the area light's colour"),
        "light_size": (1.0, 1e-3, 4.0, "multiplies the penumbra width 0.02 + 0.10 x"),
    },
    "checker_spot": {
        "texture_scale": (1.0, 0.1, 8.0, "multiplies both checkers' squares per unit (8 and 32)"),
        "contrast": (1.0, 0.0, 1.0, "scales each checker's two albedos about their mean"),
        "sky": (T._CS_SKY, 0.0, 10.0, "sky irradiance k"),
        "light_power": (1.0, 0.0, 100.0, "multiplies the small light's colour"),
        "hit_probability": (T._CS_P, 1e-4, 1.0, "probability p that a sample finds the small light"),
        "spot_size": (1.0, 0.05, 10.0, "multiplies the falloff's radius (s^2 = 0.09 spot_size^2)"),
        "light_size": (1.0, 1e-3, 10.0, "multiplies the penumbra width 0.004 + 0.012 x"),
    },
    "checker_dof": {
        "aperture": (T._CD_APERTURE, 0.0, 0.5, "lens aperture a: blur R(z) = a (1/z - 1/z_f)"),
        "focus": (T._CD_FOCUS, 0.5, 10.0, "focus depth z_f (the cards are at 1, 2 and 3)"),
        "texture_scale": (1.0, 0.1, 8.0, "multiplies every plane's squares per unit"),
    },
}
for _p in PARAMS.values():
    _p.update(_EXPOSURE)


def defaults(scene: str) -> dict:
    """``{name: default}`` of a built-in scene's parameters."""
    return {k: v[0] for k, v in PARAMS[scene].items()}


def check_params(scene: str, params) -> dict:
    """The parameters that differ from the defaults, checked: ``{name: float}`` sorted by name.

    Raises
    ------
    InputError
        For a name the scene lacks (the message lists its parameters), a value
        that is not a finite number, or one outside its range.
    """
    where = f"scene {scene!r}"
    if params is None:
        return {}
    if not isinstance(params, dict):
        raise InputError(where, "params", f"{type(params).__name__}, expected a dict of parameter values")
    table = PARAMS[scene]
    out = {}
    for name in sorted(params):
        if name not in table:
            raise InputError(where, f"params.{name}", f"unknown parameter; {scene!r} has "
                             f"{', '.join(table) if table else 'none'}")
        v = params[name]
        if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) \
                or not math.isfinite(float(v)):
            raise InputError(where, f"params.{name}", f"{v!r}, expected a finite number")
        default, lo, hi, _ = table[name]
        if not lo <= float(v) <= hi:
            raise InputError(where, f"params.{name}", f"{float(v)!r} is outside [{lo}, {hi}] ({table[name][3]})")
        if float(v) != default:
            out[name] = float(v)
    if scene == "motion_blur" and "speed" in out:
        pair = K._mb_overlap(_mb_objects(out["speed"]))
        if pair is not None:
            raise InputError(where, "params.speed", f"{out['speed']!r} makes objects {pair[0]} and {pair[1]} "
                             "overlap in space-time (the closed form needs them disjoint): choose a lower speed")
    return out


def _scaled(value, factor):
    """``value * factor`` with a factor of 1 never applied (the defaults stay the constants themselves)."""
    return value if factor == 1.0 else value * factor


def _contrast(a0, a1, c):
    """The two albedos scaled by ``c`` about their mean (unchanged at c = 1)."""
    if c == 1.0:
        return np.asarray(a0, float), np.asarray(a1, float)
    m = 0.5 * (np.asarray(a0) + np.asarray(a1))
    return m + c * (np.asarray(a0) - m), m + c * (np.asarray(a1) - m)


def _mb_objects(speed):
    o = K._MB_OBJECTS.copy()
    if speed != 1.0:
        o[:, 4:6] *= speed
    return o


def pack(scene: str, params: dict) -> np.ndarray:
    """The float64 parameter array of a built-in scene (``params``: as :func:`check_params` returns)."""
    v = {**defaults(scene), **params}
    if scene == "soft_shadow":
        a0, a1 = _contrast(K._SS_A0, K._SS_A1, v["contrast"])
        occ = K._SS_OCCLUDERS.copy()
        if v["occluder_shift"] != 0.0:
            occ[:, 0:2] += v["occluder_shift"]
        parts = [a0, a1, [v["ambient"]], _scaled(K._SS_LIGHT, v["light_power"]),
                 [_scaled(K._SS_CHECKER, v["texture_scale"])],
                 [_scaled(K._SS_W0, v["light_size"]), _scaled(K._SS_W1, v["light_size"])], occ.ravel()]
    elif scene == "depth_of_field":
        s, c = v["texture_scale"], v["contrast"]
        band = v["focus_band"]
        ramp = K._DOF_RAMP if band == K._DOF_BAND else 0.5 - band
        parts = [[_scaled(K._DOF_RMAX, v["aperture"]), band, max(ramp, 1e-3)], [_scaled(f, s) for f in K._DOF_FREQ],
                 K._DOF_A, _scaled(K._DOF_B, c), _scaled(K._DOF_D, c), K._DOF_PHI, _scaled(K._DOF_E, c), K._DOF_PSI,
                 _scaled(K._DOF_F, c)]
    elif scene == "motion_blur":
        parts = [K._MB_BACKGROUND, [_scaled(K._MB_CHECKER, v["texture_scale"])], _mb_objects(v["speed"]).ravel()]
    elif scene == "caustic":
        parts = [[v["hit_probability"], K._CA_CX, K._CA_CY], _scaled(K._CA_COLOUR, v["power"]), [K._CA_GLOW],
                 [_scaled(K._CA_HALF_WIDTH, v["ring_width"]), v["ring_radius"], K._CA_ECC]]
    elif scene == "hdr":
        dim = v["dim_level"]
        parts = [[K._HD_CX, K._HD_CY, v["emitter_radius"], v["power"], dim,
                  _scaled(K._HD_CHECKER, v["texture_scale"])], K._HD_OCC,
                 [_scaled(K._HD_W0, v["light_size"]), _scaled(K._HD_W1, v["light_size"]),
                  K._HD_DIM_ALBEDO if dim == K._HD_DIM_LEVEL else 0.8 / dim]]
    elif scene in ("checker_wall", "checker_spot"):
        c, s = v["contrast"], v["texture_scale"]
        coarse = _contrast(*T._CW_COARSE_ALBEDO, c)
        fine = _contrast(*T._CW_FINE_ALBEDO, c)
        parts = [[_scaled(T._CW_COARSE, s)], coarse[0], coarse[1], [_scaled(T._CW_FINE, s), T._CW_FINE_X, T._CW_FINE_Y],
                 fine[0], fine[1]]
        if scene == "checker_wall":
            parts += [[v["sky"]], _scaled(T._CW_LIGHT, v["light_power"]), T._CW_OCC,
                      [_scaled(T._CW_W0, v["light_size"]), _scaled(T._CW_W1, v["light_size"]), T._CW_DEPTH]]
        else:
            size = v["spot_size"]
            parts += [[v["hit_probability"], v["sky"]], _scaled(T._CS_LIGHT, v["light_power"]),
                      [T._CS_CX, T._CS_CY, T._CS_S2 if size == 1.0 else T._CS_S2 * size * size], T._CS_OCC,
                      [_scaled(T._CS_W0, v["light_size"]), _scaled(T._CS_W1, v["light_size"])]]
    elif scene == "checker_dof":
        parts = [T._cd_planes(v["aperture"], v["focus"], v["texture_scale"]).ravel()]
    else:  # flat: numpy code, no kernel
        parts = [[]]
    out = np.concatenate([np.asarray(p, dtype=np.float64).ravel() for p in parts])
    out.setflags(write=False)
    return out
