"""Tone operators: the display model ``T(x)`` of a pixel's radiance.

A registry of monotone non-decreasing functions (:data:`TONE_OPERATORS`,
:func:`register_tone_operator`, :func:`get_tone_operator`) and
:func:`tone_map`, the displayed value ``T(2**exposure * x)`` (exposure in stops, as the
PNG previews of :mod:`mcrecon.io.images` take it).  The ``ci``
method (:mod:`mcrecon.methods.ci`) decides on the displayed value, and the
bootstrap bias (:mod:`mcrecon.methods.ci.analysis.bootstrap`) reports bias in display
space; anyone else may use them too.

A tone operator is a *display* model: it drives sampling decisions and
display-space error/bias numbers only, never the radiance a method returns.

References
----------
.. [1] R. Tamstorf, H. W. Jensen, "Adaptive Sampling and Bias Estimation
   in Path Tracing", Rendering Techniques '97 (Proc. 8th Eurographics
   Workshop on Rendering), 1997, Eq. (4) and (9).
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np

from ...errors import InputError

__all__ = ["ToneOperator", "TONE_OPERATORS", "register_tone_operator", "get_tone_operator", "tone_map"]

#: Codes of the operators the bootstrap kernel evaluates natively (numba):
#: ``_tone_scalar`` in :mod:`mcrecon.methods.ci.analysis.bootstrap` is their scalar twin.
_CODE_LINEAR, _CODE_GAMMA, _CODE_REINHARD = 0, 1, 2

# x/(1+x) of a value above this is 1 to double precision; capping keeps
# inf/(1+inf) = nan out of the Reinhard curve.
_BIG = 1e300


def _tone_linear(x: np.ndarray, gamma: float) -> np.ndarray:
    return np.asarray(x, dtype=np.float64)


def _tone_gamma(x: np.ndarray, gamma: float) -> np.ndarray:
    # A display shows [0, 1]; values outside it are clipped by the device,
    # so their differences are invisible (the paper's "6.5 or 7.5" example).
    return np.power(np.clip(np.asarray(x, dtype=np.float64), 0.0, 1.0), 1.0 / gamma)


def _tone_reinhard(x: np.ndarray, gamma: float) -> np.ndarray:
    x = np.clip(np.asarray(x, dtype=np.float64), 0.0, _BIG)
    return np.power(x / (1.0 + x), 1.0 / gamma)


@dataclasses.dataclass(frozen=True)
class ToneOperator:
    """A monotone non-decreasing display function ``T(x)``.

    Attributes
    ----------
    name : str
    fn : callable ``(x: ndarray, gamma: float) -> ndarray``
        Vectorised; must accept +-inf (the interval of a pixel without a
        variance estimate is infinite) and return finite or +-inf values.
    help : str
    code : int
        Built-in operators have a native code the bootstrap kernel runs;
        user operators (-1) run through a slower numpy path.
    """

    name: str
    fn: Callable[[np.ndarray, float], np.ndarray]
    help: str
    code: int = -1


#: Registry of tone operators, name -> :class:`ToneOperator`.
TONE_OPERATORS: dict[str, ToneOperator] = {}


def register_tone_operator(name: str, fn: Callable[[np.ndarray, float], np.ndarray], *,
                           help: str = "", _code: int = -1) -> ToneOperator:
    """Register a tone operator ``fn(x, gamma)`` under ``name``.

    The stopping rule's derivation (Eq. 9) needs T non-decreasing; it is
    checked on a grid of 2001 values from -1 to 1e6 (and at +-inf).

    Raises
    ------
    InputError
        ``name`` is empty or ``fn`` is not callable, not vectorised, or
        decreases somewhere on the check grid.
    """
    where = "register_tone_operator"
    if not isinstance(name, str) or not name:
        raise InputError(where, "name", "expected a non-empty string")
    if not callable(fn):
        raise InputError(where, "fn", f"{fn!r} is not callable; expected fn(x: ndarray, gamma) -> ndarray")
    grid = np.concatenate([[-np.inf], np.linspace(-1.0, 1.0, 1001), np.geomspace(1.0, 1e6, 1000)[1:],
                           [np.inf]])
    with np.errstate(all="ignore"):
        try:
            y = np.asarray(fn(grid, 2.2), dtype=np.float64)
        except Exception as exc:
            raise InputError(where, "fn", f"failed on an array: {type(exc).__name__}: {exc}") from None
    if y.shape != grid.shape:
        raise InputError(where, "fn", f"returned shape {y.shape} for input {grid.shape}; expected elementwise")
    if np.isnan(y).any() or (np.diff(y) < 0).any():
        raise InputError(where, "fn", "must be non-decreasing (Eq. 9 of Tamstorf and Jensen) and never NaN, "
                         "also at +-inf")
    op = ToneOperator(name, fn, help, _code)
    TONE_OPERATORS[name] = op
    return op


register_tone_operator("gamma", _tone_gamma, _code=_CODE_GAMMA,
                       help="display gamma: clip to [0, 1], then x^(1/gamma) (the paper's, gamma = 2.2)")
register_tone_operator("linear", _tone_linear, _code=_CODE_LINEAR,
                       help="no tone operator: Purgathofer's criterion on radiance (Eq. 3)")
register_tone_operator("reinhard", _tone_reinhard, _code=_CODE_REINHARD,
                       help="HDR: x/(1+x) (x clipped at 0), then x^(1/gamma)")


def get_tone_operator(name: str, *, where: str = "tone") -> ToneOperator:
    """The registered operator ``name``; InputError listing the valid ones."""
    op = TONE_OPERATORS.get(name) if isinstance(name, str) else None
    if op is None:
        raise InputError(where, "tone", f"unknown tone operator {name!r}; valid: {', '.join(TONE_OPERATORS)}")
    return op


def tone_map(x, *, tone: str = "gamma", gamma: float = 2.2, exposure: float = 0.0) -> np.ndarray:
    """Displayed value ``T(2**exposure * x)`` (Eq. 4), ``exposure`` in stops."""
    op = get_tone_operator(tone)
    with np.errstate(invalid="ignore", over="ignore"):
        # 2**exposure > 0, so a scaled +-inf stays +-inf; no NaN arises.
        return op.fn(2.0 ** float(exposure) * np.asarray(x, dtype=np.float64), float(gamma))
