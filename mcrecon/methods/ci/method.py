"""``ci``: confidence-interval adaptive sampling on the *displayed* value.

The stopping rule of Tamstorf and Jensen (Sec. 2-3, 5): the Student-t
interval of Eq. (6) per pixel and channel, pushed through a monotone tone
operator T (Eq. 9, :mod:`mcrecon.methods.ci.tone`); a pixel is done when
``T(U) - T(L) <= 2 d`` (Eq. 10) in *every* channel.
:class:`StoppingRule`, :func:`confidence_interval`, :func:`display_width`,
:func:`stopping_rule`, :class:`CIMethod`.

The bias this rule causes and the normality it assumes are measured by
:mod:`mcrecon.methods.ci.analysis` (bootstrap bias, chi-square test).  The
equation-to-function map is in ``docs/methods/ci.md``.

References
----------
.. [1] R. Tamstorf, H. W. Jensen, "Adaptive Sampling and Bias Estimation
   in Path Tracing", Rendering Techniques '97 (Proc. 8th Eurographics
   Workshop on Rendering), 1997.
.. [2] W. Purgathofer, "A statistical method for adaptive stochastic
   sampling", Computers & Graphics 11(2), 1987.
"""

from __future__ import annotations

import dataclasses
import math
import weakref

import numba
import numpy as np
from scipy.special import stdtrit

from ...errors import InputError
from ...core.requests import SampleRequest
from ...core.stats import PixelStats
from .tone import TONE_OPERATORS, get_tone_operator, tone_map
from ..base import AdaptiveState, Method, MethodInputs, Option, RunState, uniform_counts, variant_option
from ...core.fill import fill_empty_pixels

__all__ = ["CIMethod", "StoppingRule", "t_quantile", "confidence_interval", "display_width", "stopping_rule",
           "DEFAULT_MIN_SPP", "borrow_neighbour_variance"]

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
        # Few distinct counts per image: evaluate scipy once per count (a table indexed
        # by the count: no sort of the image's counts, as np.unique would do).
        have = n[ok]
        uniq = np.flatnonzero(np.bincount(have))
        table = np.empty(int(uniq[-1]) + 1)
        # Student's t quantile: scipy.stats.t.ppf is this function (whose module would cost every
        # command that imports the methods 0.3-0.5 s)
        table[uniq] = stdtrit(uniq - 1, 1.0 - alpha / 2.0)
        out[ok] = table[have]
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
                  exposure: float = 0.0) -> np.ndarray:
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
        Exposure in stops: the radiance is scaled by ``e = 2**exposure``
        before the operator (0: unscaled).
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
    exposure: float = 0.0
    min_spp: int = DEFAULT_MIN_SPP
    step_spp: int = 0
    max_spp: int = 1024

    def __post_init__(self):
        where = "stopping rule"
        for name in ("tolerance", "gamma", "exposure"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float, np.number)) and math.isfinite(v) and (v > 0 or name == "exposure")):
                raise InputError(where, name, f"got {v!r}, expected a finite number" + ("" if name == "exposure"
                                                                                       else " > 0"))
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

    @property
    def scale(self) -> float:
        """The radiance factor ``e = 2**exposure``."""
        return 2.0 ** float(self.exposure)

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
                  tone: str = "gamma", gamma: float = 2.2, exposure: float = 0.0,
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


#: A pixel's samples count as all equal when their standard deviation is at
#: most this fraction of their mean: the Welford/Chan updates leave ~1e-16
#: relative rounding in the variance of identical values (measured: 3e-39
#: for eight samples of 3e-4), which is not a sign of a second value.
EQUAL_SAMPLES_RTOL = 1e-12


