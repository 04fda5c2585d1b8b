"""Adaptive counts that complete each pixel's nets: every pixel's total a power of two.

A renderer with a per-pixel low-discrepancy sampler (an Owen-scrambled
Sobol sequence continued from the request's ``first_index``) gives a pixel
whose count is a power of two ``2^m`` a full net: its mean stands on
``2^m`` points stratified in every elementary interval.  A count between
two powers of two is the net of ``2^m`` plus the first points of the next
block, which are stratified among themselves far less: on a rare bright
component such a pixel's mean errs about as much as its last complete
net's (on checker_spot's spotlight, found by one sample in 20, the means
of 17 to 31 Sobol samples err as much as those of their first 16), so the
samples past the net are spent for little.
An adaptive allocation that hands out arbitrary counts thus loses to a
uniform render of the same budget, whose every pixel has a full net.

:func:`net_counts` rounds an allocation so that each pixel's new total is
its current count or a power of two above it: the allocation decides
which pixels deserve samples, the rounding grants them whole nets.
Stratified means err far less at the next net up from a low count than
``1/n`` says (on motion_blur a Sobol pixel at 16 samples errs 5x its error
at 32, one at 32 1.7x its error at 64), so the freed samples complete the
lowest nets first: an allocation that wants a little more everywhere
becomes uniform, and a pixel steps to 64 only once the pixels wished at 16
have their 32.  With independent samples the coarser steps cost more than
they gain, so the methods apply it where the renderer declares a
stratified sampler (``net_counts=-1``, awr's default; docs/adaptive.md).

:func:`rare_net_floor` is the net a stratified pixel needs to hold a rare
bright component its neighbourhood shows, which gem's and awr's rounds pay
first (:func:`rare_net_deficit`), and gem's greedy counts there go in whole
nets; :func:`fill_lowest` hands out samples
from the pixels of fewest samples up (gem's uniform share with
independent samples, and a round smaller than the floors it owes).

:func:`shows_structure` is the planners' significance test: where the
committed samples show no pixel whose expectation or noise differs from
the others' beyond what noise alone gives (a constant image under
homogeneous noise: the flat scene), any allocation ranks pixels by noise
and can only lose to uniform counts, so the round is :func:`even_round`'s
(whole nets lowest first for a stratified sampler, the fewest samples
first for independent ones) and the run ends at a uniform render's counts.

:func:`net_plan`'s net gate: a round in whole nets raises a pixel a net ahead at the price of two left a
net behind, which pays only where the errors it serves exceed those it leaves by far (on a wide defocus
blur they do not: awr's whole nets erred 1.12x a uniform render's).  Where the renderer declares a
stratified sampler and no neighbourhood shows a rare component, the round is :func:`even_round`'s unless
:func:`beats_even` predicts the planned totals to err less, from each pixel's error of the method's own
reconstruction of its prefix halves (:func:`halves_error`).
"""

from __future__ import annotations

import copy
import dataclasses

import numba
import numpy as np

__all__ = ["net_counts", "fill_lowest", "rare_net_floor", "state_rare_net_floor", "covering_rare_net_floor",
           "rare_net_deficit", "hit_rate", "covered_even_plan",
           "shows_structure", "even_round", "even_plan", "noise_only", "counts_with_pending", "round_cap_spp",
           "halves_error", "beats_even"]

#: Standard deviations (under Gaussian noise) a dispersion statistic must exceed its noise-only value by.
STRUCTURE_Z = 4.0
#: A reconstruction's error in whole Sobol nets falls as ``n^-NET_RATE`` (awr on depth_of_field,
#: depth_of_field-1 and checker_dof: a pixel at 16 samples errs 1.7x, one at 64 0.53-0.67x its error at 32).
NET_RATE = 0.75
#: awr's and auto's independent rounds pay the rare component's floor only where it covers more than this share
#: of the pixels (a light over most of the film: checker_spot's 0.6-0.94; a caustic's 0.21-0.29 and an emitter's
#: rim, 0.01-0.05 on hdr, keep the sampler's own ranking: docs/adaptive.md).
RARE_COVER = 0.5


