"""``ci``: confidence-interval adaptive sampling on the *displayed* value,
bootstrap estimation of the bias it causes, and the chi-square test of the
normality the interval assumes (Tamstorf and Jensen 1997).

Three tools, one module (the equation-to-function map is in
``docs/methods/ci.md``):

* **Stopping rule** (Sec. 2-3).  The Student-t interval of Eq. (6) per
  pixel and channel, pushed through a monotone tone operator T (Eq. 9);
  a pixel is done when ``T(U) - T(L) <= 2 d`` (Eq. 10) in *every*
  channel.  :class:`StoppingRule`, :func:`confidence_interval`,
  :func:`display_width`, :func:`stopping_rule`, :class:`CIMethod`.
* **Bootstrap bias** (Sec. 4, Eq. 11-15).  Per pixel, the stopping rule
  is re-run B times on resamples drawn with replacement from the pixel's
  own samples (the empirical distribution F-hat); the mean of the B
  estimates minus ``t(F-hat)`` (the pixel's sample mean) estimates the
  bias.  One numba kernel, parallel over pixels.
  :func:`bootstrap_bias`, :func:`bootstrap_bias_log`,
  :func:`group_samples`, :func:`exact_two_point_bias` (Eq. 11 computed
  exactly for a two-point pixel, used to validate the bootstrap).
* **Normality test** (Sec. 3, 5.1, Eq. 16).  m independent estimates of
  n samples per pixel, 8 equiprobable classes of N(mu-hat, s^2), Pearson's
  statistic z against the chi2(classes - 3) quantile.
  :func:`chi2_normality`, :func:`repeated_estimates`,
  :func:`normality_experiment`.

Tone operators are a registry of monotone non-decreasing functions
(:data:`TONE_OPERATORS`, :func:`register_tone_operator`).  They are a
*display* model that only drives sampling decisions and display-space
error/bias numbers: the radiance the method returns is never clipped or
rescaled.

References
----------
.. [1] R. Tamstorf, H. W. Jensen, "Adaptive Sampling and Bias Estimation
   in Path Tracing", Rendering Techniques '97 (Proc. 8th Eurographics
   Workshop on Rendering), 1997.
.. [2] W. Purgathofer, "A statistical method for adaptive stochastic
   sampling", Computers & Graphics 11(2), 1987.
.. [3] B. Efron, R. J. Tibshirani, "An Introduction to the Bootstrap",
   Chapman & Hall, 1993.
.. [4] H. Chernoff, E. L. Lehmann, "The use of maximum likelihood
   estimates in chi-square tests for goodness of fit", Ann. Math. Statist.
   25(3), 1954.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from typing import Callable, Sequence

import numba
import numpy as np
from numba import prange
from scipy import stats as sps

from ..errors import InputError, McreconWarning
from ..protocol import SampleRequest, validate_reply
from ..samples import source_name
from ..stats import PixelStats
from .base import AdaptiveState, Method, MethodInputs, Option, RunState, uniform_counts
from .box import fill_empty_pixels

__all__ = [
    "CIMethod", "StoppingRule", "ToneOperator", "TONE_OPERATORS", "register_tone_operator",
    "get_tone_operator", "tone_map", "t_quantile", "confidence_interval", "display_width",
    "stopping_rule", "PixelSamples", "group_samples", "group_log", "BiasEstimate",
    "BootstrapBiasResult", "bootstrap_bias", "bootstrap_bias_log", "bootstrap_bias_samples",
    "exact_two_point_bias", "ChiSquareResult", "chi2_normality", "repeated_estimates",
    "normality_experiment", "DEFAULT_MIN_SPP",
]

# --------------------------------------------------------------------------
# Tone operators
# --------------------------------------------------------------------------

#: Codes of the operators the bootstrap kernel evaluates natively (numba).
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


def tone_map(x, *, tone: str = "gamma", gamma: float = 2.2, exposure: float = 1.0) -> np.ndarray:
    """Displayed value ``T(exposure * x)`` (Eq. 4)."""
    op = get_tone_operator(tone)
    with np.errstate(invalid="ignore", over="ignore"):
        # exposure * (+-inf) stays +-inf for exposure > 0; no NaN arises.
        return op.fn(float(exposure) * np.asarray(x, dtype=np.float64), float(gamma))


# --------------------------------------------------------------------------
# Eq. (6): the Student-t confidence interval; Eq. (10): the stopping rule
# --------------------------------------------------------------------------

#: Default minimum (initial) samples per pixel, see :class:`StoppingRule`.
DEFAULT_MIN_SPP = 8


def t_quantile(count, alpha: float) -> np.ndarray:
    """``t(n - 1)_{1 - alpha/2}`` of Eq. (6) for an array of sample counts.

    Counts below 2 have no variance estimate: their quantile is +inf (an
    infinitely wide interval, never converged).
    """
    n = np.asarray(count, dtype=np.int64)
    out = np.full(n.shape, np.inf)
    ok = n >= 2
    if ok.any():
        # Few distinct counts per image: evaluate scipy once per count.
        uniq, inv = np.unique(n[ok], return_inverse=True)
        out[ok] = sps.t.ppf(1.0 - alpha / 2.0, uniq - 1)[inv]
    return out


def confidence_interval(mean, variance, count, *, alpha: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """The approximate ``1 - alpha`` interval of Eq. (6).

    ``[mean - t s / sqrt(n), mean + t s / sqrt(n)]`` with ``t`` the
    ``1 - alpha/2`` quantile of Student's t with ``n - 1`` degrees of
    freedom and ``s^2`` the sample variance.

    Parameters
    ----------
    mean, variance : array_like (..., C)
    count : array_like (...)
        Samples per pixel; broadcast against the channel axis.
    alpha : float
        ``1 - alpha`` is the confidence level.

    Returns
    -------
    lower, upper : ndarray (..., C)
        ``-inf, +inf`` where ``count < 2`` or the variance is undefined.

    References
    ----------
    .. [1] Tamstorf and Jensen 1997, Eq. (6).
    """
    mean = np.asarray(mean, dtype=np.float64)
    var = np.asarray(variance, dtype=np.float64)
    n = np.asarray(count)
    t = t_quantile(n, alpha)[..., None]
    n = n[..., None].astype(np.float64)
    ok = np.isfinite(t) & np.isfinite(var) & (n >= 2)
    half = np.full(np.broadcast_shapes(mean.shape, var.shape, ok.shape), np.inf)
    np.multiply(t, np.sqrt(np.maximum(var, 0.0) / np.maximum(n, 1.0), where=ok,
                           out=np.zeros(half.shape)), out=half, where=ok)
    return mean - half, mean + half


def display_width(lower, upper, *, tone: str = "gamma", gamma: float = 2.2,
                  exposure: float = 1.0) -> np.ndarray:
    """``T(L_U) - T(L_L)``: the interval's width on the display (Eq. 9-10)."""
    tu = tone_map(upper, tone=tone, gamma=gamma, exposure=exposure)
    tl = tone_map(lower, tone=tone, gamma=gamma, exposure=exposure)
    with np.errstate(invalid="ignore"):
        w = tu - tl
    # inf - inf cannot occur (upper >= lower); a user operator saturating to
    # the same infinity at both ends would give NaN: treat as not converged.
    return np.where(np.isnan(w), np.inf, w)


