"""Filter selection of ``gem`` (Rousselle et al. 2011, Secs. 4 and 6).

The error-rate parameter (:func:`check_gamma`, :func:`z_of_gamma`), the
finest scale's variance with its fill-in policy for n < 2
(:func:`mean_variance_policy`), the scale selector S of Eq. 1
(:func:`bias_coefficient`, :func:`scale_selector_terms`), the binary
stopping maps and their outlier removal (:func:`stopping_maps`,
:func:`remove_outliers`, :func:`select_from_stops`), the whole selection
(:func:`gem_select`, and the ground-truth :func:`oracle_select`) and the
MSE of the selected filters (:func:`estimate_mse`, Sec. 5).
"""

from __future__ import annotations

import dataclasses
import math

import numba
import numpy as np

from ...filters.engine import correlate_jobs, parallel_calls, separable_weights
from ...errors import InputError
from ...core.metrics import DEFAULT_EPS
from ...filters.gaussian import TRUNCATE, check_filter_inputs, gaussian_kernel
from .kernels import FilterBank, _chan_sum, _filter_bank, _uses_sub

__all__ = ['GAMMA_MAX', 'OUTLIER_RULES', 'CHANNEL_WEIGHTS', 'CHANNEL_EPS', 'check_gamma', 'confirm_pair_stops',
           'z_of_gamma', 'bias_coefficient', 'scale_selector_terms', 'stopping_maps', 'remove_outliers',
           'select_from_stops', 'GEMSelection', 'gem_select', 'oracle_select', 'estimate_mse']

#: gamma must lie in (0, GAMMA_MAX): the paper's z(gamma) is "valid in the
#: range 0 < gamma < 0.4" (and undefined from 1.9 gamma >= 1, gamma ~ 0.526).
GAMMA_MAX = 0.4
#: Outlier-removal rules of the final reconstruction (see :func:`gem_select`).
OUTLIER_RULES = ("paper", "adaptive")
#: Channel weighting of the scale selector (see :func:`stopping_maps`):
#: 'relative' divides each channel's terms by value^2 + CHANNEL_EPS (the
#: pixel's relative MSE, with the eps of :func:`mcrecon.core.metrics.relative_mse`),
#: 'absolute' sums the channels' squared errors as the paper does.
CHANNEL_WEIGHTS = ("relative", "absolute")
CHANNEL_EPS = DEFAULT_EPS


def _check_channel_weights(where: str, channel_weights) -> None:
    if channel_weights not in CHANNEL_WEIGHTS:
        raise InputError(where, "channel_weights", f"{channel_weights!r}; valid: {', '.join(CHANNEL_WEIGHTS)}")


# ----------------------------------------------------------------------------
# Parameters
# ----------------------------------------------------------------------------

def check_gamma(gamma, where: str = "method gem") -> float:
    """Validate the error-rate parameter: a real number with 0 < gamma < 0.4.

    Raises
    ------
    InputError
        Naming ``gamma`` and the valid range.
    """
    try:
        g = float(gamma)
    except (TypeError, ValueError):
        raise InputError(where, "gamma", f"{gamma!r} is not a number; expected 0 < gamma < {GAMMA_MAX} "
                         "(the target error rate of the scale selector, default 0.2)") from None
    if not (0.0 < g < GAMMA_MAX):
        raise InputError(where, "gamma", f"{gamma!r} is outside 0 < gamma < {GAMMA_MAX}: the paper's "
                         "z(gamma) = -log(1 - (1.9 gamma)^(1/sqrt 2)) is only calibrated there "
                         "(and undefined from gamma ~ 0.526); use e.g. 0.1 to 0.3, default 0.2")
    return g


def z_of_gamma(gamma) -> float:
    """Bias-term weight controlling the error rate (Sec. 4.3).

    ``z(gamma) = -log(1 - (1.9 gamma)^(1/sqrt(2)))``, valid for
    ``0 < gamma < 0.4``.

    References
    ----------
    .. [1] Rousselle et al. 2011, Sec. 4.3 "Intuitive Parameterization".
    """
    g = check_gamma(gamma)
    return -math.log(1.0 - (1.9 * g) ** (1.0 / math.sqrt(2.0)))


# ----------------------------------------------------------------------------
# Scale selector (Eq. 1)
# ----------------------------------------------------------------------------