def borrow_neighbour_variance(variance, count, mean=None) -> np.ndarray:
    """Sample variances in which pixels whose samples were all equal borrow their neighbours'.

    A pixel with ``count >= 2`` samples and a sample variance of exactly 0
    in every channel takes, per channel, the largest finite sample variance
    of its 3 x 3 neighbourhood; every other pixel keeps its own.  Why: all
    ``n`` samples of a pixel on an emitter's rim or beside a caustic can
    miss the rare bright path (probability ``(1 - p)^n``), and Eq. (6)
    then gives a zero-width interval, so the paper's rule stops the pixel
    on its first ``min_spp`` samples for good.  A neighbour that caught
    the path shows the variance the pixel may have; a pixel in a region
    that is constant everywhere (all neighbours zero too) still stops.

    Parameters
    ----------
    variance : array_like (H, W, C)
        Sample variances (NaN where undefined, ``count < 2``).
    count : array_like (H, W)
    mean : array_like (H, W, C), optional
        Pixel means: a variance up to ``(EQUAL_SAMPLES_RTOL * mean)^2``
        (rounding of identical samples) counts as zero.

    Returns
    -------
    ndarray (H, W, C) float64
    """
    from scipy import ndimage

    var = np.asarray(variance, dtype=np.float64)
    n = np.asarray(count)
    limit = 0.0 if mean is None else (EQUAL_SAMPLES_RTOL * np.asarray(mean, dtype=np.float64)) ** 2
    with np.errstate(invalid="ignore"):
        zero = (n >= 2) & np.all(var <= limit, axis=-1)
    if not zero.any():
        return var
    finite = np.where(np.isfinite(var), var, 0.0)
    around = ndimage.maximum_filter(finite, size=(3, 3, 1), mode="nearest")
    return np.where(zero[..., None], around, var)


# --------------------------------------------------------------------------
# The method
# --------------------------------------------------------------------------