@dataclasses.dataclass(frozen=True)
class StoppingRule:
    """The adaptive sampling rule of Tamstorf and Jensen (Sec. 2-3, 5).

    Start with ``min_spp`` samples per pixel; after every batch, a pixel
    is converged when in every channel ``T(e U) - T(e L) <= 2 d`` (Eq. 10)
    with ``[L, U]`` the interval of Eq. (6); unconverged pixels get
    ``step_spp`` more ("another n samples", Sec. 5) until ``max_spp``.

    Parameters
    ----------
    tolerance : float
        ``d``, half the allowed display width (1/256: one 8-bit level).
    alpha : float
        ``1 - alpha`` is the confidence level.
    tone : str
        A registered tone operator (:data:`TONE_OPERATORS`).
    gamma : float
        Display gamma used by the ``gamma`` and ``reinhard`` operators.
    exposure : float
        Radiance scale ``e`` applied before the operator.
    min_spp : int
        Initial samples per pixel, >= 2.  The paper uses Purgathofer's lower
        bound [2], which its text does not restate; we use a documented
        default of 8: the smallest n at which the t quantile is within 20%
        of the normal one (t(7)_0.975 = 2.36 vs 1.96), and close to the
        n = 10 at which the paper's chi-square test found the normal
        approximation acceptable for ~90% of pixels (Sec. 5.1).
    step_spp : int
        Samples added per round to an unconverged pixel (0: ``min_spp``).
    max_spp : int
        Per-pixel cap: a pixel with this many samples stops (needed so the
        bootstrap rerun terminates; the adaptive driver's budget usually
        binds first).
    """

    tolerance: float = 1.0 / 256.0
    alpha: float = 0.05
    tone: str = "gamma"
    gamma: float = 2.2
    exposure: float = 1.0
    min_spp: int = DEFAULT_MIN_SPP
    step_spp: int = 0
    max_spp: int = 1024

    def __post_init__(self):
        where = "stopping rule"
        for name in ("tolerance", "gamma", "exposure"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float, np.number)) and math.isfinite(v) and v > 0):
                raise InputError(where, name, f"got {v!r}, expected a finite number > 0")
        if not (isinstance(self.alpha, (int, float, np.number)) and 0.0 < self.alpha < 1.0):
            raise InputError(where, "alpha", f"got {self.alpha!r}, expected 0 < alpha < 1 "
                             "(1 - alpha is the confidence level)")
        get_tone_operator(self.tone, where=where)
        for name in ("min_spp", "step_spp", "max_spp"):
            v = getattr(self, name)
            if not isinstance(v, (int, np.integer)) or isinstance(v, bool):
                raise InputError(where, name, f"got {v!r}, expected an integer")
        if self.min_spp < 2:
            raise InputError(where, "min_spp", f"got {self.min_spp}, expected >= 2 (Eq. 6 needs a variance)")
        if self.step_spp < 0:
            raise InputError(where, "step_spp", f"got {self.step_spp}, expected >= 0 (0: min_spp)")
        if self.max_spp < self.min_spp:
            raise InputError(where, "max_spp", f"got {self.max_spp}, expected >= min_spp = {self.min_spp}")
        if self.max_spp >= 2**31:
            raise InputError(where, "max_spp", f"got {self.max_spp}, expected < 2^31")

    @property
    def step(self) -> int:
        return int(self.step_spp or self.min_spp)

    def widths(self, mean, variance, count) -> np.ndarray:
        """Display width ``T(e U) - T(e L)`` per pixel and channel."""
        lo, hi = confidence_interval(mean, variance, count, alpha=self.alpha)
        return display_width(lo, hi, tone=self.tone, gamma=self.gamma, exposure=self.exposure)

    def converged(self, mean, variance, count) -> np.ndarray:
        """Pixels that stop: every channel satisfies Eq. (10) after at least
        ``min_spp`` samples, or the pixel reached ``max_spp``."""
        count = np.asarray(count)
        ok = np.all(self.widths(mean, variance, count) <= 2.0 * self.tolerance, axis=-1)
        return (ok & (count >= self.min_spp)) | (count >= self.max_spp)

    def converged_stats(self, stats: PixelStats) -> np.ndarray:
        return self.converged(stats.mean, stats.sample_variance(undefined=np.nan), stats.count)

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


def stopping_rule(mean, variance, count, *, tolerance: float = 1.0 / 256.0, alpha: float = 0.05,
                  tone: str = "gamma", gamma: float = 2.2, exposure: float = 1.0,
                  per_channel: bool = False) -> np.ndarray:
    """Eq. (10): ``T(L_U) - T(L_L) <= 2 d`` with ``[L_L, L_U]`` from Eq. (6).

    Returns a boolean (..., C) array with ``per_channel``, else (...): true
    where *every* channel satisfies the rule.  Why all channels: the paper's
    tolerance is the resolution of each displayed colour value ("8
    bitplanes per color"); a luminance test would let chromatic noise that
    cancels in the luminance (red against blue) pass unseen by the rule but
    not by the viewer.  Counts below 2 never satisfy it.
    """
    rule = StoppingRule(tolerance=tolerance, alpha=alpha, tone=tone, gamma=gamma, exposure=exposure,
                        min_spp=2, max_spp=2**31 - 1)
    w = rule.widths(mean, variance, count) <= 2.0 * tolerance
    return w if per_channel else np.all(w, axis=-1)


# --------------------------------------------------------------------------
# The method
# --------------------------------------------------------------------------

class CIMethod(Method):
    """Confidence-interval adaptive sampling with a tone operator.

    Round 0 gives every pixel ``min_spp`` samples; every later round gives
    ``step_spp`` more to each pixel that does not satisfy Eq. (10) in every
    channel.  When the remaining budget cannot serve all of them, the
    pixels with the widest displayed interval (relative to ``2 d``) are
    served first (the rest wait: their interval is the narrowest).
    ``plan`` returns None once every pixel converged (or hit ``max_spp``).
    The image is the per-pixel sample mean (Eq. 2, box filter).

    Diagnostics: ``spp`` (samples per pixel), ``converged`` (0/1) and
    ``width_ratio`` (largest ``(T(U) - T(L)) / 2d`` over the channels;
    pixels without a variance estimate show the largest finite ratio).

    References
    ----------
    .. [1] Tamstorf and Jensen 1997, Eq. (6), (10), Sec. 5.
    """

    name = "ci"
    adaptive = True
    options = (
        Option("alpha", float, 0.05, "1 - alpha is the confidence level of Eq. (6)"),
        Option("tolerance", float, 1.0 / 256.0, "d of Eq. (10): half the allowed display width"),
        Option("tone", str, "gamma", "tone operator T: " + ", ".join(
            f"{k} ({v.help})" for k, v in TONE_OPERATORS.items())),
        Option("gamma", float, 2.2, "display gamma of the gamma/reinhard operators"),
        Option("exposure", float, 1.0, "radiance scale applied before the tone operator"),
        Option("min_spp", int, DEFAULT_MIN_SPP, "initial samples per pixel (>= 2)"),
        Option("step_spp", int, 0, "samples added per round to unconverged pixels (0: min_spp)"),
        Option("max_spp", int, 1024, "per-pixel cap: a pixel with this many samples stops"),
    )

    def _configure(self, params: dict) -> None:
        try:
            rule = StoppingRule(tolerance=params["tolerance"], alpha=params["alpha"], tone=params["tone"],
                                gamma=params["gamma"], exposure=params["exposure"], min_spp=params["min_spp"],
                                step_spp=params["step_spp"], max_spp=params["max_spp"])
        except InputError as exc:  # name the method, not the helper, in the message
            raise InputError(self.where, exc.field, exc.problem) from None
        self.rule = rule

    def reconstruct_run(self, run: RunState, inputs: MethodInputs) -> np.ndarray:
        stats = inputs.stats
        return fill_empty_pixels(stats.mean.copy(), stats.count)

    def _update_diagnostics(self, run: RunState, stats: PixelStats, widths: np.ndarray,
                            done: np.ndarray) -> np.ndarray:
        ratio = np.max(widths, axis=-1) / (2.0 * self.rule.tolerance)
        finite = np.isfinite(ratio)
        fill = float(ratio[finite].max()) if finite.any() else 0.0
        ratio = np.where(finite, ratio, fill)
        run.diagnostics["spp"] = stats.count.astype(np.float64)
        run.diagnostics["converged"] = done.astype(np.float64)
        run.diagnostics["width_ratio"] = ratio
        return ratio

    def plan(self, run: RunState, state: AdaptiveState) -> SampleRequest | None:
        remaining = state.remaining
        st = state.stats
        rule = self.rule
        n = st.count
        widths = rule.widths(st.mean, st.sample_variance(undefined=np.nan), n)
        done = (np.all(widths <= 2.0 * rule.tolerance, axis=-1) & (n >= rule.min_spp)) | (n >= rule.max_spp)
        ratio = self._update_diagnostics(run, st, widths, done)
        if remaining <= 0 or done.all():
            return None
        # Pixels below the initial count (round 0, or a budget-cut round 0)
        # are first topped up to min_spp; the others get another step.
        need = np.where(n < rule.min_spp, rule.min_spp - n, rule.step)
        need = np.minimum(need, rule.max_spp - n)
        need = np.where(done, 0, need).astype(np.int64)
        total = int(need.sum())
        if total <= remaining:
            return state.request(counts=need)
        if n.max() == 0:
            # Budget below the initial pass: spread it evenly.
            return state.request(counts=uniform_counts(state.width, state.height, remaining, state.rng))
        # Widest displayed interval first; pixels without any variance
        # estimate (n < 2) have an infinite ratio and come first.  Ties keep
        # row-major order (stable sort): plan depends only on the state.
        flat_need = need.ravel()
        key = np.where(n.ravel() < 2, np.inf, ratio.ravel())
        order = np.argsort(-key, kind="stable")
        order = order[flat_need[order] > 0]
        cum = np.cumsum(flat_need[order])
        k = int(np.searchsorted(cum, remaining, side="right"))
        counts = np.zeros_like(flat_need)
        counts[order[:k]] = flat_need[order[:k]]
        left = remaining - (int(cum[k - 1]) if k else 0)
        if left > 0 and k < order.size:
            counts[order[k]] = left
        return state.request(counts=counts.reshape(n.shape))


