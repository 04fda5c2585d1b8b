"""auto's per-pixel selection: channel means of estimates, floors, the global prior, heavy tails.
"""

from __future__ import annotations


import numba
import numpy as np

from ...filters.engine import parallel_rows

from .estimates import relative_denominator_loo, sorted_neighbours8
from ...core.metrics import DEFAULT_EPS
from ...filters.masked import _smooth_masked_many, effective_counts

@numba.njit(cache=True, nogil=True)
def _chan_mean_ratio(mse, den, out):
    # out = mean over channels of mse / den: the channel terms added in order
    # from the first, then divided by C -- numpy's np.mean(axis=2) for C < 8
    h, w, c = mse.shape
    for i in range(h):
        for j in range(w):
            s = mse[i, j, 0] / den[i, j, 0]
            for ch in range(1, c):
                s += mse[i, j, ch] / den[i, j, ch]
            out[i, j] = s / c


@numba.njit(cache=True, nogil=True)
def _chan_mean(a, out):
    h, w, c = a.shape
    for i in range(h):
        for j in range(w):
            s = a[i, j, 0]
            for ch in range(1, c):
                s += a[i, j, ch]
            out[i, j] = s / c


def _mean_c(a: np.ndarray, den: np.ndarray | None = None) -> np.ndarray:
    """``np.mean(a / den, axis=2)`` (bit-identical; compiled for fewer than 8 channels)."""
    if a.shape[2] >= 8:
        return np.mean(a if den is None else a / den, axis=2)
    out = np.empty(a.shape[:2])
    if den is None:
        _chan_mean(np.ascontiguousarray(a, dtype=np.float64), out)
    else:
        _chan_mean_ratio(np.ascontiguousarray(a, dtype=np.float64), np.ascontiguousarray(den, dtype=np.float64),
                         out)
    return out


@numba.njit(cache=True, nogil=True)
def _nanmax(a, b):
    # np.maximum: NaN if either is NaN
    if a != a or b != b:
        return np.nan
    return a if a >= b else b


@numba.njit(cache=True, nogil=True)
def _floored(r, x, y, sd, den, has, z, out):
    """``max(r, mean_c max(|x - y| - z sd, 0)^2 / den)`` (0 floor where the pixel is empty), NaN as np.maximum."""
    h, w, c = x.shape
    for i in range(h):
        for j in range(w):
            s = 0.0
            for ch in range(c):
                lb = abs(x[i, j, ch] - y[i, j, ch]) - z * sd[i, j, ch]
                lb = _nanmax(lb, 0.0)
                if not has[i, j]:
                    lb = 0.0
                t = lb * lb / den[i, j, ch]
                s = t if ch == 0 else s + t
            out[i, j] = _nanmax(r[i, j], s / c)


#: Standard errors (the larger of the pixel's and its 3 x 3 neighbourhood's mean) beyond which the
#: global prior's candidate counts as biased at a pixel, which then keeps the per-pixel choice.  Above
#: the safeguard's 4: under pure noise a test at 4 fires on ~3 channels of a 128^2 RGB image, exactly
#: the pixels of largest error, where the clamped wide candidate beats any per-pixel choice.
Z_BIAS_PRIOR = 5.0
#: The global prior leaves out pixels whose 3 x 3 sample maximum exceeds this many times their mean
#: and their 3 x 3 neighbourhood's mean (rare huge samples around).  Not HEAVY_TAIL's 10: 32 exponential samples per pixel exceed 10x
#: their mean somewhere in a 3 x 3 neighbourhood at ~4 % of the pixels, 30x practically never.
HEAVY_PRIOR = 30.0


def _heavy_tailed(y: np.ndarray, hi: np.ndarray, factor: float) -> np.ndarray:
    """Per pixel and channel: the 3 x 3 sample maximum ``hi`` above ``factor`` times both ``|y|`` and the
    median of ``|y|`` over the 3 x 3 neighbourhood (edges repeated).  The median only where the first
    test fires (rare): a whole-image median filter cost 1 s at 1024^2."""
    ay = np.abs(np.where(np.isfinite(y), y, 0.0))
    out = hi > factor * ay
    idx = np.nonzero(out)
    if idx[0].size:
        pad = np.pad(ay, ((1, 1), (1, 1), (0, 0)), mode="edge")
        i, j, c = idx
        nb = np.stack([pad[i + di, j + dj, c] for di in range(3) for dj in range(3)], axis=1)
        out[idx] = hi[idx] > factor * np.median(nb, axis=1)
    return out