def bias_coefficient(r_f: float, r_c: float) -> float:
    """Factor of (c - f)^2 in the approximate bias term (Sec. 4.2).

    With ``Bias[c] = (r_c^2 / r_f^2) Bias[f]`` (quadratic image, kernels
    with vanishing first moments) and ``c - f = Bias[c] - Bias[f]``:
    ``Bias[c]^2 - Bias[f]^2 = (r_c^2 + r_f^2) / (r_c^2 - r_f^2) (c - f)^2``.
    The paper prints the denominator as ``r_f^2 - r_c^2``, which would make
    the bias term of a coarser scale negative; the derivation gives the
    positive form used here (5/3 for dyadic scales, 3 for sqrt(2) steps).
    ``r_f = 0`` (the pixel filter, unbiased) gives 1: the exact squared
    difference of Sec. 6.
    """
    r_f, r_c = float(r_f), float(r_c)
    if not r_c > r_f >= 0:
        raise InputError("bias_coefficient", "r_f, r_c", f"got {r_f}, {r_c}; expected 0 <= r_f < r_c")
    return (r_c * r_c + r_f * r_f) / (r_c * r_c - r_f * r_f)


def scale_selector_terms(f, c, var_f, var_c, *, r_f: float, r_c: float, n, gamma: float | None):
    """The scale selector S of Eq. 1 and its two terms.

    ``bias = rho * z(gamma) * coef(r_f, r_c) * (c - f)^2`` with
    ``rho = 1 - 1/|P|`` (Sec. 4.3), ``variance = Var[c] - Var[f]`` and
    ``S = bias + variance``.  ``S > 0`` means "stop at the fine scale".
    ``gamma=None`` leaves the bias unweighted (the plain MSE difference of
    Eq. 1, used for MSE accumulation and ground-truth experiments).
    ``r_f = 0`` denotes the pixel filter (exact squared difference).

    Parameters
    ----------
    f, c : array_like
        Fine and coarse filtered values (same shape).
    var_f, var_c : array_like
        Their variances.
    n : array_like or float
        Samples in the pixel, |P| (rho = 1 - 1/max(n, 1)).

    Returns
    -------
    bias, variance, S : ndarray
    """
    f = np.asarray(f, dtype=np.float64)
    c = np.asarray(c, dtype=np.float64)
    d = c - f
    bias = bias_coefficient(r_f, r_c) * d * d
    if gamma is not None:
        rho = 1.0 - 1.0 / np.maximum(np.asarray(n, dtype=np.float64), 1.0)
        bias = bias * (rho * z_of_gamma(gamma))
    variance = np.asarray(var_c, dtype=np.float64) - np.asarray(var_f, dtype=np.float64)
    return bias, variance, bias + variance


def _pair_radii(bank, k):
    """(r_f, r_c) of the pair (k, k+1); scale 0 is the pixel filter (r = 0)."""
    r = bank.sigmas if bank.radii is None else bank.radii
    return (0.0 if k == 0 else float(r[k - 1])), float(r[k])


@numba.njit(cache=True, nogil=True)
def _stop_pair(e, coef, vsc, vsf, rho_z, weighted, delta, stop):
    # b = coef |c - f|^2, vterm = Var[c] - Var[f]; delta = b + vterm;
    # stop = (rho z b + vterm > 0), the arithmetic of the numpy expressions
    h, w = e.shape
    for i in range(h):
        for j in range(w):
            b = coef * e[i, j]
            vt = vsc[i, j] - vsf[i, j]
            d = b + vt
            delta[i, j] = d
            stop[i, j] = ((b * rho_z[i, j] + vt) if weighted else d) > 0


@numba.njit(cache=True, nogil=True)
def _stop_pair_abs(f, c, vsc, vsf, coef, rho_z, weighted, delta, stop):
    # _stop_pair with |c - f|^2 summed over channels in the same pass, left to right from channel 0:
    # one call per pair, the pairs on the threads.  numpy's einsum, which this replaced, may add the
    # channels in another order (3 channels: (0 + 2) + 1), so ``delta`` can differ from it in the
    # last bit; the stops, images and plans were identical on every input compared.
    h, w, nc = f.shape
    for i in range(h):
        for j in range(w):
            e = 0.0
            for ch in range(nc):
                d = c[i, j, ch] - f[i, j, ch]
                e += d * d
            b = coef * e
            vt = vsc[i, j] - vsf[i, j]
            dd = b + vt
            delta[i, j] = dd
            stop[i, j] = ((b * rho_z[i, j] + vt) if weighted else dd) > 0