# --------------------------------------------------------------------------
# Grouping a log's samples by pixel (CSR)
# --------------------------------------------------------------------------

@numba.njit(cache=True)
def _counting_sort(pix, n_pixels):
    """Stable counting sort: (order, offsets) with pixel p's samples at
    ``order[offsets[p]:offsets[p+1]]`` in their original order."""
    offsets = np.zeros(n_pixels + 1, np.int64)
    for i in range(pix.size):
        offsets[pix[i] + 1] += 1
    for p in range(n_pixels):
        offsets[p + 1] += offsets[p]
    fill = offsets[:-1].copy()
    order = np.empty(pix.size, np.int64)
    for i in range(pix.size):
        q = pix[i]
        order[fill[q]] = i
        fill[q] += 1
    return order, offsets


@dataclasses.dataclass(eq=False)
class PixelSamples:
    """Samples grouped by pixel, in their original (chronological) order.

    Pixel ``p = row * width + col`` owns ``values[offsets[p]:offsets[p+1]]``;
    ``order`` maps these rows back to the input rows.

    Attributes
    ----------
    width, height : int
    channels : tuple of str
    values : ndarray (N, C) float64, grouped
    offsets : ndarray (H*W + 1,) int64
    order : ndarray (N,) int64
    """

    width: int
    height: int
    channels: tuple
    values: np.ndarray
    offsets: np.ndarray
    order: np.ndarray

    @property
    def counts(self) -> np.ndarray:
        """Samples per pixel (H, W)."""
        return np.diff(self.offsets).reshape(self.height, self.width)

    def pixel(self, col: int, row: int) -> np.ndarray:
        p = int(row) * self.width + int(col)
        return self.values[self.offsets[p]:self.offsets[p + 1]]

    def means(self) -> np.ndarray:
        """Per-pixel sample means (H, W, C), 0 where empty: ``t(F-hat)``."""
        cnt = np.diff(self.offsets)
        pix = np.repeat(np.arange(cnt.size), cnt)
        sums = np.stack([np.bincount(pix, weights=self.values[:, c], minlength=cnt.size)
                         for c in range(self.values.shape[1])], axis=1)
        return (sums / np.maximum(cnt, 1)[:, None]).reshape(self.height, self.width, -1)


def group_samples(positions, values, *, width: int, height: int, channels: Sequence[str] | None = None,
                  nonfinite: str = "drop", source: str = "samples") -> PixelSamples:
    """Group samples by pixel (stable counting sort, O(N)).

    Parameters
    ----------
    positions : array_like (N, 2)
        Film positions (x = column, y = row), inside [0, W) x [0, H).
    values : array_like (N, C)
    nonfinite : {'drop', 'raise'}
        Samples with a NaN/Inf value are dropped with a McreconWarning
        (the sample log's default policy) or refused.
    """
    if nonfinite not in ("drop", "raise"):
        raise InputError(source, "nonfinite", f"got {nonfinite!r}; valid: drop, raise")
    width, height = int(width), int(height)
    if width < 1 or height < 1:
        raise InputError(source, "width/height", f"got {width}x{height}, expected at least 1x1")
    pos = np.asarray(positions, dtype=np.float64)
    val = np.asarray(values, dtype=np.float64)
    if val.ndim == 1:
        val = val[:, None]
    if pos.ndim != 2 or pos.shape[1] != 2:
        raise InputError(source, "positions", f"shape {pos.shape}, expected (N, 2)")
    if val.ndim != 2 or val.shape[0] != pos.shape[0] or val.shape[1] < 1:
        raise InputError(source, "values", f"shape {val.shape}, expected ({pos.shape[0]}, C)")
    chans = tuple(channels) if channels is not None else (
        ("R", "G", "B") if val.shape[1] == 3 else tuple(f"C{i}" for i in range(val.shape[1])))
    if len(chans) != val.shape[1]:
        raise InputError(source, "channels", f"{len(chans)} names for {val.shape[1]} value columns")
    bad = ~((pos[:, 0] >= 0) & (pos[:, 0] < width) & (pos[:, 1] >= 0) & (pos[:, 1] < height))
    if bad.any():
        raise InputError(source, "positions", f"{int(bad.sum())} sample(s) off the film [0, {width}) x "
                         f"[0, {height}) or non-finite")
    finite = np.isfinite(val).all(axis=1)
    keep = np.flatnonzero(finite)
    if keep.size != val.shape[0]:
        if nonfinite == "raise":
            raise InputError(source, "values", f"{int((~finite).sum())} sample(s) with NaN or Inf; "
                             "drop them with nonfinite='drop'")
        warnings.warn(f"{source}: values: {int((~finite).sum())} sample(s) with NaN or Inf dropped",
                      McreconWarning, stacklevel=2)
        pos, val = pos[keep], val[keep]
    pix = (np.floor(pos[:, 1]).astype(np.int64) * width + np.floor(pos[:, 0]).astype(np.int64))
    order, offsets = _counting_sort(pix, width * height)
    grouped = np.ascontiguousarray(val[order])
    if keep.size != finite.size:
        order = keep[order]
    return PixelSamples(width, height, chans, grouped, offsets, order)