@dataclasses.dataclass(eq=False)
class CIRun(RunState):
    """Per-run state of :class:`CIMethod`: the widths of the last plan, reused where nothing changed."""

    cache: dict | None = None
    #: (count, mean, m2, pending) of a plan that took the shortcut: its maps are built when asked for
    diagnostics_from: tuple | None = None


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
    run_type = CIRun
    adaptive = True
    #: One round of lag (``adapt(..., pipeline=True)``) only when asked: a pixel then gets
    #: its next step before the previous one is seen, so the rule's per-pixel counts
    #: differ from the paper's (the share of emitter pixels stopping at min_spp is 0.898 with
    #: the lag against 0.90 without it, on the hdr run of tests/test_ci.py); pending samples count toward max_spp.
    #: A pixel whose initial pass is still in flight waits for it (see plan).
    pipeline = False
    #: The paper's rule (``variant="paper"``) against the measured default
    #: (docs/methods/ci.md, "Default vs paper"): zero-variance pixels borrow
    #: their neighbours' variance instead of stopping on their first samples.
    variants = {"robust": {}, "paper": {"zero_variance": "stop"}}
    options = (
        variant_option(variants),
        Option("alpha", float, 0.05, "1 - alpha is the confidence level of Eq. (6)", min=0.0, max=1.0,
               min_open=True, max_open=True),
        Option("tolerance", float, 1.0 / 256.0, "d of Eq. (10): half the allowed display width", min=0.0,
               min_open=True),
        Option("tone", str, "gamma", "tone operator T: " + ", ".join(
            f"{k} ({v.help})" for k, v in TONE_OPERATORS.items())),
        Option("gamma", float, 2.2, "display gamma of the gamma/reinhard operators", min=0.0, min_open=True),
        Option("exposure", float, 0.0, "exposure in stops before the tone operator (radiance scaled by 2**exposure)"),
        Option("min_spp", int, DEFAULT_MIN_SPP, "initial samples per pixel", min=2,
               note="Eq. 6 needs a sample variance"),
        Option("step_spp", int, 0, "samples added per round to unconverged pixels (0: min_spp)", min=0),
        Option("max_spp", int, 1024, "per-pixel cap (>= min_spp): a pixel with this many samples stops", min=2,
               max=2**31, max_open=True),
        Option("zero_variance", str, "neighbours", "pixels whose samples were all equal: 'stop' as Eq. 6 says "
               "(paper), or 'neighbours': borrow the largest sample variance of the 3x3 neighbourhood",
               ("neighbours", "stop")),
    )

    def _configure(self, params: dict) -> None:
        try:
            rule = StoppingRule(tolerance=params["tolerance"], alpha=params["alpha"], tone=params["tone"],
                                gamma=params["gamma"], exposure=params["exposure"], min_spp=params["min_spp"],
                                step_spp=params["step_spp"], max_spp=params["max_spp"])
        except InputError as exc:  # name the method, not the helper, in the message
            raise InputError(self.where, exc.field, exc.problem) from None
        self.rule = rule

    def halo(self, width, height):
        return 0  # the pixel's own mean, like box

    def reconstruct_run(self, run: RunState, inputs: MethodInputs) -> np.ndarray:
        stats = inputs.stats
        return fill_empty_pixels(stats.mean.copy(), stats.count)

    def _update_diagnostics(self, run: RunState, count: np.ndarray, widths: np.ndarray,
                            done: np.ndarray) -> np.ndarray:
        ratio = _max_channels(widths) / (2.0 * self.rule.tolerance)
        finite = np.isfinite(ratio)
        fill = float(ratio[finite].max()) if finite.any() else 0.0
        ratio = np.where(finite, ratio, fill)
        run.diagnostics["spp"] = count.astype(np.float64)
        run.diagnostics["converged"] = done.astype(np.float64)
        run.diagnostics["width_ratio"] = ratio
        return ratio

    def initial_pass(self, budget: int, pixels: int) -> int:
        """``min_spp`` (capped by ``max_spp``): Eq. 6 needs a sample variance in every pixel."""
        return min(self.rule.min_spp, self.rule.max_spp)

    def diagnostics(self, run: RunState):
        snap = getattr(run, "diagnostics_from", None)
        if snap is not None:  # the last plan took the shortcut: its maps, built now
            count, mean, m2, pending = snap
            var, widths, _ = self._evaluate(count, mean, _own_variance(count, m2))
            done = count + pending >= self.rule.max_spp  # nothing else converges below min_spp
            self._update_diagnostics(run, count, widths, done)
            run.diagnostics_from = None
        return super().diagnostics(run)

    def _evaluate(self, count, mean, own_var):
        """(variance used, display widths, any pixel borrowed) from a pixel's samples (any set of pixels)."""
        var = own_var
        if self.params["zero_variance"] == "neighbours":
            var = borrow_neighbour_variance(own_var, count, mean)
        return var, self.rule.widths(mean, var, count), var is not own_var

    def _widths(self, run: "CIRun", st: PixelStats):
        """Display widths of every pixel, recomputed only where the statistics changed since the last plan.

        A pixel's width depends on its own samples and, through the
        borrowed variance, on its 3 x 3 neighbours' sample variances: the
        pixels whose count changed, dilated by one pixel, are evaluated
        again by the same elementwise code on just those pixels; the rest
        keep their cached width.  The result is the full computation's bit
        for bit (tested); a plan costs what changed, not the image.
        Returns (own variance, widths, any pixel borrowed), arrays owned by
        the cache (read, do not modify).
        """
        n = st.count
        c = getattr(run, "cache", None)
        if c is not None and c["stats"]() is not st:
            c = None  # other statistics than the last plan's (a run's own only grow: their counts tell)
        if c is None:
            own = _own_variance(n, st.m2)
            zero = None
            var = own
            if self.params["zero_variance"] == "neighbours":
                # borrow_neighbour_variance, with the 3 x 3 maximum taken only where a pixel borrows
                zero = _zero_variance(own, n, st.mean)
                zi = np.flatnonzero(zero)
                if zi.size:
                    h, w = n.shape
                    var = own.copy()
                    var.reshape(h * w, -1)[zi] = _max_around(own, zi, h, w)
            widths = self.rule.widths(st.mean, var, n)
            run.cache = c = {"stats": weakref.ref(st), "count": n.copy(), "own": own, "widths": widths,
                             "zero": zero}
            return own, widths, zero is not None and bool(zero.any())
        changed = n != c["count"]
        if changed.mean() > 0.5:  # most pixels changed: the whole image costs less than gathers and scatters
            run.cache = None
            return self._widths(run, st)
        if changed.any():
            h, w = n.shape
            own, widths, zero = c["own"], c["widths"], c["zero"]
            ci = np.flatnonzero(changed)
            own.reshape(h * w, -1)[ci] = _own_variance(n.reshape(-1)[ci], st.m2.reshape(h * w, -1)[ci])
            c["count"][changed] = n[changed]
            if zero is not None:
                ring = np.zeros((h + 2, w + 2), bool)  # changed pixels dilated by one (3 x 3)
                for dy in range(3):
                    for dx in range(3):
                        ring[dy:dy + h, dx:dx + w] |= changed
                ri = np.flatnonzero(ring[1:h + 1, 1:w + 1])
            else:
                ri = ci
            nr = n.reshape(-1)[ri]
            mr = st.mean.reshape(h * w, -1)[ri]
            vr = own.reshape(h * w, -1)[ri]
            if zero is not None:
                zr = _zero_variance(vr, nr, mr)
                zero.reshape(-1)[ri] = zr
                if zr.any():
                    vr = vr.copy()
                    vr[zr] = _max_around(own, ri[zr], h, w)
            widths.reshape(h * w, -1)[ri] = self.rule.widths(mr, vr, nr)
        zero = c["zero"]
        return c["own"], c["widths"], zero is not None and bool(zero.any())

    def plan(self, run: RunState, state: AdaptiveState) -> SampleRequest | None:
        """After the initial pass (``min_spp`` everywhere): ``step`` more to every pixel not converged (Eq. 10).

        While every pixel is below ``min_spp`` (nothing can have converged)
        the plan needs no interval: it tops every pixel up (or adds a step
        to the pixels the round in flight tops up), exactly what the full
        rule would ask for, and builds its diagnostic maps only when asked.
        Pipelined (``state.pending``: the round in flight), a pixel whose
        initial pass is not yet seen whole gets no step (it waits for it);
        when every pixel that is not done waits, the plan asks for nothing,
        and the driver commits the round in flight and plans again.
        (Measured and rejected: every pixel getting a second uniform
        step before its initial pass is seen: +12-22 % relative MSE on 4 of
        the 6 built-in scenes, 128^2, 32 spp, 16 seeds.)
        """
        remaining = state.remaining
        st = state.stats
        rule = self.rule
        n = st.count
        # a pipelined run: samples requested but not yet in the statistics count toward the caps
        pending = state.pending if state.pending is not None else 0
        have = n + pending
        # pipelined: a pixel whose initial pass is still in flight waits for it (no blind step)
        unseen = (n < rule.min_spp) & (have > n) if state.pending is not None else None
        if remaining > 0 and int(n.max()) < rule.min_spp and int(np.max(have)) < rule.max_spp:
            # no pixel can be done: every one is topped up to min_spp or gets a step
            need = np.where(have < rule.min_spp, rule.min_spp - have, rule.step)
            need = np.minimum(need, rule.max_spp - have).astype(np.int64)
            if unseen is not None:
                need[unseen] = 0
            if int(need.sum()) <= remaining:
                run.diagnostics_from = (n.copy(), st.mean.copy(), st.m2.copy(),
                                        np.array(pending, np.int64, copy=True))
                return state.request(counts=need)  # nothing asked: every pixel waits for the round in flight
        run.diagnostics_from = None
        own_var, widths, borrowed = self._widths(run, st)
        done = (_all_channels(widths <= 2.0 * rule.tolerance) & (n >= rule.min_spp)) | (have >= rule.max_spp)
        ratio = self._update_diagnostics(run, n, widths, done)
        if remaining <= 0 or done.all():
            return None
        # Pixels below the initial count (round 0, or a budget-cut round 0)
        # are first topped up to min_spp; the others get another step.
        need = np.where(have < rule.min_spp, rule.min_spp - have, rule.step)
        need = np.minimum(need, rule.max_spp - have)
        need = np.where(done, 0, need).astype(np.int64)
        if unseen is not None:
            need[unseen] = 0
            if not need.any():
                return state.request(counts=need)  # the pixels not done all wait for their initial pass
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
        # A borrowed variance only keeps a pixel from stopping; it does not rank
        # it: pixels whose own samples show noise are served first (measured: a
        # borrowed rank sends a tight budget to the dim pixels beside an emitter
        # instead of its rim, hdr 32 spp relative MSE 5.6x box instead of 1.3x).
        if borrowed:
            # the widths of the pixels' own variances: the cached ones, but where a pixel borrowed
            zi = np.flatnonzero(run.cache["zero"])
            h, w = n.shape
            own_widths = widths.copy()
            own_widths.reshape(h * w, -1)[zi] = rule.widths(st.mean.reshape(h * w, -1)[zi],
                                                            own_var.reshape(h * w, -1)[zi], n.reshape(-1)[zi])
            ratio = _max_channels(own_widths) / (2.0 * rule.tolerance)
            ratio = np.where(np.isfinite(ratio), ratio, 0.0)
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