#: Standard errors by which a feature-guided candidate's summed estimate must undercut the best colour
#: candidate's to become the global default, and the tile (pixels) of the sums the error comes from.
#: 0.5, not 2: with albedo demodulation among the feature candidates, 2 kept NL-means the default of a
#: textured Mitsuba wall where the demodulated filter is 10 % better (sum -1.7, se 1.8); 0.5 still
#: keeps the colour default where a feature candidate's lower sum is noise (docs/methods/auto.md).
Z_GLOBAL = 0.5
BLOCK = 8


def _significantly_lower(d: np.ndarray) -> bool:
    """Whether ``sum(d) < -Z_GLOBAL * se``, se from the spread of the sums over BLOCK x BLOCK tiles."""
    h, w = d.shape
    hb, wb = -(-h // BLOCK), -(-w // BLOCK)
    pad = np.zeros((hb * BLOCK, wb * BLOCK))
    pad[:h, :w] = d
    t = pad.reshape(hb, BLOCK, wb, BLOCK).sum(axis=(1, 3)).ravel()
    if t.size < 2:
        return False
    se = float(np.sqrt(t.size) * np.std(t, ddof=1))
    return float(t.sum()) < -Z_GLOBAL * se


def _nearer_the_neighbours(cands, g, choice, y, where):
    """Per pixel of ``where``: candidate ``g``'s value no farther than the chosen candidate's from the median
    of the 8 neighbours' means (the sum over channels of the distances; edges repeated, empty neighbours'
    means 0); False elsewhere and where a neighbour's mean or a value is NaN."""
    out = np.zeros(y.shape[:2], bool)
    idx = np.nonzero(where)
    if not idx[0].size:
        return out
    i, j = idx
    chosen = np.empty((i.size, y.shape[2]))
    pick = choice[idx]
    for k in np.unique(pick):
        sel = pick == k
        chosen[sel] = cands[int(k)].image[i[sel], j[sel]]
    out[idx] = _nearer_at(np.ascontiguousarray(y, dtype=np.float64), i.astype(np.int64), j.astype(np.int64),
                          np.ascontiguousarray(cands[g].image[idx], dtype=np.float64), chosen)
    return out


@numba.njit(cache=True, nogil=True)
def _nearer_at(y, ii, jj, xg, xc):
    every = np.ones(y.shape[:2], np.bool_)
    nb = np.empty(8)
    res = np.zeros(ii.size, np.bool_)
    for p in range(ii.size):
        dg = 0.0
        dc = 0.0
        for ch in range(y.shape[2]):
            sorted_neighbours8(y, every, ii[p], jj[p], ch, nb)
            for m in range(8):
                if nb[m] != nb[m]:
                    dg = np.nan
            med = (nb[3] + nb[4]) / 2.0
            dg += abs(xg[p, ch] - med)
            dc += abs(xc[p, ch] - med)
        res[p] = dg <= dc  # False when any is NaN
    return res


def _global_prior(cands, smoothed, relm, choice, y, v, count, bounds, sigma, z, safeguard, guarded=()):
    """The per-pixel choice with the best single candidate over the image as the default.

    ``g`` = the candidate of least summed leave-one-out relative estimate
    (:func:`relative_denominator_loo`) over the pixels that vote, each
    pixel's estimate capped at ``(safeguard + 1)^2 v``: after the clamp
    into ``y +- safeguard sd`` no candidate's squared error exceeds about
    that, so a candidate that is wild at a few pixels the safeguard repairs
    is not ruled out for them.  Over ~all pixels the sums are far less
    noisy than any per-pixel estimate.  A pixel takes ``g`` unless another
    candidate k's smoothed estimate is lower by more than ``z`` standard
    errors of the smoothed difference ``raw_k - raw_g`` (local spread over
    the smoothing's effective pixels, :func:`effective_counts`: ``4 pi
    sigma^2`` inside the image, about half along its edges); among ``g`` and such candidates
    the least smoothed estimate wins (``g``'s own unfloored: its bias is the
    next test's).  Pixels keep the plain per-pixel ``choice`` where ``g``
    departs from the pixel mean by more than :data:`Z_BIAS_PRIOR` standard
    errors (evidence of bias), where rare huge samples are around or the
    pixel is far brighter than its neighbours (:data:`HEAVY_PRIOR`; there
    every estimate is least reliable, and a relative one divided by the
    neighbours' mu^2 can be 10^4 times the typical) and where
    all samples agree (v = 0: the safeguard pins them whatever is chosen),
    unless ``g`` lies no farther than the plain choice from the median of
    the 8 neighbours' means (:func:`_nearer_the_neighbours`) and no other
    candidate passed the local test (then they take ``g``); none of these
    vote.  (Giving all of them ``g`` helped the built-in checker_spot,
    0.19 -> 0.13 of the mean's error, and broke a Mitsuba scene with
    caustics through glass, 0.10 -> 0.54: one firefly that nfor, ``g``
    there, kept and the plain choice had removed.)  When ``g`` is the pixel mean (candidate 0 named ``box``) the
    plain choice stands everywhere: the
    region guard already makes the mean the default of every region
    without evidence against it (measured: a global box default cost the
    built-in caustic 15 %).  A ``guarded`` candidate (the feature-guided
    ones) is ``g`` only if its sum undercuts the best other candidate's
    significantly (:func:`_significantly_lower`): their estimates are the
    noisiest where they differ most, at texture edges.  Returns the new
    choice and the mask of pixels whose choice is ``g`` (all False when the
    prior does not apply).
    """
    from scipy.ndimage import uniform_filter

    den_loo = relative_denominator_loo(y, v, count, eps=DEFAULT_EPS)
    cap = None if safeguard is None else (safeguard + 1.0) ** 2 * v
    loo = [_mean_c(c.mse if cap is None else np.where(np.isnan(c.mse), np.nan, np.minimum(c.mse, cap)), den_loo)
           for c in cands]
    # rare huge samples: the 3 x 3 maximum far above the pixel's mean and its neighbourhood's median
    # (so that one pixel whose mean fell near 0 by chance does not count; a median, not a mean,
    # which a bright emitter beside dim pixels would dominate)
    apart = np.any(_heavy_tailed(y, bounds[1], HEAVY_PRIOR), axis=2)
    # and pixels far brighter than their neighbourhood (an emitter's edge): their relative estimates,
    # divided by the neighbours' mu^2, reach ~1e4 where the typical is ~1 (a Cornell box with a small
    # bright light: two such pixels made a 1.41 px Gaussian the whole image's default)
    with np.errstate(invalid="ignore"):
        apart |= np.any(np.maximum(y * y - v, 0.0) > HEAVY_PRIOR ** 2 * den_loo, axis=2)
    if safeguard is not None:
        apart |= ~np.any(v > 0, axis=2)
    vote = np.logical_and.reduce([np.isfinite(r) for r in loo]) & ~apart
    none = np.zeros(choice.shape, bool)
    if not vote.any():
        return choice, none
    sums = [float(np.sum(r[vote])) for r in loo]
    g = int(np.argmin(sums))
    plain = [k for k in range(len(cands)) if k not in guarded]
    if g in guarded and plain:
        # a guarded (feature-guided) candidate is the default only where its lower sum is real: lower
        # than the best other candidate's by Z_GLOBAL standard errors of the summed difference, from
        # sums over BLOCK x BLOCK tiles (neighbouring pixels' estimates are correlated)
        c = plain[int(np.argmin([sums[k] for k in plain]))]
        if not _significantly_lower(np.where(vote, loo[g] - loo[c], 0.0)):
            g = c
    if g == 0 and cands[0].name == "box":
        return choice, none
    ok = np.zeros(relm.shape, bool)
    ok[g] = True
    others = [k for k in range(len(cands)) if k != g]
    maps = []
    for k in others:
        d = loo[k] - loo[g]
        d = np.where(np.isnan(loo[k]) | np.isnan(loo[g]) | np.isinf(loo[g]), np.nan, d)
        maps += [d, d * d]
    sm = _smooth_masked_many(maps, sigma)
    # the smoothing's effective number of pixels, per pixel: about half of 4 pi sigma^2 along the
    # image's edges, a quarter in its corners (with 4 pi sigma^2 everywhere, 9 of the 16 regions of
    # flat exponential noise, 64^2 at 8 spp, 4 seeds, where a worse candidate passed the test lay
    # on the border; the flat field's error 0.00079 -> 0.00070 of the mean's, 128^2 at 32 spp)
    masks = [np.isfinite(maps[2 * i]) for i in range(len(others))]
    first = [next(a for a in range(i + 1) if np.array_equal(masks[a], masks[i])) for i in range(len(masks))]
    counts = dict(zip(sorted(set(first)), effective_counts([masks[a] for a in sorted(set(first))], sigma)))
    n_eff = {k: counts[first[i]] for i, k in enumerate(others)}  # (the masks are mostly one: filtered once)
    for i, k in enumerate(others):
        m, q = sm[2 * i], sm[2 * i + 1]
        with np.errstate(invalid="ignore", divide="ignore"):
            se = np.sqrt(np.maximum(q - m * m, 0.0) / n_eff[k])
            ok[k] = np.isfinite(m) & (m < -z * se)
    # the test's standard error: the larger of the pixel's own and its 3 x 3 neighbourhood's mean
    # (a pixel's own sample variance is often far too small under skewed noise: with exponential
    # samples at 32 spp its own alone flagged 1.7 % of a flat field at 4 sd)
    sd_test = np.sqrt(np.maximum(v, uniform_filter(np.where(np.isfinite(v), v, 0.0), size=(3, 3, 1),
                                                   mode="nearest")))
    with np.errstate(invalid="ignore"):
        biased = np.any(np.abs(cands[g].image - y) > Z_BIAS_PRIOR * sd_test, axis=2) & (count > 0)
    # g's own bias was the test above; its floor at Z_BIAS (4.6 % of pure-noise pixels) would hand
    # the pixel to any alternative that passed the z test by chance
    fin_g = np.isfinite(relm[g])
    relm = relm.copy()
    relm[g] = np.where(np.isfinite(smoothed[g]), smoothed[g], relm[g])
    c2 = np.argmin(np.where(ok, relm, np.inf), axis=0)
    # where the estimates are least reliable (rare huge samples around) g still stands, if no other
    # candidate passed the local test there, where it lies no farther than the plain choice from the
    # median of the 8 neighbours' means: a robust reference that a firefly kept by g (NFOR's
    # own-patch weights keep one) lies far from
    at_g = apart & (c2 == g)
    default = fin_g & ~biased & (~apart | _nearer_the_neighbours(cands, g, choice, y, at_g))
    out = np.where(default, c2, choice)
    return out, default & (c2 == g)


def _pick_where(choice, k, src, out):
    """``out[p] = src[p]`` where ``choice[p] == k`` (src and out (H, W, C) or (H, W), C-contiguous, raveled alike).

    Both as 2-D (pixels, values) views: one compiled kernel for images and maps (it was compiled for each).
    """
    m = choice.size
    if not out.flags.c_contiguous:
        raise ValueError("_pick_where writes into a C-contiguous out")
    _pick_rows(np.ascontiguousarray(choice, dtype=np.int64), int(k), np.ascontiguousarray(src).reshape(m, -1),
               out.reshape(m, -1))


@numba.njit(cache=True, nogil=True)
def _pick_rows(choice, k, s2, o2):
    m, n = s2.shape
    for p in range(m):
        if choice[p] == k:
            for q in range(n):
                o2[p, q] = s2[p, q]


#: A pixel's neighbourhood is heavy-tailed when the largest sample around it exceeds this many times its mean.
HEAVY_TAIL = 10.0


def _no_push_in_heavy_tails(img: np.ndarray, y: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Where the samples around a pixel are heavy-tailed, a candidate may pull it towards its neighbours, not away.

    A pixel is heavy-tailed when the largest sample of its 3 x 3
    neighbourhood (``hi``, from :func:`sample_range_bounds`) exceeds
    :data:`HEAVY_TAIL` times its mean ``y``: rare huge samples (caustics,
    small lights) are around.  There the error estimates that chose a
    candidate are least reliable, and a candidate that moves the pixel
    *further* from the median of its 8 neighbours' means than its own mean
    is (above it when the mean is above the median, or below) carries a
    neighbour's rare sample into it; the pixel keeps its own mean.  Per
    channel; at the film's border the missing neighbours repeat the edge
    (the pixel itself may count up to three times), an empty neighbour's
    mean is 0.  From pixel statistics without a sample range (a half-buffer
    pair, an EXR) ``hi`` is the 3 x 3 maximum of the pixel means, so the
    rule then fires at any edge of more than 10x contrast.  Measured (128^2, 32 spp, 5 seeds, ratio to box): caustic
    0.757 -> 0.522; soft shadow, depth of field, motion blur, hdr and flat
    within 0.1 %; Mitsuba Cornell boxes +1.5-1.7 % (docs/methods/auto.md).
    """
    # one compiled pass: the test and the 8-neighbour median only where the rule can fire
    # (the numpy formulation, kept in the tests as the reference, was 1.2 s of auto's 8 s at 1024^2)
    img = np.ascontiguousarray(img, dtype=np.float64)
    out = img.copy()
    y = np.ascontiguousarray(y, dtype=np.float64)
    hi = np.ascontiguousarray(hi, dtype=np.float64)
    every = np.ones(y.shape[:2], bool)
    # row blocks on the filters' thread pool (a parallel=True kernel cost 1.5 s of compilation on a first run)
    parallel_rows(_no_push_rows, (img, y, hi, every, HEAVY_TAIL, out), y.shape[0])
    return out


@numba.njit(cache=True, nogil=True)
def _no_push_rows(img, y, hi, every, heavy_tail, out, i0, i1):
    """:func:`_no_push_in_heavy_tails` per pixel and channel in rows [i0, i1) (``out`` starts as a copy of ``img``).

    The median of the 8 neighbours (edge-repeated; ``every`` all True:
    an empty neighbour's mean counts) is the mean of the 4th and 5th of
    them sorted, as :func:`numpy.median` computes it; NaN anywhere among
    them makes it NaN, and a NaN median never reverts.
    """
    h, w, c = y.shape
    nb = np.empty(8)
    for i in range(i0, i1):
        for j in range(w):
            for ch in range(c):
                yc = y[i, j, ch]
                oc = img[i, j, ch]
                if not (hi[i, j, ch] > heavy_tail * abs(yc)) or not (oc != yc):
                    continue
                sorted_neighbours8(y, every, i, j, ch, nb)
                nan = False
                for m in range(8):
                    if nb[m] != nb[m]:
                        nan = True
                if nan:
                    continue
                med = (nb[3] + nb[4]) / 2.0
                if (yc > med and oc > yc) or (yc < med and oc < yc):
                    out[i, j, ch] = yc


def _largest_remainder(pri: np.ndarray, total: int) -> np.ndarray:
    """Integer counts summing to ``total`` in proportion to ``pri`` (inf: served first, evenly)."""
    h, w = pri.shape
    flat = pri.ravel()
    counts = np.zeros(flat.size, np.int64)
    inf = np.isposinf(flat)
    if inf.any():
        idx = np.flatnonzero(inf)
        k = min(total, idx.size)
        counts[idx[:k]] += 1
        total -= k
        flat = np.where(inf, 0.0, flat)
    s = float(flat.sum())
    if total > 0:
        if not s > 0:
            flat = np.ones(flat.size)
            s = float(flat.size)
        share = flat * (total / s)
        base = np.floor(share).astype(np.int64)
        rest = total - int(base.sum())
        if rest > 0:
            order = np.argsort(-(share - base), kind="stable")[:rest]
            base[order] += 1
        counts += base
    return counts.reshape(h, w)