def group_log(log, *, nonfinite: str = "drop") -> PixelSamples:
    """Group the samples of a sample source (a :class:`~mcrecon.io.SampleLog` or a
    :class:`~mcrecon.samples.SampleSet`) by pixel; holds every sample in memory."""
    if not (hasattr(log, "iter_chunks") and hasattr(log, "width")):
        raise InputError("group_log", "log", f"got {type(log).__name__}; expected a sample source "
                         "(mcrecon.read_log(path) or a SampleSet)")
    chunks = list(log.iter_chunks(with_round=False))
    c = len(log.channels)
    pos = np.concatenate([np.asarray(ch.positions) for ch in chunks]) if chunks else np.zeros((0, 2))
    val = np.concatenate([np.asarray(ch.values) for ch in chunks]) if chunks else np.zeros((0, c))
    return group_samples(pos, val, width=log.width, height=log.height,
                         channels=log.channels, nonfinite=nonfinite, source=source_name(log))


# --------------------------------------------------------------------------
# Bootstrap bias (Sec. 4): the numba kernel
# --------------------------------------------------------------------------

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_MIX1 = np.uint64(0xBF58476D1CE4E5B9)
_MIX2 = np.uint64(0x94D049BB133111EB)


@numba.njit(cache=True, inline="always")
def _mix64(z):
    z = (z ^ (z >> np.uint64(30))) * _MIX1
    z = (z ^ (z >> np.uint64(27))) * _MIX2
    return z ^ (z >> np.uint64(31))


@numba.njit(cache=True, inline="always")
def _stream_start(base, pixel, B, b):
    # One SplitMix64 stream per (pixel, resample), keyed by a hash of the
    # counter: independent of thread scheduling, so results are
    # reproducible for a seed whatever the number of threads.
    return _mix64(base + np.uint64(pixel) * np.uint64(B) + np.uint64(b))


@numba.njit(cache=True, inline="always")
def _tone_scalar(code, x, inv_gamma):
    if code == 0:
        return x
    if x <= 0.0:
        return 0.0
    if code == 1:
        if x >= 1.0:
            return 1.0
        return x ** inv_gamma
    if x > 1e300:
        x = 1e300
    return (x / (1.0 + x)) ** inv_gamma


@numba.njit(cache=True, inline="always")
def _draw(vals, lo, n, state, k, target, s1, s2):
    """Draw samples with replacement from vals[lo:lo+n] until k == target.

    Each 64-bit SplitMix64 output gives two indices (its high and low 32
    bits) through Lemire's multiply-shift, uniform in [0, n) up to a
    relative bias of n / 2^32 (< 1e-6 for n < 4096), far below the Monte
    Carlo error.  An odd target leaves the second index of the last output
    unused: the stream stays a pure function of (seed, pixel, resample, k).
    """
    C = vals.shape[1]
    nn = np.uint64(n)
    m32 = np.uint64(0xFFFFFFFF)
    sh = np.uint64(32)
    if C == 3:
        # Scalar accumulators stay in registers (array ones go through memory).
        a1, b1, c1 = s1[0], s1[1], s1[2]
        a2, b2, c2 = s2[0], s2[1], s2[2]
        while k < target:
            state = state + _GOLDEN
            z = _mix64(state)
            r = lo + np.int64(((z >> sh) * nn) >> sh)
            v0, v1, v2 = vals[r, 0], vals[r, 1], vals[r, 2]
            a1 += v0
            b1 += v1
            c1 += v2
            a2 += v0 * v0
            b2 += v1 * v1
            c2 += v2 * v2
            k += 1
            if k < target:
                r = lo + np.int64(((z & m32) * nn) >> sh)
                v0, v1, v2 = vals[r, 0], vals[r, 1], vals[r, 2]
                a1 += v0
                b1 += v1
                c1 += v2
                a2 += v0 * v0
                b2 += v1 * v1
                c2 += v2 * v2
                k += 1
        s1[0], s1[1], s1[2] = a1, b1, c1
        s2[0], s2[1], s2[2] = a2, b2, c2
        return state, k
    while k < target:
        state = state + _GOLDEN
        z = _mix64(state)
        r = lo + np.int64(((z >> sh) * nn) >> sh)
        for c in range(C):
            v = vals[r, c]
            s1[c] += v
            s2[c] += v * v
        k += 1
        if k < target:
            r = lo + np.int64(((z & m32) * nn) >> sh)
            for c in range(C):
                v = vals[r, c]
                s1[c] += v
                s2[c] += v * v
            k += 1
    return state, k


_BINADE_OFFSET = 1100


def _slope_table(inv_gamma: float) -> np.ndarray:
    """``2^(e (1/gamma - 1))`` for binade exponents e (frexp) from -1099 to 9."""
    e = np.arange(-_BINADE_OFFSET, 10, dtype=np.float64)
    with np.errstate(over="ignore"):
        return np.exp2(e * (inv_gamma - 1.0))


@numba.njit(cache=True, inline="always")
def _width_decided(code, lo, hi, inv_gamma, two_d, tab):
    """Decide ``T(hi) - T(lo) <= 2d`` without pow when slopes allow it.

    Returns 1 (surely within), 0 (surely not) or -1 (compute exactly).
    Gamma (concave on [0, 1]): the width lies between the slope at the
    upper end and the slope at the lower end times ``b - a``; the slope
    ``g x^(g-1)`` is bounded on x's binade ``[2^(e-1), 2^e)`` by the table
    ``2^(e (g-1))``.  Reinhard: the slope on [lo, hi] is at least
    ``g / (1 + hi)^2``.  Bounds are applied with a 1e-12 relative margin, so
    a decision differs from the exact comparison only within rounding.
    """
    if code == 1 and inv_gamma <= 1.0:
        a = lo if lo > 0.0 else 0.0
        b = hi if hi < 1.0 else 1.0
        if b <= a:
            return 1
        span = b - a
        # the slope on [0, 1] is at least 1/gamma: most unconverged checks end here
        if inv_gamma * span > two_d * (1.0 + 1e-12):
            return 0
        mb, eb = math.frexp(b)  # (frexp costs ~10 ns: only near the boundary)
        if inv_gamma * tab[eb + _BINADE_OFFSET] * span > two_d * (1.0 + 1e-12):
            return 0
        if a > 0.0:
            ma, ea = math.frexp(a)
            if inv_gamma * tab[ea - 1 + _BINADE_OFFSET] * span < two_d * (1.0 - 1e-12):
                return 1
        return -1
    if code == 2 and inv_gamma <= 1.0:
        a = lo if lo > 0.0 else 0.0
        if hi <= a:
            return 1
        if inv_gamma * (hi - a) / ((1.0 + hi) * (1.0 + hi)) > two_d * (1.0 + 1e-12):
            return 0
        return -1
    return -1


@numba.njit(cache=True, inline="always")
def _rule_ok(s1, s2, k, theta, p, tq, two_d, code, inv_gamma, exposure, tab):
    """Eq. (10) in every channel, from centred running sums (same arithmetic
    as the numpy path: mean, var = m2/(k-1), h = t sqrt(var/k))."""
    for c in range(s1.size):
        m = s1[c] / k
        var = (s2[c] - s1[c] * m) / (k - 1)
        if var < 0.0:
            var = 0.0
        h = tq * math.sqrt(var / k)
        mu = theta[p, c] + m
        lo = exposure * (mu - h)
        hi = exposure * (mu + h)
        dec = _width_decided(code, lo, hi, inv_gamma, two_d, tab)
        if dec == 0:
            return False
        if dec == 1:
            continue
        w = _tone_scalar(code, hi, inv_gamma) - _tone_scalar(code, lo, inv_gamma)
        if not (w <= two_d):
            return False
    return True