def _pow2_floor(x: np.ndarray) -> np.ndarray:
    """Largest power of two <= x (x >= 1), int64."""
    out = np.ones_like(x)
    pos = x >= 1
    out[pos] = np.left_shift(1, np.floor(np.log2(x[pos].astype(np.float64))).astype(np.int64))
    # log2 of an int64 near a power of two may round either way: fix by one step
    out = np.where(out * 2 <= x, out * 2, out)
    return np.where(out > x, out // 2, out)


@numba.njit(cache=True, nogil=True)
def _grant(order, cost, left, extra):
    # whole upgrades in ``order`` while they fit; then the rest, part of an upgrade each
    for i in range(order.size):
        p = order[i]
        if cost[p] <= left:
            extra[p] += cost[p]
            left -= cost[p]
    for i in range(order.size):
        if left <= 0:
            break
        p = order[i]
        if extra[p] == 0:
            k = min(cost[p] - 1, left)
            extra[p] += k
            left -= k
    return left


def net_counts(desired: np.ndarray, current: np.ndarray) -> np.ndarray:
    """New samples per pixel (H, W) int64 summing to ``desired.sum()``, each pixel's total a power of two.

    Parameters
    ----------
    desired : ndarray (H, W) of int
        The allocation's new samples per pixel (>= 0).
    current : ndarray (H, W) of int
        Samples each pixel already has or has in flight (the index of its
        first new sample).

    Returns
    -------
    ndarray (H, W) int64
        New samples: each pixel's desired total ``T = current + desired``
        rounds down to the largest power of two ``<= T`` above ``current``
        (or ``current`` itself); the samples this frees raise the wishing
        pixels to their next power of two, the lowest ``floor`` first and
        among equal floors the largest fraction ``(T - floor) / (ceil -
        floor)`` first, while a whole step fits.  What is left then (less
        than any remaining step) goes to the next pixels in that order as
        part of their step, so the round keeps its size exactly.  Pixels
        the allocation gave nothing keep nothing.
    """
    d = np.asarray(desired, dtype=np.int64)
    c = np.asarray(current, dtype=np.int64)
    if d.shape != c.shape:
        raise ValueError(f"net_counts: desired {d.shape} and current {c.shape} differ")
    n = int(d.sum())
    if n <= 0:
        return np.zeros_like(d)
    t = c + d
    # next power of two strictly above the current count (1 for an empty pixel)
    nxt = np.where(c > 0, _pow2_floor(np.maximum(c, 1)) * 2, 1)
    lo = np.where(t >= nxt, _pow2_floor(np.maximum(t, 1)), c)
    hi = np.where(lo == c, nxt, lo * 2)
    extra = (lo - c).ravel().copy()
    frac = np.where(d > 0, (t - lo) / (hi - lo), 0.0).ravel()
    order = np.flatnonzero(frac > 0)
    # the lowest nets first (a step from 16 to 32 Sobol samples cuts a pixel's error far more than twice,
    # one from 32 to 64 far less), then the largest fraction of the step wished
    order = order[np.lexsort((-frac[order], lo.ravel()[order]))]
    left = _grant(order, (hi - lo).ravel(), n - int(extra.sum()), extra)
    if left > 0:  # every pixel with a wish is at its ceiling: the rest where it was wished most
        order = np.argsort(-d.ravel(), kind="stable")
        extra[order[: left % order.size]] += 1
        extra += left // order.size
    return extra.reshape(d.shape)


def net_round(desired: np.ndarray, current: np.ndarray, defensive: int, rng: np.random.Generator) -> np.ndarray:
    """A round's new samples per pixel: ``defensive`` samples breadth-first, then ``desired`` by :func:`net_counts`.

    The defensive part is the uniform share of a mixture in whole nets: the
    pixels of fewest samples step up to their next power of two first (ties:
    the allocation's wish, then at random), so no pixel falls a net behind
    the others while samples go where the allocation wants them.  A uniform
    spread of a share below one sample per pixel adds one sample to random
    pixels, which completes no net.

    Parameters
    ----------
    desired : ndarray (H, W) of int
        The allocation's new samples per pixel.
    current : ndarray (H, W) of int
        Samples each pixel already has or has in flight.
    defensive : int
        Samples of the round spread breadth-first.
    rng : numpy.random.Generator
        Breaks ties among pixels of equal count and wish.

    Returns
    -------
    ndarray (H, W) int64 summing to ``desired.sum() + defensive``.
    """
    d = np.asarray(desired, dtype=np.int64)
    c = np.asarray(current, dtype=np.int64)
    defensive = int(defensive)
    extra = np.zeros(d.size, np.int64)
    if defensive > 0:
        cf = c.ravel()
        nxt = np.where(cf > 0, _pow2_floor(np.maximum(cf, 1)) * 2, 1)
        # lexicographic: fewest samples, then most wished, then a random key
        order = np.lexsort((rng.random(cf.size), -d.ravel(), cf))
        left = _grant(order, nxt - cf, defensive, extra)
        if left > 0:  # a step for every pixel fitted: the rest goes to the allocation
            d = d.copy()
            d.ravel()[np.argmax(d.ravel()) if d.any() else 0] += left
    return extra.reshape(d.shape) + net_counts(d, c + extra.reshape(d.shape))


def rare_net_floor(var_mean: np.ndarray, mean: np.ndarray, count: np.ndarray, *, cap: int,
                   threshold: float) -> np.ndarray:
    """Samples per pixel (H, W) int64 a stratified pixel needs to hold a rare bright component: 0 where none shows.

    A component found with probability ``p`` (checker_spot's small light, a
    caustic) is in a pixel's net of ``2^m`` stratified samples about
    ``2^m p`` times, so below about ``1 / p`` samples a net holds it once
    or not at all and the pixel mean errs by the whole component; from a
    few times ``1 / p`` on its share is nearly exact, where independent
    samples would still err as ``s^2 / n``.  The neighbourhood's mean
    per-sample relative variance ``r`` (:func:`~mcrecon.core.safeguard.neighbourhood_mean_variance`
    over the squared 5 x 5 mean, the largest channel) reads about ``1 / p``
    where the component carries the pixel and less where other light
    dilutes it, so the floor is the power of two at or above ``2 r``,
    at most ``cap``; it applies wherever
    :func:`~mcrecon.core.safeguard.rare_component_mask` marks the
    neighbourhood (``threshold``).

    Parameters
    ----------
    var_mean, mean : ndarray (H, W, C)
        Variance of each pixel's mean and the pixel means.
    count : ndarray (H, W)
        Samples per pixel.
    cap : int
        Largest floor (a power of two: the budget's whole net per pixel).
    threshold : float
        The rare-component gate (per-sample relative variance).
    """
    from scipy.ndimage import uniform_filter
    from .safeguard import RARE_EPS, neighbourhood_mean_variance, rare_component_mask

    v = np.asarray(var_mean, dtype=np.float64)
    m = np.asarray(mean, dtype=np.float64)
    c = np.asarray(count)
    rare = rare_component_mask(v, m, c, threshold=threshold).any(axis=2)
    if not rare.any():
        return np.zeros(c.shape, np.int64)
    per_sample = neighbourhood_mean_variance(v, c) * c[..., None]
    mu = uniform_filter(m, size=(5, 5, 1), mode="nearest")
    with np.errstate(invalid="ignore", over="ignore"):
        r = np.max(np.where(np.isfinite(per_sample), per_sample / (mu * mu + RARE_EPS), 0.0), axis=2)
    want = np.ceil(np.clip(2.0 * r, 1.0, float(cap))).astype(np.int64)
    floor = _pow2_floor(want)
    floor = np.where(floor < want, floor * 2, floor)          # the power of two at or above 2 r
    return np.where(rare, np.minimum(floor, int(cap)), 0).astype(np.int64)


@numba.njit(cache=True, nogil=True)
def _given_sum(c, room, t):
    # sum(min(max(t - c, 0), room)): the samples a fill to level t hands out
    s = 0
    for i in range(c.size):
        g = t - c[i]
        if g > 0:
            s += min(g, room[i])
    return s


def fill_lowest(current: np.ndarray, n: int, rng: np.random.Generator, *,
                cap: np.ndarray | None = None) -> np.ndarray:
    """``n`` new samples per pixel (H, W) int64 that raise the pixels of fewest samples to a common level.

    The defensive share of a round: where the greedy distribution leaves
    pixels behind (a coarse filter selected from a few noisy samples reads
    a small expected reduction, however large its error), an even spread
    adds the same to every pixel and leaves them behind; filling from the
    bottom (water-filling) raises exactly those.  The level ``t`` is the
    highest with ``sum(clip(t - current, 0, cap - current)) <= n``; the
    samples left (fewer than the pixels that could rise past ``t``) go one
    each to such pixels drawn at random.

    Parameters
    ----------
    current : ndarray (H, W) of int
        Samples each pixel has (and has in flight).
    n : int
        Samples to hand out (>= 0); with ``cap``, at most ``sum(cap - current)``.
    rng : numpy.random.Generator
        Draws the pixels that take the last samples.
    cap : ndarray (H, W) of int, optional
        No pixel rises above it (a pixel at or above its cap takes nothing).
    """
    c = np.asarray(current, dtype=np.int64).ravel()
    n = int(n)
    shape = np.shape(current)
    if n <= 0 or c.size == 0:
        return np.zeros(shape, np.int64)
    top = np.full(c.size, np.iinfo(np.int64).max // 4) if cap is None else np.asarray(cap, np.int64).ravel()
    room = np.maximum(top - c, 0)
    if cap is not None and int(room.sum()) < n:
        raise ValueError(f"fill_lowest: {n} samples, room for {int(room.sum())} under the cap")

    def given(t):
        return np.minimum(np.maximum(t - c, 0), room)

    lo, hi = int(c.min()), int(c.max()) + n        # given(lo) sums to 0 <= n; given(hi) to at least n
    while lo < hi:                                  # the highest level whose fill fits
        t = (lo + hi + 1) // 2
        if _given_sum(c, room, t) <= n:             # given(t).sum(), without its temporaries
            lo = t
        else:
            hi = t - 1
    out = given(lo)
    left = n - int(out.sum())
    if left > 0:
        at = np.flatnonzero((c + out == lo) & (out < room))
        out[rng.choice(at, size=left, replace=False)] += 1
    return out.reshape(shape)


def round_cap_spp(budget: int, n_pixels: int, parts: int, floor: int) -> int:
    """Whole samples per pixel of the largest doubling round: 1 / ``parts`` of the budget, never below ``floor``
    samples (:attr:`~mcrecon.methods.base.Method.max_round_parts`, ``max_round_floor``)."""
    return max(-(-budget // (parts * n_pixels)), -(-floor // n_pixels))


def counts_with_pending(state) -> np.ndarray:
    """Samples per pixel (H, W) of an :class:`~mcrecon.methods.base.AdaptiveState`, committed or in flight
    (``pending``): what a round's counts add to."""
    return state.stats.count if state.pending is None else state.stats.count + state.pending


def state_rare_net_floor(state, *, threshold: float) -> np.ndarray:
    """:func:`rare_net_floor` (H, W) of an adaptive round's committed statistics, at most the budget's net per pixel.

    ``state`` is an :class:`~mcrecon.methods.base.AdaptiveState`; the cap is the largest power of two
    at most its average spp.
    """
    from .fill import mean_variance_policy

    st = state.stats
    spp = max(1, int(state.budget) // (state.width * state.height))
    return rare_net_floor(mean_variance_policy(st), st.mean, st.count, cap=1 << (spp.bit_length() - 1),
                          threshold=threshold)


def covering_rare_net_floor(state, *, threshold: float, min_cover: float) -> np.ndarray | None:
    """:func:`state_rare_net_floor`, or None where ``min_cover`` > 0 and the floor covers no more than that share
    of the pixels (:data:`RARE_COVER`: a light over most of the film, whose noise every pixel's estimates read)."""
    floor = state_rare_net_floor(state, threshold=threshold)
    if min_cover > 0 and np.mean(floor > 0) <= min_cover:
        return None
    return floor


def rare_net_deficit(state, *, threshold: float, min_cover: float = 0.0) -> np.ndarray | None:
    """Samples per pixel (H, W) int64 an adaptive round owes a pixel to reach its
    :func:`state_rare_net_floor`, the samples in flight counted as taken; None where ``min_cover`` > 0
    and the floor covers no more than that share of the pixels (:func:`covering_rare_net_floor`)."""
    floor = covering_rare_net_floor(state, threshold=threshold, min_cover=min_cover)
    if floor is None:
        return None
    return np.maximum(floor - counts_with_pending(state), 0).astype(np.int64)


def hit_rate(state, covered: np.ndarray) -> float:
    """Per-sample rate at which the ``covered`` pixels' samples find a rare bright component.

    ``s``, the share of the covered pixels whose own samples show it (a per-sample relative variance of 1
    or more in some channel: a pixel whose samples all missed it reads its texture's, far below), is the
    chance that ``n`` samples find it once or more, ``1 - (1 - p)^n``, so ``p = -ln(1 - s) / n`` with ``n``
    the covered pixels' median count (checker_spot at 16 samples: light probability 0.097 read as 0.098,
    0.0546 as 0.059, 0.0248 as 0.024).
    """
    from .fill import mean_variance_policy
    from .safeguard import RARE_EPS

    st = state.stats
    per_sample = mean_variance_policy(st) * st.count[..., None]
    found = np.max(per_sample / (st.mean ** 2 + RARE_EPS), axis=2) >= 1.0
    share = float(np.mean(found[covered]))
    n = float(np.median(st.count[covered]))
    if share >= 1.0:
        return np.inf
    return -np.log1p(-share) / max(n, 1.0)


def covered_even_plan(method, state, *, threshold: float, min_hit_rate: float = 0.0):
    """An independent run's round where the rare component's floor (:func:`covering_rare_net_floor` at
    ``threshold``) covers more than :data:`RARE_COVER` of the pixels and the covered pixels' samples find
    it at ``min_hit_rate`` or more (:func:`hit_rate`; 0: whatever the rate): :func:`even_plan`'s (auto's
    rounds, whose final default there is a black box whose error rises with uneven counts; awr's above its
    ``EVEN_HIT_RATE``; docs/adaptive.md).  None elsewhere, for a stratified sampler or a method's
    ``net_counts`` of 1: the method's own round."""
    if state.sampler != "independent" or method.params.get("net_counts") == 1:
        return None
    floor = covering_rare_net_floor(state, threshold=threshold, min_cover=RARE_COVER)
    if floor is None or (min_hit_rate > 0 and hit_rate(state, floor > 0) < min_hit_rate):
        return None
    return even_plan(method, state)


def net_plan(method, run, state):
    """A method's adaptive round in whole nets: :meth:`~mcrecon.methods.base.Method.round_size`'s samples,
    its ``uniform_share`` breadth-first and :meth:`place`'s counts rounded (:func:`net_round`).

    ``place`` must return counts per pixel (H, W), or None to stop the run.  The net gate: with the method's
    ``net_gate`` on (:class:`~mcrecon.methods.base.Method`), not a paper variant, a stratified sampler
    declared and no rare bright component shown (:func:`~mcrecon.core.safeguard.rare_component_mask`: the
    halves miss it), the round is :func:`even_round`'s unless :func:`beats_even` predicts the plan to err less.
    Where one shows, the round is the even one only where the method's
    :meth:`~mcrecon.methods.base.Method.even_under_rare` says so (auto: where its final default would be a black
    box, a thin vote).
    """
    n = method.round_size(state)
    if n is None:
        return None
    n_def = int(round(method.params.get("uniform_share", 0.0) * n))
    zeros = np.zeros((state.height, state.width), np.int64)
    placed = method.place(run, state, n - n_def) if n > n_def else zeros
    if placed is None:
        return None
    placed = np.asarray(placed)
    if placed.shape != zeros.shape:  # nothing placed (an empty position list)
        placed = zeros
    current = counts_with_pending(state)
    counts = net_round(placed, current, n_def, state.rng)
    if method.net_gate and method.params.get("variant") != "paper" and state.strata is not None and \
            state.sampler != "independent":
        rare = _shows_rare_component(state)
        if not rare or method.even_under_rare(run, state):
            # the even round's ties from a copy of the generator: a plan the gate keeps is the plan without it
            even = even_round(dataclasses.replace(state, rng=copy.deepcopy(state.rng)), n)
            if rare or not beats_even(halves_error(method, run, state), current + counts, current + even):
                counts = even
    return state.request(counts=counts)


def _shows_rare_component(state) -> bool:
    """Whether a pixel's neighbourhood shows a rare bright component (:func:`~mcrecon.core.safeguard.rare_component_mask`):
    there the prefix halves miss it as the pixel's samples do, and their error says nothing of it."""
    from .fill import mean_variance_policy
    from .safeguard import rare_component_mask

    st = state.stats
    return bool(rare_component_mask(mean_variance_policy(st), st.mean, st.count).any())


def halves_error(method, run, state, *, size: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """Each pixel's relative error (H, W) of the method's reconstruction of its committed prefix, and the
    prefix's samples (H, W): what :func:`beats_even` scales to a round's counts.

    The method reconstructs each of the two prefix halves (``state.strata``, each an aligned block of the
    pixel's sequence: a net of a stratified sampler) from their means, the pixels' sample variance and the
    halves' counts; ``((R_A - R_B) / 2)^2`` is then the variance of the prefix's reconstruction as the
    reconstruction smooths it (a wide defocus blur: little error left whatever a pixel's variance), over the
    squared ``size x size`` mean plus 0.01 (the relMSE's eps), averaged over the channels and over the
    ``size x size`` neighbourhood (one pixel's square is one degree of freedom).  The allocation read the
    samples' variance, not the halves' difference, so the score carries far less of the luck that made it.
    """
    import warnings

    from scipy.ndimage import uniform_filter

    st = state.stats
    mean_a, mean_b, n_a, n_b = state.strata.halves()
    var = st.sample_variance(undefined=0.0)
    images = []
    for m, k in ((mean_a, n_a), (mean_b, n_b)):
        half = st.copy()
        half.count, half.mean, half.m2 = k.astype(np.int64), m, var * np.maximum(k - 1, 0)[..., None]
        with warnings.catch_warnings():  # a half's statistics alone: a method may warn what it cannot run
            warnings.simplefilter("ignore")
            inputs = dataclasses.replace(state.inputs(), stats=half, reference=None)
            images.append(method.reconstruct_run(run, inputs))
    mu = uniform_filter(st.mean, size=(size, size, 1), mode="nearest")
    both = (n_a > 0) & (n_b > 0)
    err = np.where(both, ((0.5 * (images[0] - images[1])) ** 2 / (mu * mu + 0.01)).mean(axis=2), 0.0)
    return uniform_filter(err, size=size, mode="nearest"), (n_a + n_b).astype(np.float64)


def beats_even(error, planned: np.ndarray, even: np.ndarray, *, rate: float = NET_RATE) -> bool:
    """Whether a round's planned totals (H, W) are predicted to err less than the even round's.

    ``error`` is :func:`halves_error`'s ``(e, n)``: each pixel's error ``e`` at ``n`` samples, which at a
    total ``t`` becomes ``e (n / t)^rate``.  Both totals hold the same samples in whole nets, so the
    comparison prices the granularity the allocation pays: two pixels left a net behind for one raised a
    net ahead.  With ``rate`` below 1 a pixel's error falls slowly past its net, so an allocation beats
    the even round only where the errors it serves exceed those it leaves by far (awr on checker_dof: the
    pixels it raises to 64 samples err 8.6x those it leaves at 16 under uniform counts; on a wide defocus
    blur 1.3x).
    """
    e, n = error
    pa, pe = (float((e * (n / np.maximum(np.asarray(t, np.float64), 1.0)) ** rate).sum()) for t in (planned, even))
    return pa < pe


def shows_structure(stats, *, z: float = STRUCTURE_Z) -> bool:
    """Whether the pixels' means or per-sample variances differ beyond what noise alone gives.

    Two dispersion statistics per channel over the pixels with two samples
    or more (``k = n - 1`` degrees of freedom, pooled variance ``σ²``):
    the means' ``mean(n (m - m̄)² / σ²)`` and the variances'
    ``mean(k (s²/σ² - 1)² / 2)``; each is about 1 for a constant
    expectation under homogeneous Gaussian noise (less for lighter tails
    and for stratified samples, whose means err less than ``σ²/n``), with a
    standard deviation about ``sqrt((2 + 12/k) / N)`` over ``N`` pixels.
    Structure: either exceeds ``1 + z`` of those in any channel.
    Heavy-tailed noise (a rare component) reads as structure, so the test
    only ever withholds an allocation where the noise is homogeneous.

    Parameters
    ----------
    stats : PixelStats
        The committed samples' per-pixel count, mean and ``m2``.
    z : float
        Margin in standard deviations.
    """
    count = np.ascontiguousarray(stats.count).reshape(-1)
    c = stats.mean.shape[-1]
    mean = np.ascontiguousarray(stats.mean, dtype=np.float64).reshape(-1, c)
    m2 = np.ascontiguousarray(stats.m2, dtype=np.float64).reshape(-1, c)
    n_ok, k_sum, k_min, n_sum, m2_sum, nm_sum, lo, hi = _pooled_sums(count, mean, m2)
    if n_ok < 2:
        return True                                 # too few samples to tell: let the allocation decide
    sigma2 = m2_sum / k_sum
    live = sigma2 > 0
    if not live.any():                              # noise-free: structure only if the means differ
        return bool((hi - lo).max() > 0)
    t_mean, t_var = _dispersions(count, mean, m2, sigma2, nm_sum / n_sum, live)
    limit = 1.0 + z * np.sqrt((2.0 + 12.0 / k_min) / n_ok)
    return bool(max(t_mean[live].max(), t_var[live].max()) > limit)


@numba.njit(cache=True, nogil=True)
def _pooled_sums(count, mean, m2):
    """Over the pixels with two samples or more: their number, the summed and least ``k = n - 1``, the
    summed ``n``, and per channel the summed ``m2``, the summed ``n m`` and the means' least and greatest."""
    c = mean.shape[1]
    m2_sum = np.zeros(c)
    nm_sum = np.zeros(c)
    lo = np.full(c, np.inf)
    hi = np.full(c, -np.inf)
    n_ok = 0
    k_sum = 0.0
    n_sum = 0.0
    k_min = np.inf
    for i in range(count.shape[0]):
        n = float(count[i])
        if n < 2:
            continue
        n_ok += 1
        k_sum += n - 1.0
        n_sum += n
        k_min = min(k_min, n - 1.0)
        for j in range(c):
            m2_sum[j] += m2[i, j]
            nm_sum[j] += n * mean[i, j]
            lo[j] = min(lo[j], mean[i, j])
            hi[j] = max(hi[j], mean[i, j])
    return n_ok, k_sum, k_min, n_sum, m2_sum, nm_sum, lo, hi


@numba.njit(cache=True, nogil=True)
def _dispersions(count, mean, m2, sigma2, mbar, live):
    """Per channel (those ``live``), the means' ``mean(n (m - m̄)² / σ²)`` and the variances'
    ``mean(k (s²/σ² - 1)² / 2)`` over the pixels with two samples or more."""
    c = mean.shape[1]
    t_mean = np.zeros(c)
    t_var = np.zeros(c)
    n_ok = 0
    for i in range(count.shape[0]):
        n = float(count[i])
        if n < 2:
            continue
        n_ok += 1
        k = n - 1.0
        for j in range(c):
            if live[j]:
                d = mean[i, j] - mbar[j]
                t_mean[j] += n * d * d / sigma2[j]
                r = m2[i, j] / (k * sigma2[j]) - 1.0
                t_var[j] += k * r * r / 2.0
    return t_mean / n_ok, t_var / n_ok


def even_round(state, n: int) -> np.ndarray:
    """``n`` new samples per pixel (H, W) int64 toward a uniform render's counts, the samples in flight counted
    as taken: for a stratified sampler whole nets breadth-first (the pixels of fewest samples step up to their
    next power of two first, ties at random, over as many steps as the round holds), for independent samples
    the fewest samples first (:func:`fill_lowest`)."""
    current = counts_with_pending(state)
    if state.sampler == "independent":
        return fill_lowest(current, n, state.rng)
    c = np.asarray(current, np.int64).ravel().copy()
    out = np.zeros(c.size, np.int64)
    left = int(n)
    while left > 0:
        extra = np.zeros(c.size, np.int64)
        nxt = np.where(c > 0, _pow2_floor(np.maximum(c, 1)) * 2, 1)
        left = _grant(np.lexsort((state.rng.random(c.size), c)), nxt - c, left, extra)
        c += extra
        out += extra
    return out.reshape(np.shape(current))


def noise_only(method, state) -> bool:
    """Whether an adaptive method's round is uniform (:func:`even_plan`): the committed samples show no
    structure beyond noise (:func:`shows_structure`), the method's ``structure_test`` is on and it is not a
    paper variant."""
    return method.adaptive and method.structure_test and method.params.get("variant") != "paper" and \
        not shows_structure(state.stats)


def even_plan(method, state):
    """The request of a round of :meth:`~mcrecon.methods.base.Method.round_size`'s samples in
    :func:`even_round`'s counts (the plans' round where the samples show no structure), None when the
    budget is spent."""
    n = method.round_size(state)
    return None if n is None else state.request(counts=even_round(state, n))