#: Beyond this |value| the relative weight is computed without squaring the value.
_BIG = 1e150


@numba.njit(cache=True, nogil=True)
def _stop_pair_relative(f, c, vf, vc, eps, coef, rho_z, weighted, delta, stop):
    # per channel weight 1 / (c^2 + eps) (c: the pair's coarse value), the same
    # weight on the bias and the variance term of that channel, summed over
    # channels: S of the pixel's relative MSE; stop and delta as in _stop_pair
    h, w, nc = f.shape
    for i in range(h):
        for j in range(w):
            e = 0.0
            vt = 0.0
            for ch in range(nc):
                cc = c[i, j, ch]
                dd = cc - f[i, j, ch]
                dv = np.float64(vc[i, j, ch]) - np.float64(vf[i, j, ch])
                if abs(cc) < _BIG:
                    wt = 1.0 / (cc * cc + eps)
                    e += wt * (dd * dd)
                    vt += wt * dv
                else:
                    # cc^2 would overflow (weight 0, then 0 * inf = NaN, and a NaN S
                    # never stops: a huge value spread to its neighbours); here
                    # cc^2 + eps == cc^2, so divide by |cc| twice instead
                    t = dd / abs(cc)
                    e += t * t
                    vt += (dv / abs(cc)) / abs(cc)
            b = coef * e
            d = b + vt
            delta[i, j] = d
            stop[i, j] = ((b * rho_z[i, j] + vt) if weighted else d) > 0


def stopping_maps(bank: FilterBank, count: np.ndarray, gamma: float | None, *, channel_eps: float | None = None):
    """Binary stopping maps ``S_k > 0`` for every pair (k, k+1), and the unweighted S_k.

    Channels are combined by summing S over channels: with ``channel_eps``
    None the plain sum (the pixel's total squared error, the paper's
    choice); with a number each channel's bias and variance terms are
    divided by ``c^2 + channel_eps`` (c: that channel's value at the pair's
    coarse scale), so S estimates the change of the pixel's *relative* MSE
    summed over channels (needs a bank with per-channel variances).  The
    weights are common to both sides of the comparison, so with one channel
    (or channels proportional to each other) the decisions are unchanged.
    Returns ``stops`` (K, H, W) bool and ``delta`` (K, H, W), the estimate
    of MSE[k+1] - MSE[k] without the rho z(gamma) weight, summed over
    channels with the same channel weights.
    """
    nk = bank.n_scales - 1
    h, w = count.shape
    stops = np.zeros((nk, h, w), bool)
    delta = np.zeros((nk, h, w))
    rho_z = np.zeros((1, 1))
    if gamma is not None:
        rho_z = (1.0 - 1.0 / np.maximum(count, 1)) * z_of_gamma(gamma)
    if channel_eps is not None:
        if any(v.ndim != 3 for v in bank.var):
            raise InputError("stopping_maps", "bank", "channel_eps needs per-channel variances "
                             "(filter_bank(..., per_channel=True))")
        eps = float(channel_eps)
        for k in range(nk):
            r_f, r_c = _pair_radii(bank, k)
            _stop_pair_relative(np.ascontiguousarray(bank.values[k]), np.ascontiguousarray(bank.values[k + 1]),
                                np.ascontiguousarray(bank.var[k]), np.ascontiguousarray(bank.var[k + 1]), eps,
                                bias_coefficient(r_f, r_c), rho_z, gamma is not None, delta[k], stops[k])
        return stops, delta
    # channel sums of each scale's variance, once (each serves two pairs)
    vsum = [_chan_sum(v) for v in bank.var]
    if all(v.ndim == 3 and v.dtype == np.float64 for v in bank.values) and \
            all(v.dtype == np.float64 for v in vsum):
        # the pairs are independent: one compiled pass each, on the filters' threads
        vals = [np.ascontiguousarray(v) for v in bank.values]
        parallel_calls(_stop_pair_abs, [(vals[k], vals[k + 1], vsum[k + 1], vsum[k],
                                         bias_coefficient(*_pair_radii(bank, k)), rho_z, gamma is not None,
                                         delta[k], stops[k]) for k in range(nk)])
        return stops, delta
    dv = None
    for k in range(nk):
        r_f, r_c = _pair_radii(bank, k)
        dv = np.subtract(bank.values[k + 1], bank.values[k], out=dv)
        e = np.einsum("ijc,ijc->ij", dv, dv)
        _stop_pair(e, bias_coefficient(r_f, r_c), vsum[k + 1], vsum[k], rho_z, gamma is not None,
                   delta[k], stops[k])
    return stops, delta