def _own_variance(count, m2):
    """Sample variance ``m2 / (n - 1)``, NaN for n < 2: :meth:`PixelStats.sample_variance`
    (``undefined=nan``) on any set of pixels (count (...), m2 (..., C)), elementwise alike."""
    n = np.asarray(count)[..., None]
    out = np.full(m2.shape, np.nan, dtype=np.float64)
    ok = np.broadcast_to(n > 1, out.shape)
    np.divide(np.maximum(m2, 0.0), np.maximum(n - 1, 1), out=out, where=ok)
    return out


def _zero_variance(var, count, mean):
    """The pixels :func:`borrow_neighbour_variance` lets borrow (its test, on any set of pixels)."""
    limit = (EQUAL_SAMPLES_RTOL * np.asarray(mean, dtype=np.float64)) ** 2
    with np.errstate(invalid="ignore"):
        return (np.asarray(count) >= 2) & _all_channels(var <= limit)


def _all_channels(a):
    """``np.all(a, axis=-1)`` of a boolean (..., C) array: one pass per channel (numpy's reduction over
    a short last axis is several times slower at 1024^2)."""
    out = a[..., 0].copy()
    for c in range(1, a.shape[-1]):
        out &= a[..., c]
    return out


def _max_channels(a):
    """``np.max(a, axis=-1)`` (NaN propagates alike), one pass per channel."""
    out = a[..., 0].copy()
    for c in range(1, a.shape[-1]):
        np.maximum(out, a[..., c], out=out)
    return out


def _max_around(var, flat_idx, h, w):
    """Per channel, the largest finite value of ``var`` (H, W, C) in the 3 x 3 neighbourhood of the
    pixels ``flat_idx`` (edges clamped: ``maximum_filter(mode="nearest")`` of the finite values, 0 for
    non-finite ones; a maximum is exact, so the numbers are the filter's)."""
    out = np.empty((len(flat_idx), var.shape[-1]))
    _max_around_kernel(np.ascontiguousarray(var, dtype=np.float64), np.asarray(flat_idx, np.int64), out)
    return out


@numba.njit(cache=True, nogil=True)
def _max_around_kernel(var, flat_idx, out):
    h, w, nc = var.shape
    for q in range(flat_idx.size):
        y = flat_idx[q] // w
        x = flat_idx[q] - y * w
        for c in range(nc):
            m = -np.inf
            for dy in range(-1, 2):
                yy = min(max(y + dy, 0), h - 1)
                for dx in range(-1, 2):
                    xx = min(max(x + dx, 0), w - 1)
                    v = var[yy, xx, c]
                    if not math.isfinite(v):
                        v = 0.0
                    if v > m:
                        m = v
            out[q, c] = m
