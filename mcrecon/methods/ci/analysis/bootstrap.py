"""Bootstrap estimation and correction of the bias of the ``ci`` stopping rule.

Tamstorf and Jensen, Sec. 4, Eq. (11)-(15).  Per pixel, the stopping rule
(:class:`~mcrecon.methods.ci.method.StoppingRule`) is re-run B times on resamples
drawn with replacement from the pixel's own samples (the empirical
distribution F-hat, :mod:`mcrecon.methods.ci.analysis.grouping`); the mean of the B
estimates minus ``t(F-hat)`` (the pixel's sample mean) estimates the bias.
One numba kernel, parallel over pixels, for the built-in tone operators; a
numpy path with the very same random streams for user-registered ones.
:func:`exact_two_point_bias` computes Eq. (11) exactly for a two-point
pixel (used to validate the bootstrap).

Public: :func:`bootstrap_bias` (arrays), :func:`bootstrap_bias_log` (a
sample source), :func:`bootstrap_bias_samples` (grouped samples),
:class:`BootstrapBiasResult` (with the bias-corrected estimate),
:class:`BiasEstimate`, :func:`exact_two_point_bias`.

References
----------
.. [1] R. Tamstorf, H. W. Jensen, "Adaptive Sampling and Bias Estimation
   in Path Tracing", Rendering Techniques '97 (Proc. 8th Eurographics
   Workshop on Rendering), 1997.
.. [2] B. Efron, R. J. Tibshirani, "An Introduction to the Bootstrap",
   Chapman & Hall, 1993.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Sequence

import numba
import numpy as np
from scipy import stats as sps

from ....filters.engine import parallel_rows
from ....errors import InputError
from ..method import StoppingRule
from ..tone import get_tone_operator, tone_map
from .grouping import PixelSamples, group_log, group_samples

__all__ = ["BiasEstimate", "BootstrapBiasResult", "bootstrap_bias", "bootstrap_bias_log", "bootstrap_bias_samples",
           "exact_two_point_bias"]

# --------------------------------------------------------------------------
# The numba kernel
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
    # Scalar twin of the built-in operators of mcrecon.methods.ci.tone, by their code:
    # 0 linear, 1 gamma, 2 reinhard.
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
            for half in range(2):  # the high 32 bits, then the low ones (unless the target is reached)
                if half == 1 and k >= target:
                    break
                bits = (z >> sh) if half == 0 else (z & m32)
                r = lo + np.int64((bits * nn) >> sh)
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
def _rule_ok(s1, s2, k, theta, p, tq, two_d, code, inv_gamma, scale, tab):
    """Eq. (10) in every channel, from centred running sums (same arithmetic
    as the numpy path: mean, var = m2/(k-1), h = t sqrt(var/k))."""
    for c in range(s1.size):
        m = s1[c] / k
        var = (s2[c] - s1[c] * m) / (k - 1)
        if var < 0.0:
            var = 0.0
        h = tq * math.sqrt(var / k)
        mu = theta[p, c] + m
        lo = scale * (mu - h)
        hi = scale * (mu + h)
        dec = _width_decided(code, lo, hi, inv_gamma, two_d, tab)
        if dec == 0:
            return False
        if dec == 1:
            continue
        w = _tone_scalar(code, hi, inv_gamma) - _tone_scalar(code, lo, inv_gamma)
        if not (w <= two_d):
            return False
    return True


@numba.njit(cache=True, nogil=True)
def _bootstrap_kernel(vals, offsets, theta, base, B, n0, step, max_n, tq, two_d, code, inv_gamma,
                      scale, tab, dev_mean, dev_m2, disp_mean, disp_m2, spp_mean, capped, p0, p1):
    """Pixels ``[p0, p1)``: each pixel writes only its own outputs, so blocks run on separate threads."""
    C = vals.shape[1]
    for p in range(p0, p1):
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
            t0[c] = _tone_scalar(code, scale * theta[p, c], inv_gamma)
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
                if _rule_ok(s1, s2, k, theta, p, tq[k], two_d, code, inv_gamma, scale, tab):
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
                dd = _tone_scalar(code, scale * (theta[p, c] + dev), inv_gamma) - t0[c]
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


@numba.njit(cache=True, nogil=True)
def _init_states(base, pix, bidx, B, states, i0, i1):
    for i in range(i0, i1):
        states[i] = _stream_start(base, pix[i], B, bidx[i])


@numba.njit(cache=True, nogil=True)
def _draw_pairs(vals, offsets, pix, active, states, ks, targets, s1, s2, i0, i1):
    for i in range(i0, i1):
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
    e, g = rule.scale, float(rule.gamma)
    for a in range(0, nonempty.size, chunk):
        pixels = nonempty[a:a + chunk]
        pix = np.repeat(pixels, B)
        bidx = np.tile(np.arange(B, dtype=np.int64), pixels.size)
        states = np.empty(pix.size, np.uint64)
        parallel_rows(_init_states, (base, pix, bidx, B, states), pix.size)
        ks = np.zeros(pix.size, np.int64)
        targets = np.full(pix.size, rule.min_spp, np.int64)
        s1 = np.zeros((pix.size, C))
        s2 = np.zeros((pix.size, C))
        active = np.ones(pix.size, np.bool_)
        while active.any():
            parallel_rows(_draw_pairs, (vals, offsets, pix, active, states, ks, targets, s1, s2), pix.size)
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
# Public API
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
        # pixel blocks on the filters' thread pool: each pixel has its own random streams and writes only its
        # own outputs, so the result does not depend on the blocks or the threads
        parallel_rows(_bootstrap_kernel, (vals, samples.offsets, theta, base, B, int(rule.min_spp), int(rule.step),
                                          int(rule.max_spp), tq, 2.0 * rule.tolerance, op.code, 1.0 / rule.gamma,
                                          rule.scale, _slope_table(1.0 / rule.gamma), *out), P)
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
        t_disp = op.fn(rule.scale * theta, rule.gamma)
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