# ----------------------------------------------------------------------------
# Outlier removal (Sec. 4.4, Sec. 6)
# ----------------------------------------------------------------------------

def remove_outliers(stops: np.ndarray, sigmas, *, final: bool = False, size_factor: float | None = None,
                    voters: np.ndarray | None = None, truncate: float = TRUNCATE,
                    threads: int | None = None) -> np.ndarray:
    """Filter each binary stopping map and round it back to binary (Sec. 4.4, Sec. 6).

    Map k (pair k -> k+1) is filtered with a sampled Gaussian of the
    coarse scale's sigma (``final``: twice that, Sec. 6) with the centre
    pixel's weight set to 0 ("we ignore the center pixel", Sec. 4.4),
    renormalised over the pixels that vote; the result is rounded
    (1 from 0.5 up).  With ``final`` only changes towards the coarser scale
    (from 1 to 0) are accepted.  A pixel without voting neighbours in the
    support keeps its value.

    Parameters
    ----------
    stops : ndarray (K, H, W) bool
    sigmas : sequence of float (K,)
        Gaussian scales; the coarse scale of pair k is ``sigmas[k]``.
    final : bool
        The final-reconstruction rule of Sec. 6 (twice the size, coarser-only).
    size_factor : float, optional
        Override the size factor (default 1, or 2 with ``final``).
    voters : ndarray (H, W) bool, optional
        Pixels whose decisions count in the neighbourhood vote (default
        all).  :func:`gem_select` excludes pixels that skip the search
        (zero estimated variance, no samples): they did not decide anything.
    threads : int, optional
        Worker threads for the map filtering (bit-identical for any value).
    """
    factor = size_factor if size_factor is not None else (2.0 if final else 1.0)
    out = np.empty_like(stops)
    h, w = stops.shape[1:]
    vf = np.ones((h, w)) if voters is None else voters.astype(np.float64)
    full = voters is None or bool(voters.all())
    ks = [gaussian_kernel(factor * float(sigmas[k]), truncate=truncate) for k in range(stops.shape[0])]
    ms = [stops[k] * vf for k in range(stops.shape[0])]
    # every map's vote (and, with non-voters, every weight sum) is an
    # independent convolution: one batch on the thread pool
    jobs = [(m, g, None, 0) for m, g in zip(ms, ks)]
    if not full:
        jobs += [(vf, g, None, 0) for g in ks]
    conv = correlate_jobs(jobs, threads)
    jobs = []
    for k in range(stops.shape[0]):
        g = ks[k]
        g0 = g[(g.size - 1) // 2] ** 2             # centre weight of the 2-D kernel
        wsum = separable_weights(h, w, g) if full else conv[stops.shape[0] + k]
        jobs.append((conv[k], ms[k], wsum, vf, g0, np.ascontiguousarray(stops[k]), bool(final), out[k]))
    parallel_calls(_vote, jobs, threads)  # each map's vote writes its own output
    return out


@numba.njit(cache=True, nogil=True)
def _vote(conv, m, wsum, vf, g0, stop, final, out):
    # num = conv - g0 m and den = W - g0 v (the centre left out); the rounded
    # vote num / den >= 0.5, or the own decision where nobody else votes;
    # the final rule only accepts switches towards the coarser scale
    h, w = conv.shape
    for i in range(h):
        for j in range(w):
            num = conv[i, j] - g0 * m[i, j]
            den = wsum[i, j] - g0 * vf[i, j]
            f = stop[i, j] if den <= 1e-9 else (num / den) >= 0.5
            out[i, j] = (stop[i, j] and f) if final else f


def select_from_stops(stops: np.ndarray) -> np.ndarray:
    """Selected scale: the finest k with stop_k = 1, else the coarsest (K)."""
    nk = stops.shape[0]
    any_stop = stops.any(axis=0)
    first = np.argmax(stops, axis=0)
    return np.where(any_stop, first, nk).astype(np.int64)


# ----------------------------------------------------------------------------
# Whole selection
# ----------------------------------------------------------------------------

@dataclasses.dataclass(eq=False)
class GEMSelection:
    """Result of :func:`gem_select` / :func:`oracle_select`.

    Attributes
    ----------
    bank : FilterBank
    selected : ndarray (H, W) int
        Selected scale (0 = pixel filter).
    stops_raw, stops : ndarray (K, H, W) bool or None
        Stopping maps before and after outlier removal (None for the oracle).
    mse : ndarray (H, W, C)
        Estimated MSE of every pixel's selected filter, per channel.
    image : ndarray (H, W, C)
        Values of the selected scales.
    """

    bank: FilterBank
    selected: np.ndarray
    stops_raw: np.ndarray | None
    stops: np.ndarray | None
    mse: np.ndarray | None
    image: np.ndarray


def _pick(stack_list, selected):
    """Per pixel, the entry of the selected scale's array."""
    arrs = tuple(np.ascontiguousarray(a) for a in stack_list)
    if len({(a.dtype, a.shape) for a in arrs}) != 1:
        arrs = tuple(np.ascontiguousarray(a, dtype=np.result_type(*arrs)) for a in arrs)
    out = np.empty_like(arrs[0])
    sel = np.ascontiguousarray(selected, dtype=np.int64)
    h, w = sel.shape
    c = out.size // max(h * w, 1)
    _pick_kernel(tuple(a.reshape(h * w, c) for a in arrs), sel.reshape(-1), out.reshape(h * w, c))
    return out


@numba.njit(cache=True, nogil=True)
def _pick_kernel(arrs, sel, out):
    for p in range(sel.size):
        a = arrs[sel[p]]
        for c in range(out.shape[1]):
            out[p, c] = a[p, c]


def confirm_pair_stops(stops_raw: np.ndarray, confirm_stops: int) -> np.ndarray:
    """Stops of the pairs (k, k+1) that count: a raw stop of pair k needs the raw stop of pair k+1.

    ``confirm_stops`` 0: none is confirmed (the paper); 1: the Gaussian
    pairs (k >= 1); 2: every pair, the pixel filter's (k = 0) too.  Only the
    *next* pair's raw stop is asked for (not a chain of every coarser pair),
    and the widest pair has no next pair: its stop counts unconfirmed.  So
    with 2 final scales (pairs 0 and 1) ``confirm_stops=1`` changes nothing,
    with 1 scale neither value does.  Returns a new array.
    """
    out = stops_raw.copy()
    for k in range(2 - confirm_stops if confirm_stops else out.shape[0], stops_raw.shape[0] - 1):
        out[k] &= stops_raw[k + 1]
    return out


def gem_select(base, mean_var, count, sigmas, *, gamma: float, final: bool, subpixels: int = 4,
               want_mse: bool = False, sub: np.ndarray | None = None, exact_below: float = 0.0,
               outlier_rule: str = "adaptive", zero_variance_votes: bool = False,
               channel_weights: str = "relative", confirm_stops: int = 0,
               variance_guard: bool = False, risk_radius: float = 0.0,
               guard_variance: np.ndarray | None = None) -> GEMSelection:
    """Filter selection of Secs. 4 and 6 on pixel arrays (works for 1-D signals as 1 x N images).

    Stopping maps from Eq. 1 weighted by rho z(gamma); pixels without samples
    never stop at the pixel filter nor at a scale with no data in its
    support; outlier removal (adaptive or final rule); pixels with zero
    estimated variance in every channel take the pixel filter without a
    search (no filter can have a lower estimated MSE than 0).

    Parameters
    ----------
    base, mean_var : ndarray (H, W, C)
    count : ndarray (H, W)
    sigmas : sequence of float
    gamma : float
        0 < gamma < 0.4.
    final : bool
        Final reconstruction: use the final outlier rule.
    want_mse : bool
        Also estimate the selected filters' MSE per channel (for sampling).
    sub, exact_below : see :func:`filter_bank`.
    outlier_rule : {'paper', 'adaptive'}
        Rule of the final reconstruction: 'paper' (Sec. 6: outlier filter
        twice the coarse scale, only switches towards the coarser scale
        accepted) or 'adaptive' (the adaptive phase's rule: the coarse
        scale's size, both directions).  Ignored when not ``final``.
    zero_variance_votes : bool
        Whether pixels with zero estimated variance (which skip the search)
        vote in the outlier removal of their neighbours.  Their "stop" only
        reflects their own zero variance, not the local bias; see
        ``docs/methods/gem.md`` for the measured effect (off while sampling,
        on in the final reconstruction by default in :class:`GEMMethod`).
    channel_weights : {'relative', 'absolute'}
        How S is summed over channels (:func:`stopping_maps`): 'relative'
        (default) weighs each channel by 1 / (value^2 + CHANNEL_EPS), so the
        choice minimises the pixel's relative MSE, the error the toolkit
        reports; 'absolute' is the paper's plain sum of squared errors.
    confirm_stops : {0, 1, 2}
        A stop of pair (k, k+1) enters the outlier removal only if pair
        (k+1, k+2) stops too (before outlier removal): 0 never (the paper),
        1 for the Gaussian pairs (k >= 1), 2 for every pair.  Under the
        locally quadratic model the bias difference grows with the scale,
        so a stop caused by bias is confirmed; a stop caused by noise is
        confirmed only as often as two nested tests err together.
        :class:`GEMMethod` passes 1 in its final reconstruction (measured in
        ``docs/methods/gem.md``); this function's default is 0.  The widest
        pair has no next pair and counts unconfirmed
        (:func:`confirm_pair_stops`).
    variance_guard : bool
        After the outlier removal, a pixel stops at pair (k, k+1) wherever
        the coarse scale's estimated variance is not below the fine one's
        (summed over channels, the weights of ``channel_weights``): going
        coarser there adds bias and saves no variance, so no vote may send
        it there.  Thin bright geometry (a fence's wires) otherwise bleeds
        into the dark pixels between the wires, whose neighbours outvote
        their stop (:func:`variance_guard_stops`).  Off: the paper.
    risk_radius : float
        > 0: after the selection, clamp each pixel's scale to the maximum
        scale whose estimated error, summed over a Gaussian neighbourhood
        of this sigma (pixels), is least (:func:`.guard.risk_guard`): no
        neighbourhood ends above its pixel means' estimated error.  0: off
        (the paper).
    guard_variance : ndarray (H, W, C), optional
        A second estimate of the pixel means' variance that the selection
        did not read (the prefix halves' :meth:`~mcrecon.core.strata.PrefixHalves.mean_variance`;
        NaN where unknown): the risk guard reads the average of it and
        ``mean_var``, so its check does not share all of the luck that
        made the selection.

    Raises
    ------
    InputError
        NaN or Inf in ``base``, ``mean_var`` or the used ``sub``, a negative
        ``count`` (naming the argument and the number of bad pixels), or an
        unknown ``outlier_rule``.

    Notes
    -----
    Channels are combined by summing S over channels (weighted, see
    ``channel_weights``), one scale per pixel.  z(gamma) was calibrated by the
    paper on one channel; with independent noise in three channels the
    realised error rate departs from gamma (measured in the tests).
    """
    count = np.asarray(count)
    if outlier_rule not in OUTLIER_RULES:
        raise InputError("gem_select", "outlier_rule", f"{outlier_rule!r}; valid: {', '.join(OUTLIER_RULES)}")
    if confirm_stops not in (0, 1, 2):
        raise InputError("gem_select", "confirm_stops", f"{confirm_stops!r}; valid: 0, 1, 2")
    _check_channel_weights("gem_select", channel_weights)
    relative = channel_weights == "relative" and np.ndim(base) == 3 and np.shape(base)[2] > 1
    check_filter_inputs("gem_select", base, mean_var, count, sub=sub if _uses_sub(sub, sigmas, exact_below) else None)
    if not (risk_radius >= 0 and math.isfinite(risk_radius)):
        raise InputError("gem_select", "risk_radius", f"{risk_radius!r}; expected a finite number >= 0 (0: off)")
    guard = risk_radius > 0 and np.ndim(base) == 3
    bank = _filter_bank(base, mean_var, count, sigmas, subpixels=subpixels, per_channel=want_mse or relative or guard,
                        with_n_eff=want_mse, sub=sub, exact_below=exact_below, truncate=TRUNCATE)
    stops_raw, _ = stopping_maps(bank, count, gamma, channel_eps=CHANNEL_EPS if relative else None)
    empty = count == 0
    for k in range(stops_raw.shape[0]):
        # no data of its own / in the fine scale's support: go coarser
        stops_raw[k] &= bank.weight[k] > 0
    zero_var = ~empty
    for c in range(mean_var.shape[2]):        # np.all(mean_var <= 0, axis=2), without the slow short axis
        zero_var &= mean_var[..., c] <= 0.0
    stops_in = confirm_pair_stops(stops_raw, confirm_stops)
    stops = remove_outliers(stops_in, bank.sigmas, final=final and outlier_rule == "paper",
                            voters=~empty if zero_variance_votes else ~(empty | zero_var))
    if variance_guard:
        stops |= variance_guard_stops(bank, channel_eps=CHANNEL_EPS if relative else None)
    for k in range(stops.shape[0]):
        stops[k] &= bank.weight[k] > 0
    stops[0] |= zero_var
    selected = select_from_stops(stops)
    image = _pick(bank.values, selected)
    if guard:
        from .guard import risk_guard
        gv = None
        if guard_variance is not None:
            v0 = np.asarray(bank.var[0], dtype=np.float64)
            hv = np.asarray(guard_variance, dtype=np.float64)
            gv = np.where(np.isfinite(hv), 0.5 * (hv + v0), v0)
        selected = risk_guard(bank, selected, image, count, radius=risk_radius, subpixels=subpixels,
                              channel_eps=CHANNEL_EPS if channel_weights == "relative" else None,
                              mean_variance=gv)
        image = _pick(bank.values, selected)
    mse = estimate_mse(bank, selected, count) if want_mse else None
    return GEMSelection(bank, selected, stops_raw, stops, mse, image)


def variance_guard_stops(bank: FilterBank, *, channel_eps: float | None = None) -> np.ndarray:
    """(K, H, W) bool: where the coarse scale of pair (k, k+1) has no less estimated variance than the fine.

    The variance term of Eq. 1, ``Var[c] - Var[f]``, summed over channels
    (each divided by ``c^2 + channel_eps`` with a number, as
    :func:`stopping_maps` weighs them).  Where it is >= 0 the coarse scale
    cannot have a lower MSE (its bias term is >= 0 too), whatever the
    neighbours vote.
    """
    nk = bank.n_scales - 1
    h, w = np.shape(bank.values[0])[:2]
    out = np.zeros((nk, h, w), bool)
    for k in range(nk):
        vf, vc = np.asarray(bank.var[k], np.float64), np.asarray(bank.var[k + 1], np.float64)
        dv = vc - vf
        if dv.ndim == 3:
            if channel_eps is not None:
                c = np.asarray(bank.values[k + 1], np.float64)
                dv = dv / (c * c + channel_eps)
            dv = dv.sum(axis=2)
        out[k] = dv >= 0.0
    return out


def oracle_select(base, mean_var, count, sigmas, reference, *, subpixels: int = 4,
                  sub: np.ndarray | None = None, exact_below: float = 0.0,
                  channel_weights: str = "relative") -> GEMSelection:
    """The paper's OUR-GRD selection: exhaustive argmin of bias^2 + Var with the true bias.

    The bias of scale k is ``K_k * reference - reference`` (the reference
    filtered exactly like the data, with the same mask); the pixel filter
    is unbiased.  The per-sample variance is a property of the renderer
    that a reference image does not carry, so the variances are the
    sample estimates (Eq. 2) -- the same ones GEM uses.  The MSE is summed
    over channels for the choice (``channel_weights`` as in :func:`gem_select`:
    'relative' divides each channel by reference^2 + CHANNEL_EPS, the pixel's
    relative MSE; 'absolute' the plain sum of the paper) and kept per
    channel for sampling.

    Raises
    ------
    InputError
        NaN or Inf in ``base``, ``mean_var``, ``reference`` or the used
        ``sub``, a negative ``count`` (naming the argument and the number of
        bad pixels), or a ``reference`` of another shape than ``base``.
    """
    ref = np.asarray(reference, dtype=np.float64)
    count = np.asarray(count)
    _check_channel_weights("oracle_select", channel_weights)
    check_filter_inputs("oracle_select", base, mean_var, count, reference=ref,
                  sub=sub if _uses_sub(sub, sigmas, exact_below) else None)
    bank = _filter_bank(base, mean_var, count, sigmas, subpixels=subpixels, per_channel=True, with_n_eff=True,
                        sub=sub, exact_below=exact_below, truncate=TRUNCATE)
    rbank = _filter_bank(ref, np.zeros_like(ref), count, sigmas, subpixels=subpixels, per_channel=False,
                         with_n_eff=False, sub=None, exact_below=0.0, truncate=TRUNCATE)
    mses = []
    for k in range(bank.n_scales):
        b = rbank.values[k] - ref
        m = b * b + bank.var[k]
        m = np.where((bank.weight[k] > 0)[..., None], m, np.inf)  # no data in the support
        mses.append(m)
    if channel_weights == "relative" and ref.ndim == 3 and ref.shape[2] > 1:
        wch = 1.0 / (ref * ref + CHANNEL_EPS)
        tot = np.stack([(m * wch).sum(axis=2) for m in mses])
    else:
        tot = np.stack([m.sum(axis=2) for m in mses])
    selected = np.argmin(tot, axis=0).astype(np.int64)
    image = _pick(bank.values, selected)
    mse = _pick(mses, selected)
    return GEMSelection(bank, selected, None, None, mse, image)


# ----------------------------------------------------------------------------
# MSE of the selected filters (Sec. 5)
# ----------------------------------------------------------------------------

def estimate_mse(bank: FilterBank, selected: np.ndarray, count: np.ndarray) -> np.ndarray:
    """MSE of the selected filter per channel by accumulating Delta-MSE estimates (Sec. 5).

    ``MSE_0 = Var_0`` (the pixel filter is unbiased); ``MSE_{k+1} = MSE_k +
    bias_k + Var_{k+1} - Var_k`` with the unweighted approximate bias term
    of Eq. 1 (gamma only calibrates the decision).  An estimate below the
    selected filter's own variance is raised to it (MSE = bias^2 + Var >=
    Var).  Pixels without samples get +inf.
    """
    v0 = bank.values[0]
    if not (v0.ndim == 3 and all(v.shape == v0.shape for v in bank.var)):
        return _estimate_mse_numpy(bank, selected, count)
    h, w, c = v0.shape

    def flat(a):
        return np.ascontiguousarray(a, dtype=np.float64).reshape(h * w, c)

    sel = np.ascontiguousarray(selected, dtype=np.int64).reshape(-1)
    coefs = np.array([bias_coefficient(*_pair_radii(bank, k)) for k in range(bank.n_scales - 1)])
    out = np.empty((h * w, c))
    _mse_kernel(tuple(flat(v) for v in bank.values), tuple(flat(v) for v in bank.var), coefs, sel, out)
    out[np.asarray(count).reshape(-1) == 0] = np.inf
    return out.reshape(h, w, c)


@numba.njit(cache=True, nogil=True)
def _mse_kernel(values, var, coefs, sel, out):
    # MSE_0 = Var_0; MSE_{k+1} = MSE_k + coef_k (v_{k+1} - v_k)^2 + Var_{k+1} - Var_k,
    # accumulated only up to the pixel's selected scale s (the rest is never
    # read), in the order of the numpy in-place updates; out = max(MSE_s, Var_s)
    n, c = out.shape
    for p in range(n):
        s = sel[p]
        for ch in range(c):
            m = var[0][p, ch]
            for k in range(s):
                d = values[k + 1][p, ch] - values[k][p, ch]
                d = d * d
                d = d * coefs[k]
                m = m + d
                m = m + var[k + 1][p, ch]
                m = m - var[k][p, ch]
            out[p, ch] = m if s == 0 else max(m, var[s][p, ch])


def _estimate_mse_numpy(bank: FilterBank, selected: np.ndarray, count: np.ndarray) -> np.ndarray:
    # the reference formulation (any shapes numpy broadcasts)
    mse = bank.var[0].copy()
    out = mse.copy()
    for k in range(bank.n_scales - 1):
        r_f, r_c = _pair_radii(bank, k)
        dv = bank.values[k + 1] - bank.values[k]
        dv *= dv
        dv *= bias_coefficient(r_f, r_c)
        mse += dv
        mse += bank.var[k + 1]
        mse -= bank.var[k]
        sel = selected == k + 1
        out[sel] = np.maximum(mse[sel], bank.var[k + 1][sel])
    return np.where((count == 0)[..., None], np.inf, out)