@numba.njit(cache=True, parallel=True)
def _bootstrap_kernel(vals, offsets, theta, base, B, n0, step, max_n, tq, two_d, code, inv_gamma,
                      exposure, tab, dev_mean, dev_m2, disp_mean, disp_m2, spp_mean, capped):
    P = offsets.size - 1
    C = vals.shape[1]
    for p in prange(P):
        lo = offsets[p]
        n = offsets[p + 1] - lo
        if n == 0:
            continue
        # A constant pixel: every resample is the same, its interval has
        # width 0 and stops at n0 with the pixel's own value (bias exactly 0).
        constant = True
        for r in range(lo + 1, lo + n):
            for c in range(C):
                if vals[r, c] != vals[lo, c]:
                    constant = False
                    break
            if not constant:
                break
        if constant:
            spp_mean[p] = min(n0, max_n)
            capped[p] = 1.0 if n0 >= max_n else 0.0
            continue
        s1 = np.zeros(C)
        s2 = np.zeros(C)
        am = np.zeros(C)
        a2 = np.zeros(C)
        dm = np.zeros(C)
        d2 = np.zeros(C)
        t0 = np.empty(C)
        for c in range(C):
            t0[c] = _tone_scalar(code, exposure * theta[p, c], inv_gamma)
        ksum = 0.0
        ncap = 0
        for b in range(B):
            state = _stream_start(base, p, B, b)
            for c in range(C):
                s1[c] = 0.0
                s2[c] = 0.0
            k = 0
            target = n0
            while True:
                state, k = _draw(vals, lo, n, state, k, target, s1, s2)
                if k >= max_n:
                    ncap += 1
                    break
                if _rule_ok(s1, s2, k, theta, p, tq[k], two_d, code, inv_gamma, exposure, tab):
                    break
                target = min(k + step, max_n)
            ksum += k
            inv = 1.0 / (b + 1)
            for c in range(C):
                # theta* - t(F-hat): the resample mean of the centred values.
                dev = s1[c] / k
                delta = dev - am[c]
                am[c] += delta * inv
                a2[c] += delta * (dev - am[c])
                dd = _tone_scalar(code, exposure * (theta[p, c] + dev), inv_gamma) - t0[c]
                delta = dd - dm[c]
                dm[c] += delta * inv
                d2[c] += delta * (dd - dm[c])
        for c in range(C):
            dev_mean[p, c] = am[c]
            dev_m2[p, c] = a2[c]
            disp_mean[p, c] = dm[c]
            disp_m2[p, c] = d2[c]
        spp_mean[p] = ksum / B
        capped[p] = ncap / B


@numba.njit(cache=True, parallel=True)
def _init_states(base, pix, bidx, B, states):
    for i in prange(pix.size):
        states[i] = _stream_start(base, pix[i], B, bidx[i])


@numba.njit(cache=True, parallel=True)
def _draw_pairs(vals, offsets, pix, active, states, ks, targets, s1, s2):
    for i in prange(pix.size):
        if not active[i]:
            continue
        p = pix[i]
        lo = offsets[p]
        states[i], ks[i] = _draw(vals, lo, offsets[p + 1] - lo, states[i], ks[i], targets[i], s1[i], s2[i])


def _bootstrap_generic(vals, offsets, theta, base, B, rule, tq, op, out):
    """The same algorithm for a tone operator without a native code: numba
    draws (the very same random streams as the kernel), numpy decides."""
    dev_mean, dev_m2, disp_mean, disp_m2, spp_mean, capped = out
    C = vals.shape[1]
    P = offsets.size - 1
    nonempty = np.flatnonzero(np.diff(offsets) > 0)
    chunk = max(1, 2_000_000 // max(B * C, 1))
    two_d = 2.0 * rule.tolerance
    e, g = float(rule.exposure), float(rule.gamma)
    for a in range(0, nonempty.size, chunk):
        pixels = nonempty[a:a + chunk]
        pix = np.repeat(pixels, B)
        bidx = np.tile(np.arange(B, dtype=np.int64), pixels.size)
        states = np.empty(pix.size, np.uint64)
        _init_states(base, pix, bidx, B, states)
        ks = np.zeros(pix.size, np.int64)
        targets = np.full(pix.size, rule.min_spp, np.int64)
        s1 = np.zeros((pix.size, C))
        s2 = np.zeros((pix.size, C))
        active = np.ones(pix.size, np.bool_)
        while active.any():
            _draw_pairs(vals, offsets, pix, active, states, ks, targets, s1, s2)
            idx = np.flatnonzero(active)
            k = ks[idx].astype(np.float64)[:, None]
            m = s1[idx] / k
            var = np.maximum((s2[idx] - s1[idx] * m) / (k - 1.0), 0.0)
            h = tq[ks[idx]][:, None] * np.sqrt(var / k)
            mu = theta[pix[idx]] + m
            with np.errstate(invalid="ignore", over="ignore"):
                w = op.fn(e * (mu + h), g) - op.fn(e * (mu - h), g)
            stop = np.all(w <= two_d, axis=1) | (ks[idx] >= rule.max_spp)
            active[idx[stop]] = False
            cont = idx[~stop]
            targets[cont] = np.minimum(ks[cont] + rule.step, rule.max_spp)
        dev = (s1 / ks[:, None]).reshape(pixels.size, B, C)
        t0 = op.fn(e * theta[pixels], g)
        with np.errstate(invalid="ignore", over="ignore"):
            disp = (op.fn(e * (theta[pixels][:, None, :] + dev), g) - t0[:, None, :])
        dev_mean[pixels] = dev.mean(axis=1)
        dev_m2[pixels] = ((dev - dev_mean[pixels][:, None, :]) ** 2).sum(axis=1)
        disp_mean[pixels] = disp.mean(axis=1)
        disp_m2[pixels] = ((disp - disp_mean[pixels][:, None, :]) ** 2).sum(axis=1)
        kk = ks.reshape(pixels.size, B)
        spp_mean[pixels] = kk.mean(axis=1)
        capped[pixels] = (kk >= rule.max_spp).mean(axis=1)
    return P


# --------------------------------------------------------------------------
# Bootstrap bias: public API
# --------------------------------------------------------------------------

@dataclasses.dataclass(eq=False)
class BiasEstimate:
    """Bootstrap bias of the adaptive estimate in one space (radiance or display).

    All arrays are (H, W, C); empty pixels hold 0.

    Attributes
    ----------
    theta : ``t(F-hat)``, the pixel's sample mean (display: ``T(e t(F-hat))``).
    mean_star : ``theta-hat*(.)``, the mean of the B bootstrap estimates (Eq. 13).
    bias : ``mean_star - theta`` (Eq. 14).
    se : ``se_B``, the standard deviation of the B estimates (Eq. 15): the
        standard error of the adaptive estimate itself.
    mc_se : ``se_B / sqrt(B)``, the Monte Carlo standard error of ``bias``.
    lower, upper : ``bias -+ z mc_se`` (Sec. 5.3: the bias estimate is a sum
        of B iid variables, so it is approximately normal).
    """

    theta: np.ndarray
    mean_star: np.ndarray
    bias: np.ndarray
    se: np.ndarray
    mc_se: np.ndarray
    lower: np.ndarray
    upper: np.ndarray


@dataclasses.dataclass(eq=False)
class BootstrapBiasResult:
    """Result of :func:`bootstrap_bias`.

    Attributes
    ----------
    radiance : BiasEstimate
        Bias of the pixel mean (the value the method outputs).
    display : BiasEstimate
        Bias of the displayed value ``T(e theta-hat)`` against ``T(e theta)``.
    count : ndarray (H, W)
        Samples of each pixel's F-hat.
    mean_spp : ndarray (H, W)
        Average samples the rule drew per resample (its expected cost in
        the bootstrap world).
    capped : ndarray (H, W)
        Fraction of resamples that stopped at ``max_spp``.
    B, level, threshold, rule, seed
    """

    radiance: BiasEstimate
    display: BiasEstimate
    count: np.ndarray
    mean_spp: np.ndarray
    capped: np.ndarray
    B: int
    level: float
    threshold: float
    rule: StoppingRule
    seed: int

    @property
    def valid(self) -> np.ndarray:
        """Pixels with at least one sample (H, W)."""
        return self.count > 0

    def corrected(self, space: str = "radiance") -> np.ndarray:
        """Bias-corrected estimate ``theta-hat - bias`` (Sec. 4), (H, W, C).

        Meaningful when the samples are the adaptive run's own (then
        ``theta`` is its output).  The paper warns that the price is a
        higher variance; on a two-point pixel (tests) the correction removed
        ~60% of the bias but raised the variance by ~40% and the MSE by ~13%.
        """
        est = self._space(space)
        return est.theta - est.bias

    def correction_variance(self, space: str = "radiance") -> dict:
        """Variance figures of the correction, (H, W, C) maps.

        ``estimate_variance``: ``se_B^2`` (Eq. 15), the variance of the
        adaptive estimate.  ``mc_variance``: ``se_B^2 / B``, the variance the
        finite B adds to the corrected value.  This is only a lower bound of
        the cost: the bias estimate also varies with the sample set itself,
        which a single bootstrap cannot see per pixel (it needs a nested
        bootstrap); measure it by repetition, as the tests do.
        """
        est = self._space(space)
        return {"estimate_variance": est.se ** 2, "mc_variance": est.mc_se ** 2}

    def _space(self, space: str) -> BiasEstimate:
        if space not in ("radiance", "display"):
            raise InputError("BootstrapBiasResult", "space", f"got {space!r}; valid: radiance, display")
        return getattr(self, space)

    def maps(self) -> dict[str, np.ndarray]:
        """(H, W) maps for false-colour PNGs (channel-wise max / any)."""
        out = {"samples": self.count.astype(np.float64), "bootstrap_spp": self.mean_spp,
               "capped": self.capped}
        for space in ("radiance", "display"):
            est = self._space(space)
            out[f"{space}_abs_bias"] = np.max(np.abs(est.bias), axis=-1)
            out[f"{space}_se"] = np.max(est.se, axis=-1)
            out[f"{space}_zero_outside"] = np.any((est.lower > 0) | (est.upper < 0), axis=-1).astype(np.float64)
            out[f"{space}_possibly_above"] = np.any((est.lower < -self.threshold) | (est.upper > self.threshold),
                                                    axis=-1).astype(np.float64)
        return out

    def summary(self) -> dict:
        """Numbers over the pixels with samples (JSON-ready).

        Per space: ``frac_zero_outside`` (the interval excludes 0 in some
        channel: the bias is significant), ``frac_zero_outside_channels``
        (over pixel-channel pairs), ``frac_abs_bias_gt_threshold`` (the
        point estimate exceeds ``threshold`` in some channel),
        ``frac_definitely_below`` (every channel's interval inside
        ``(-threshold, threshold)``, the paper's "definitely less than
        1/256"), mean/max |bias|, mean se, and the mean Monte Carlo variance
        the correction adds (a lower bound of its cost, see
        :meth:`correction_variance`).
        """
        v = self.valid
        nv = int(v.sum())
        res = {"B": self.B, "level": self.level, "threshold": self.threshold, "seed": self.seed,
               "rule": self.rule.as_dict(), "pixels": int(v.size), "pixels_with_samples": nv,
               "mean_samples": float(self.count[v].mean()) if nv else 0.0,
               "mean_bootstrap_spp": float(self.mean_spp[v].mean()) if nv else 0.0,
               "frac_capped": float(self.capped[v].mean()) if nv else 0.0}
        for space in ("radiance", "display"):
            est = self._space(space)
            if nv == 0:
                res[space] = {}
                continue
            lo, hi, b = est.lower[v], est.upper[v], est.bias[v]
            out = (lo > 0) | (hi < 0)
            thr = self.threshold
            res[space] = {
                "frac_zero_outside": float(np.any(out, axis=-1).mean()),
                "frac_zero_outside_channels": float(out.mean()),
                "frac_abs_bias_gt_threshold": float(np.any(np.abs(b) > thr, axis=-1).mean()),
                "frac_definitely_below": float(np.all((lo > -thr) & (hi < thr), axis=-1).mean()),
                "mean_abs_bias": float(np.abs(b).mean()),
                "max_abs_bias": float(np.abs(b).max()),
                "mean_bias": float(b.mean()),
                "mean_se": float(est.se[v].mean()),
                "mean_mc_se": float(est.mc_se[v].mean()),
                "mean_estimate_variance": float((est.se[v] ** 2).mean()),
                "mean_correction_mc_variance": float((est.mc_se[v] ** 2).mean()),
            }
        return res


def _seed_base(seed: int) -> np.uint64:
    return np.uint64(np.random.SeedSequence(int(seed)).generate_state(1, np.uint64)[0])


def bootstrap_bias_samples(samples: PixelSamples, *, B: int = 1000, seed: int = 0,
                           rule: StoppingRule | None = None, level: float = 0.95,
                           threshold: float = 1.0 / 256.0) -> BootstrapBiasResult:
    """Bootstrap bias of the adaptive stopping rule, per pixel (Sec. 4).

    For each pixel, F-hat is the empirical distribution of its samples;
    the rule (``rule``: initial ``min_spp`` samples, then ``step`` more
    until Eq. 10 holds in every channel or ``max_spp``) is applied B times
    to samples drawn with replacement from F-hat.  Eq. (13)-(15) give the
    bias estimate and ``se_B``; the ``level`` interval is ``bias +- z
    se_B / sqrt(B)`` (Sec. 5.3).  Each (pixel, resample) has its own random
    stream derived from ``seed``: results do not depend on the thread count.

    Parameters
    ----------
    samples : PixelSamples
        From :func:`group_samples` or :func:`group_log`.
    B : int
        Resamples (the paper: 1000 for bias, 25-200 suffice for se).
    seed : int
    rule : StoppingRule, optional
        Default ``StoppingRule()`` (gamma 2.2, d = 1/256, 95%).
    level : float
        Confidence level of the bias interval.
    threshold : float
        The "visible bias" threshold (1/256), used in the summary.

    Returns
    -------
    BootstrapBiasResult

    References
    ----------
    .. [1] Tamstorf and Jensen 1997, Eq. (11)-(15), Sec. 5.3.
    .. [2] Efron and Tibshirani 1993, Ch. 10.
    """
    where = "bootstrap_bias"
    if not isinstance(samples, PixelSamples):
        raise InputError(where, "samples", f"got {type(samples).__name__}, expected PixelSamples "
                         "(see group_samples / group_log)")
    if not isinstance(B, (int, np.integer)) or isinstance(B, bool) or B < 2:
        raise InputError(where, "B", f"got {B!r}, expected an integer >= 2 (Eq. 15 divides by B - 1)")
    if not (isinstance(level, (int, float)) and 0.0 < level < 1.0):
        raise InputError(where, "level", f"got {level!r}, expected 0 < level < 1")
    if not (isinstance(threshold, (int, float)) and math.isfinite(threshold) and threshold > 0):
        raise InputError(where, "threshold", f"got {threshold!r}, expected a finite number > 0")
    rule = StoppingRule() if rule is None else rule
    if not isinstance(rule, StoppingRule):
        raise InputError(where, "rule", f"got {type(rule).__name__}, expected StoppingRule")
    op = get_tone_operator(rule.tone, where=where)
    B = int(B)
    H, W = samples.height, samples.width
    P = H * W
    C = samples.values.shape[1]
    theta = samples.means().reshape(P, C)
    # Centre each pixel's samples on its mean: the running sums then stay
    # small, so s2 - s1^2/k keeps its digits for 1e6 +- 1e-3 values.
    cnt = np.diff(samples.offsets)
    vals = np.ascontiguousarray(samples.values - np.repeat(theta, cnt, axis=0))
    tq = np.full(rule.max_spp + 1, np.inf)
    tq[2:] = sps.t.ppf(1.0 - rule.alpha / 2.0, np.arange(1, rule.max_spp))
    out = (np.zeros((P, C)), np.zeros((P, C)), np.zeros((P, C)), np.zeros((P, C)), np.zeros(P), np.zeros(P))
    base = _seed_base(seed)
    if op.code >= 0:
        _bootstrap_kernel(vals, samples.offsets, theta, base, B, int(rule.min_spp), int(rule.step),
                          int(rule.max_spp), tq, 2.0 * rule.tolerance, op.code, 1.0 / rule.gamma,
                          float(rule.exposure), _slope_table(1.0 / rule.gamma), *out)
    else:
        _bootstrap_generic(vals, samples.offsets, theta, base, B, rule, tq, op, out)
    dev_mean, dev_m2, disp_mean, disp_m2, spp_mean, capped = out
    z = float(sps.norm.ppf(0.5 + level / 2.0))
    shape = (H, W, C)

    def est(t, mean_dev, m2):
        se = np.sqrt(np.maximum(m2, 0.0) / (B - 1)).reshape(shape)
        bias = mean_dev.reshape(shape)
        mc = se / math.sqrt(B)
        return BiasEstimate(t.reshape(shape), t.reshape(shape) + bias, bias, se, mc, bias - z * mc, bias + z * mc)

    with np.errstate(invalid="ignore", over="ignore"):
        t_disp = op.fn(rule.exposure * theta, rule.gamma)
    t_disp = np.where(cnt[:, None] > 0, t_disp, 0.0)
    return BootstrapBiasResult(
        radiance=est(theta, dev_mean, dev_m2), display=est(t_disp, disp_mean, disp_m2),
        count=cnt.reshape(H, W), mean_spp=spp_mean.reshape(H, W), capped=capped.reshape(H, W),
        B=B, level=float(level), threshold=float(threshold), rule=rule, seed=int(seed))


def bootstrap_bias(positions, values, *, width: int, height: int, B: int = 1000, seed: int = 0,
                   rule: StoppingRule | None = None, level: float = 0.95, threshold: float = 1.0 / 256.0,
                   channels: Sequence[str] | None = None, nonfinite: str = "drop") -> BootstrapBiasResult:
    """Bootstrap bias of the adaptive rule from samples held in memory.

    Groups the samples by pixel (:func:`group_samples`) and calls
    :func:`bootstrap_bias_samples`; see there.
    """
    samples = group_samples(positions, values, width=width, height=height, channels=channels,
                            nonfinite=nonfinite, source="bootstrap_bias")
    return bootstrap_bias_samples(samples, B=B, seed=seed, rule=rule, level=level, threshold=threshold)


def bootstrap_bias_log(log, *, B: int = 1000, seed: int = 0, rule: StoppingRule | None = None,
                       level: float = 0.95, threshold: float = 1.0 / 256.0,
                       nonfinite: str = "drop") -> BootstrapBiasResult:
    """Bootstrap bias of the adaptive rule on a sample source (a SampleLog or SampleSet).

    Each pixel's samples (every round, in log order) form its F-hat.  For
    the log of a ``ci`` run, pass the run's rule
    (``CIMethod(**options).rule``) to estimate the bias that run had.
    """
    return bootstrap_bias_samples(group_log(log, nonfinite=nonfinite), B=B, seed=seed, rule=rule,
                                  level=level, threshold=threshold)


def exact_two_point_bias(a, b, p: float, rule: StoppingRule) -> dict:
    """Exact bias of the stopping rule for a pixel whose samples are ``b``
    with probability ``p`` and ``a`` otherwise (Eq. 11, no simulation).

    After k samples with K of them equal to ``b`` the mean is
    ``a + (b - a) K / k`` and the sample variance ``(b - a)^2 K (k - K) /
    (k (k - 1))``, so the rule's decision depends on (k, K) only.  Dynamic
    programming over the checkpoints ``min_spp, min_spp + step, ...,
    max_spp`` carries the binomial distribution of K among the paths that
    have not stopped.

    Returns
    -------
    dict
        ``theta`` (C,), ``mean`` E[theta-hat] (C,), ``bias`` (C,),
        ``display_bias`` E[T(e theta-hat)] - T(e theta) (C,), ``mean_spp``
        (expected samples) and ``p_stop_first`` (probability of stopping at
        the first checkpoint).
    """
    a = np.atleast_1d(np.asarray(a, dtype=np.float64))
    b = np.atleast_1d(np.asarray(b, dtype=np.float64))
    if a.shape != b.shape or a.ndim != 1:
        raise InputError("exact_two_point_bias", "a/b", f"shapes {a.shape}, {b.shape}; expected equal (C,)")
    if not 0.0 <= p <= 1.0:
        raise InputError("exact_two_point_bias", "p", f"got {p!r}, expected 0 <= p <= 1")
    k = rule.min_spp
    dist = sps.binom.pmf(np.arange(k + 1), k, p)
    e_mean = np.zeros_like(a)
    e_disp = np.zeros_like(a)
    e_k = 0.0
    p_first = None
    while True:
        K = np.arange(k + 1)
        mean = a[None, :] + (b - a)[None, :] * (K / k)[:, None]
        var = (b - a)[None, :] ** 2 * (K * (k - K) / (k * (k - 1.0)))[:, None]
        if k >= rule.max_spp:
            stop = np.ones(k + 1, bool)
        else:
            stop = rule.converged(mean, var, np.full(k + 1, k))
        ps = np.where(stop, dist, 0.0)
        if p_first is None:
            p_first = float(ps.sum())
        e_mean += ps @ mean
        e_disp += ps @ tone_map(mean, tone=rule.tone, gamma=rule.gamma, exposure=rule.exposure)
        e_k += ps.sum() * k
        if stop.all():
            break
        dist = np.where(stop, 0.0, dist)
        k2 = min(k + rule.step, rule.max_spp)
        step = k2 - k
        dist = np.convolve(dist, sps.binom.pmf(np.arange(step + 1), step, p))
        k = k2
    theta = a + (b - a) * p
    t_theta = tone_map(theta, tone=rule.tone, gamma=rule.gamma, exposure=rule.exposure)
    return {"theta": theta, "mean": e_mean, "bias": e_mean - theta, "display_bias": e_disp - t_theta,
            "mean_spp": float(e_k), "p_stop_first": p_first}


# --------------------------------------------------------------------------
# Chi-square normality test (Sec. 3, 5.1, Eq. 16)
# --------------------------------------------------------------------------

@dataclasses.dataclass(eq=False)
class ChiSquareResult:
    """Result of :func:`chi2_normality`.

    Attributes
    ----------
    z : ndarray (..., C)
        Pearson's statistic (Eq. 16); 0 where untestable.
    rejected : ndarray of bool (..., C)
        ``z > critical``.
    testable : ndarray of bool (..., C)
        The m estimates are not all equal (a zero-variance pixel has no
        N(mu, s^2) to test against; it is excluded from the rate).
    critical : float
        ``chi2(classes - 3)`` quantile at ``1 - alpha`` (11.07 for 8, 5%).
    df, classes, m, alpha
    """

    z: np.ndarray
    rejected: np.ndarray
    testable: np.ndarray
    critical: float
    df: int
    classes: int
    m: int
    alpha: float

    @property
    def rejection_rate(self) -> float:
        """Fraction of testable (pixel, channel) tests rejected."""
        t = self.testable
        return float(self.rejected[t].mean()) if t.any() else 0.0

    def rejection_rate_per_channel(self) -> list[float]:
        t = self.testable.reshape(-1, self.z.shape[-1])
        r = self.rejected.reshape(-1, self.z.shape[-1])
        return [float(r[t[:, c], c].mean()) if t[:, c].any() else 0.0 for c in range(t.shape[1])]

    @property
    def z_map(self) -> np.ndarray:
        """Largest z over the channels, per pixel (the Fig. 1 map)."""
        return np.max(self.z, axis=-1)

    def summary(self) -> dict:
        return {"classes": self.classes, "df": self.df, "m": self.m, "alpha": self.alpha,
                "critical": self.critical, "rejection_rate": self.rejection_rate,
                "rejection_rate_per_channel": self.rejection_rate_per_channel(),
                "tests": int(self.testable.sum()), "untestable": int((~self.testable).sum()),
                "mean_z": float(self.z[self.testable].mean()) if self.testable.any() else 0.0}


def chi2_normality(estimates, *, classes: int = 8, alpha: float = 0.05) -> ChiSquareResult:
    """Chi-square goodness-of-fit test of normality per pixel (Eq. 16).

    From m estimates of a pixel: mean mu-hat and sample variance s^2; the
    ``classes`` equiprobable classes of N(mu-hat, s^2) are delimited by its
    ``1/classes, ..., (classes-1)/classes`` quantiles; ``z = sum_i (O_i -
    m/classes)^2 / (m/classes)``.  Rejected where z exceeds the ``1 -
    alpha`` quantile of chi2 with ``classes - 3`` degrees of freedom (two
    parameters estimated), computed with scipy: 11.07 for 8 classes at 5%.

    Note: mu-hat and s^2 come from the ungrouped estimates, so under
    normality z follows chi2(classes - 3) only approximately: Chernoff and
    Lehmann [4] show its limit lies between chi2(classes-3) and
    chi2(classes-1); for 8 classes the 5% test rejects about 6% of truly
    normal pixels (5.8% at m = 100).

    Parameters
    ----------
    estimates : array_like (m, ...) or (m, ..., C)
        m independent estimates per pixel (and channel) along axis 0.
    classes : int
        Number of equiprobable classes (>= 4: the test needs df >= 1).
    alpha : float
        Level of the test.

    Returns
    -------
    ChiSquareResult
        Arrays shaped like ``estimates[0]`` (a trailing channel axis of 1 is
        added to 1-D or 2-D per-estimate shapes).

    References
    ----------
    .. [1] Tamstorf and Jensen 1997, Sec. 3 and 5.1, Eq. (16).
    .. [2] Chernoff and Lehmann 1954.
    """
    where = "chi2_normality"
    x = np.asarray(estimates, dtype=np.float64)
    if x.ndim < 2:
        raise InputError(where, "estimates", f"shape {x.shape}, expected (m, ...) with m estimates per pixel")
    if x.ndim <= 3:
        x = x[..., None]
    m = x.shape[0]
    if not isinstance(classes, (int, np.integer)) or isinstance(classes, bool) or classes < 4:
        raise InputError(where, "classes", f"got {classes!r}, expected an integer >= 4 (df = classes - 3)")
    if not (isinstance(alpha, (int, float)) and 0.0 < alpha < 1.0):
        raise InputError(where, "alpha", f"got {alpha!r}, expected 0 < alpha < 1")
    if m < 2 * classes:
        raise InputError(where, "estimates", f"{m} estimates per pixel, expected at least 2 x classes = "
                         f"{2 * classes} (the paper uses m = 100 for 8 classes)")
    if not np.isfinite(x).all():
        raise InputError(where, "estimates", f"{int((~np.isfinite(x)).sum())} non-finite value(s)")
    mu = x.mean(axis=0)
    s = x.std(axis=0, ddof=1)
    # Constant estimates (s = 0, up to rounding of the mean) have no normal
    # law to test against.
    spread = x.max(axis=0) - x.min(axis=0)
    testable = spread > 0
    bounds = sps.norm.ppf(np.arange(1, classes) / classes)
    expected = m / classes
    z = np.zeros(mu.shape)
    below_prev = np.zeros(mu.shape)
    safe_s = np.where(testable, s, 1.0)
    for i in range(classes):
        if i < classes - 1:
            # Class i is (mu + s q_{i-1}, mu + s q_i]: count x <= mu + s q_i.
            below = np.sum(x <= mu + safe_s * bounds[i], axis=0).astype(np.float64)
        else:
            below = np.full(mu.shape, float(m))
        obs = below - below_prev
        z += (obs - expected) ** 2 / expected
        below_prev = below
    z = np.where(testable, z, 0.0)
    df = classes - 3
    crit = float(sps.chi2.ppf(1.0 - alpha, df))
    return ChiSquareResult(z=z, rejected=testable & (z > crit), testable=testable, critical=crit, df=df,
                           classes=int(classes), m=int(m), alpha=float(alpha))


def repeated_estimates(renderer, *, n: int, m: int, seed: int = 0) -> np.ndarray:
    """m independent n-sample pixel means from a renderer, (m, H, W, C).

    Each estimate is its own request (``counts = n`` everywhere) with its
    own seed, so the estimates are independent even for a renderer that
    stratifies the samples within a request.
    """
    where = "repeated_estimates"
    for name, v, lo in (("n", n, 1), ("m", m, 2)):
        if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v < lo:
            raise InputError(where, name, f"got {v!r}, expected an integer >= {lo}")
    for attr in ("width", "height", "channels", "render"):
        if not hasattr(renderer, attr):
            raise InputError(where, "renderer", f"missing {attr}: expected a mcrecon.protocol.Renderer")
    w, h = int(renderer.width), int(renderer.height)
    chans = tuple(renderer.channels)
    seeds = np.random.SeedSequence(int(seed)).generate_state(int(m), np.uint32)
    counts = np.full((h, w), int(n), np.int64)
    out = np.empty((int(m), h, w, len(chans)))
    name = str(getattr(renderer, "name", type(renderer).__name__))
    for r in range(int(m)):
        req = SampleRequest(w, h, counts=counts, round_index=r, seed=int(seeds[r]))
        batch = validate_reply(req, renderer.render(req), n_channels=len(chans), renderer=name)
        st = PixelStats.from_samples(batch.positions, batch.values, width=w, height=h, channels=chans,
                                     nonfinite="raise")
        out[r] = st.mean
    return out


def normality_experiment(renderer, *, n: int = 10, m: int = 100, seed: int = 0, classes: int = 8,
                         alpha: float = 0.05) -> ChiSquareResult:
    """The paper's Sec. 5.1 experiment on any renderer.

    ``m`` independent estimates of ``n`` samples per pixel
    (:func:`repeated_estimates`), then :func:`chi2_normality`.  The paper:
    n = 10, m = 100 on a Cornell box rejects ~10% of the pixels; n = 50
    about 7%.
    """
    est = repeated_estimates(renderer, n=n, m=m, seed=seed)
    return chi2_normality(est, classes=classes, alpha=alpha)
