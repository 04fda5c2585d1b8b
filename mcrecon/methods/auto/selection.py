"""auto's per-pixel selection: channel means of estimates, floors, the global prior, heavy tails.
"""

from __future__ import annotations


import numba
import numpy as np

from ...filters.engine import parallel_rows

from .estimates import relative_denominator_loo
from ...core.metrics import DEFAULT_EPS
from ...filters.masked import MaskedSmoothing, effective_counts
from ...filters.order import median9, neighbour_median8, neighbour_medians8

@numba.njit(cache=True, nogil=True, inline="always")
def _chan_mean_at(a, den, i, j):
    # mean over channels of a / den at pixel (i, j): the channel terms added in order from the
    # first, then divided by C -- numpy's np.mean(axis=2) for C < 8 (den None: of a itself)
    c = a.shape[2]
    s = a[i, j, 0] if den is None else a[i, j, 0] / den[i, j, 0]
    for ch in range(1, c):
        s += a[i, j, ch] if den is None else a[i, j, ch] / den[i, j, ch]
    return s / c


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _chan_mean_rows(a, den, out, i0, i1):
    # each row's ratios in one flat loop (contiguous: vectorised), then summed per pixel
    h, w, c = a.shape
    n = w * c
    buf = np.empty(n)
    for i in range(i0, i1):
        ar = a[i].reshape(n)
        if den is None:
            for q in range(n):
                buf[q] = ar[q]
        else:
            dr = den[i].reshape(n)
            for q in range(n):
                buf[q] = ar[q] / dr[q]
        _sum_channels(buf, c, out[i])


@numba.njit(cache=True, nogil=True, inline="always")
def _sum_channels(buf, c, out_row):
    # out_row[j] = (buf[j c] + buf[j c + 1] + ...) / c, added in order from the first
    for j in range(out_row.size):
        s = buf[j * c]
        for ch in range(1, c):
            s += buf[j * c + ch]
        out_row[j] = s / c


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _pick_mean_rows(choice, k, a, den, out, i0, i1):
    # out = the channel mean of a / den where choice == k
    for i in range(i0, i1):
        for j in range(a.shape[1]):
            if choice[i, j] == k:
                out[i, j] = _chan_mean_at(a, den, i, j)


def _c64(a):
    return None if a is None else np.ascontiguousarray(a, dtype=np.float64)


def _mean_c(a: np.ndarray, den: np.ndarray | None = None) -> np.ndarray:
    """``np.mean(a / den, axis=2)`` (bit-identical; compiled for fewer than 8 channels)."""
    if a.shape[2] >= 8:
        return np.mean(a if den is None else a / den, axis=2)
    out = np.empty(a.shape[:2])
    parallel_rows(_chan_mean_rows, (_c64(a), _c64(den), out), a.shape[0])
    return out


def _pick_mean_c(choice: np.ndarray, k: int, a: np.ndarray, den: np.ndarray | None, out: np.ndarray) -> None:
    """``out[p] = _mean_c(a, den)[p]`` where ``choice[p] == k``, computed only there."""
    if a.shape[2] >= 8:
        _pick_where(choice.ravel(), k, _mean_c(a, den), out)
        return
    parallel_rows(_pick_mean_rows, (np.ascontiguousarray(choice), int(k), _c64(a), _c64(den), out),
                  a.shape[0])


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _capped_mean_rows(a, v, s, den, out, i0, i1):
    # the channel mean of np.minimum(a, s * v) / den: NaN if either is NaN, the second on ties
    h, w, c = a.shape
    n = w * c
    buf = np.empty(n)
    for i in range(i0, i1):
        ar, vr, dr = a[i].reshape(n), v[i].reshape(n), den[i].reshape(n)
        for q in range(n):
            x = ar[q]
            m = s * vr[q]
            buf[q] = (x if x < m or x != x else m) / dr[q]
        _sum_channels(buf, c, out[i])


def _capped_mean_c(a: np.ndarray, v: np.ndarray, s: float | None, den: np.ndarray) -> np.ndarray:
    """``_mean_c(np.minimum(a, s * v), den)`` (``s`` None: no cap), without the capped copy of ``a``."""
    if s is None or a.shape[2] >= 8:
        return _mean_c(a if s is None else np.where(np.isnan(a), np.nan, np.minimum(a, s * v)), den)
    out = np.empty(a.shape[:2])
    parallel_rows(_capped_mean_rows, (_c64(a), _c64(v), float(s), _c64(den), out), a.shape[0])
    return out


@numba.njit(cache=True, nogil=True)
def _nanmax(a, b):
    # NaN if either is NaN, else the larger (the first of +0 and -0, where np.maximum gives the second:
    # the kernels that compare its result, not store it, use it in place of np.maximum)
    if a != a or b != b:
        return np.nan
    return a if a >= b else b


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _floored_rows(r, x, y, sd, den, has, z, out, i0, i1):
    # rows [i0, i1) of _floored: the squared bias bounds of a row in one flat loop (vectorised), then
    # summed per pixel (an empty pixel's bound is 0: its terms 0 / den)
    h, w, c = x.shape
    n = w * c
    buf = np.empty(n)
    for i in range(i0, i1):
        xr, yr, sr, dr = x[i].reshape(n), y[i].reshape(n), sd[i].reshape(n), den[i].reshape(n)
        every = True
        for j in range(w):
            every = every and has[i, j]
        for q in range(n):
            lb = abs(xr[q] - yr[q]) - z * sr[q]
            lb = np.nan if lb != lb else (lb if lb >= 0.0 else 0.0)
            buf[q] = lb * lb / dr[q]
        for j in range(0 if every else w):
            if not has[i, j]:
                for ch in range(c):
                    buf[j * c + ch] = 0.0 / dr[j * c + ch]
        _sum_channels(buf, c, out[i])
        for j in range(w):
            out[i, j] = _nanmax(r[i, j], out[i, j])


def _floored(r, x, y, sd, den, has, z, out):
    """``out = max(r, mean_c max(|x - y| - z sd, 0)^2 / den)`` (0 floor where the pixel is empty), NaN as
    np.maximum; ``has`` the pixels with samples."""
    parallel_rows(_floored_rows, (_c64(r), _c64(x), _c64(y), _c64(sd), _c64(den), np.ascontiguousarray(has),
                                  float(z), out), x.shape[0])


@numba.njit(cache=True, nogil=True)
def _take_lower_rows(vals, k, best, idx, i0, i1):
    # where vals (NaN as +inf) < best: best = vals, idx = k
    for i in range(i0, i1):
        for j in range(vals.shape[1]):
            x = vals[i, j]
            if x < best[i, j]:
                best[i, j] = x
                idx[i, j] = k


class _FirstLeast:
    """The index of the least of maps offered one at a time (NaN counting as +inf): ``np.argmin`` of their
    stack, ties to the first, without the stack.  A pixel where every map is NaN or +inf keeps index 0."""

    def __init__(self, shape):
        self.best = np.full(shape, np.inf)
        self.index = np.zeros(shape, np.int64)

    def offer(self, k: int, vals: np.ndarray) -> None:
        parallel_rows(_take_lower_rows, (_c64(vals), int(k), self.best, self.index), vals.shape[0])


def _relative_choice(cands, den, y, sd, count, smoothing, z):
    """Every candidate's smoothed relative estimate floored by its own evidence of bias (:func:`_floored`
    at ``z`` standard errors ``sd``) as a (K, H, W) array, and the per-pixel choice (the first of least
    estimate; an undefined one, NaN, never chosen over a defined one).

    One candidate at a time: its relative map, smoothed (``smoothing``, a :class:`MaskedSmoothing`),
    floored into its plane; the maps of all at once cost more in fresh memory than in arithmetic.
    """
    h, w = count.shape
    has = np.ascontiguousarray(count > 0)
    rel = np.empty((len(cands), h, w))
    least = _FirstLeast((h, w))
    for k, c in enumerate(cands):
        _floored(smoothing([_mean_c(c.mse, den)])[0], c.image, y, sd, den, has, z, rel[k])
        least.offer(k, rel[k])
    return rel, least.index


#: Standard errors (the larger of the pixel's and its 3 x 3 neighbourhood's mean) beyond which the
#: global prior's candidate counts as biased at a pixel, which then keeps the per-pixel choice.  Above
#: the safeguard's 4: under pure noise a test at 4 fires on ~3 channels of a 128^2 RGB image, exactly
#: the pixels of largest error, where the clamped wide candidate beats any per-pixel choice.
Z_BIAS_PRIOR = 5.0
#: The global prior leaves out pixels whose 3 x 3 sample maximum exceeds this many times their mean
#: and their 3 x 3 neighbourhood's mean (rare huge samples around).  Not HEAVY_TAIL's 10: 32 exponential samples per pixel exceed 10x
#: their mean somewhere in a 3 x 3 neighbourhood at ~4 % of the pixels, 30x practically never.
HEAVY_PRIOR = 30.0


@numba.njit(cache=True, nogil=True, inline="always")
def _abs0(x):
    return abs(x) if np.isfinite(x) else 0.0


@numba.njit(cache=True, nogil=True)
def _apart_rows(y, v, hi, den_loo, heavy, bright, need_v, out, i0, i1):
    # rows [i0, i1) of _apart; |y| read as 0 where y is not finite
    h, w, c = y.shape
    for i in range(i0, i1):
        ia, ib = max(i - 1, 0), min(i + 1, h - 1)
        for j in range(w):
            ja, jb = max(j - 1, 0), min(j + 1, w - 1)
            apart = False
            any_v = False
            for ch in range(c):
                yc = y[i, j, ch]
                ay = _abs0(yc)
                if hi[i, j, ch] > heavy * ay:
                    med = median9(_abs0(y[ia, ja, ch]), _abs0(y[ia, j, ch]), _abs0(y[ia, jb, ch]),
                                  _abs0(y[i, ja, ch]), ay, _abs0(y[i, jb, ch]),
                                  _abs0(y[ib, ja, ch]), _abs0(y[ib, j, ch]), _abs0(y[ib, jb, ch]))
                    if hi[i, j, ch] > heavy * med:
                        apart = True
                if _nanmax(yc * yc - v[i, j, ch], 0.0) > bright * den_loo[i, j, ch]:
                    apart = True
                if v[i, j, ch] > 0:
                    any_v = True
            out[i, j] = apart or (need_v and not any_v)


def _apart(y: np.ndarray, v: np.ndarray, hi: np.ndarray, den_loo: np.ndarray, need_v: bool) -> np.ndarray:
    """The pixels the global prior leaves out, (H, W) bool: in any channel, rare huge samples around (the
    3 x 3 sample maximum ``hi`` above :data:`HEAVY_PRIOR` times both ``|y|`` and the median of ``|y|``
    over the 3 x 3 neighbourhood, edges repeated), or far brighter than the neighbourhood
    (``max(y^2 - v, 0)`` above ``HEAVY_PRIOR^2`` times ``den_loo``); with ``need_v`` also pixels without
    variance in any channel.  One compiled pass, the median only where the first test fires."""
    out = np.empty(y.shape[:2], bool)
    parallel_rows(_apart_rows, (_c64(y), _c64(v), _c64(hi), _c64(den_loo), HEAVY_PRIOR, HEAVY_PRIOR ** 2,
                                bool(need_v), out), y.shape[0])
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
    i, j = idx[0].astype(np.int64), idx[1].astype(np.int64)
    pick = np.ascontiguousarray(choice[idx], dtype=np.int64)
    chosen = np.empty((i.size, y.shape[2]))
    for k, c in enumerate(cands):
        _gather_at(pick, k, _c64(c.image), i, j, chosen)
    out[idx] = _nearer_at(_c64(y), i, j, np.ascontiguousarray(cands[g].image[idx], dtype=np.float64), chosen)
    return out


@numba.njit(cache=True, nogil=True)
def _gather_at(pick, k, image, ii, jj, out):
    # out[p] = image[ii[p], jj[p]] where pick[p] == k
    for p in range(pick.size):
        if pick[p] == k:
            for ch in range(image.shape[2]):
                out[p, ch] = image[ii[p], jj[p], ch]


@numba.njit(cache=True, nogil=True)
def _nearer_at(y, ii, jj, xg, xc):
    res = np.zeros(ii.size, np.bool_)
    for p in range(ii.size):
        dg = 0.0
        dc = 0.0
        for ch in range(y.shape[2]):
            med = neighbour_median8(y, ii[p], jj[p], ch)
            dg += abs(xg[p, ch] - med)
            dc += abs(xc[p, ch] - med)
        res[p] = dg <= dc  # False when any is NaN
    return res


def _global_prior(cands, smoothed, rel, choice, y, v, count, bounds, sigma, z, safeguard, guarded=()):
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

    ``smoothed(k)``: candidate k's smoothed relative estimate (asked for
    ``g``'s only); ``rel`` (K, H, W): the floored ones ``choice`` minimised
    (NaN: undefined, never the least).  Each other candidate's test runs on
    its own, one after the other (the difference maps of all of them at
    once cost more in fresh memory than their arithmetic).
    """
    den_loo = relative_denominator_loo(y, v, count, eps=DEFAULT_EPS)
    loo = [_capped_mean_c(c.mse, v, None if safeguard is None else (safeguard + 1.0) ** 2, den_loo) for c in cands]
    # rare huge samples: the 3 x 3 maximum far above the pixel's mean and its neighbourhood's median
    # (so that one pixel whose mean fell near 0 by chance does not count; a median, not a mean,
    # which a bright emitter beside dim pixels would dominate); and pixels far brighter than their
    # neighbourhood (an emitter's edge): their relative estimates, divided by the neighbours' mu^2,
    # reach ~1e4 where the typical is ~1 (a Cornell box with a small bright light: two such pixels
    # made a 1.41 px Gaussian the whole image's default)
    apart = _apart(y, v, bounds[1], den_loo, safeguard is not None)
    vote = ~apart
    for r in loo:
        vote &= np.isfinite(r)
    none = np.zeros(choice.shape, bool)
    if not vote.any():
        return choice, none
    # np.sum(r[vote]) of each, the voters gathered into one buffer (numpy's pairwise sum of the same
    # contiguous values: the same bits)
    buf = np.empty(vote.size)
    sums = [float(np.sum(buf[:_compress(r.ravel(), vote.ravel(), buf)])) for r in loo]
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
    smoothing = MaskedSmoothing(sigma)
    least = _FirstLeast(choice.shape)
    masks, n_eff = [], []
    h = choice.shape[0]
    for k in range(len(cands)):
        if k == g:
            # g's own unfloored estimate: its bias is the test below; its floor at Z_BIAS (4.6 % of
            # pure-noise pixels) would hand the pixel to any alternative that passed the z test by chance
            sg = smoothed(g)
            least.offer(g, np.where(np.isfinite(sg), sg, rel[g]))
            continue
        d, d2, mask = np.empty(choice.shape), np.empty(choice.shape), np.empty(choice.shape, bool)
        parallel_rows(_difference_rows, (loo[k], loo[g], d, d2, mask), h)
        m, q = smoothing([d, d2])
        # the smoothing's effective number of pixels, per pixel: about half of 4 pi sigma^2 along the
        # image's edges, a quarter in its corners (with 4 pi sigma^2 everywhere, 9 of the 16 regions of
        # flat exponential noise, 64^2 at 8 spp, 4 seeds, where a worse candidate passed the test lay
        # on the border; the flat field's error 0.00079 -> 0.00070 of the mean's, 128^2 at 32 spp).
        # The masks are mostly one: filtered once.
        a = next((a for a, mk in enumerate(masks) if np.array_equal(mk, mask)), None)
        if a is None:
            a = len(masks)
            masks.append(mask)
            n_eff += effective_counts([mask], sigma)
        # k's estimate where it passed its test (written over m), +inf elsewhere
        parallel_rows(_passed_rows, (m, q, n_eff[a], float(z), rel[k], m), h)
        least.offer(k, m)
    c2 = least.index
    # the test's standard error: the larger of the pixel's own and its 3 x 3 neighbourhood's mean
    # (a pixel's own sample variance is often far too small under skewed noise: with exponential
    # samples at 32 spp its own alone flagged 1.7 % of a flat field at 4 sd)
    biased = np.empty(choice.shape, bool)
    _biased(_c64(cands[g].image), _c64(y), _c64(v), Z_BIAS_PRIOR, np.ascontiguousarray(count > 0), biased)
    # where the estimates are least reliable (rare huge samples around) g still stands, if no other
    # candidate passed the local test there, where it lies no farther than the plain choice from the
    # median of the 8 neighbours' means: a robust reference that a firefly kept by g (NFOR's
    # own-patch weights keep one) lies far from
    at_g = apart & (c2 == g)
    default = np.isfinite(rel[g]) & ~biased & (~apart | _nearer_the_neighbours(cands, g, choice, y, at_g))
    out = np.where(default, c2, choice)
    return out, default & (c2 == g)


@numba.njit(cache=True, nogil=True)
def _compress(a, keep, out):
    # out[:n] = a[keep], returns n (each value written, the next one over it unless kept: no branch)
    n = 0
    for p in range(a.size):
        out[n] = a[p]
        n += keep[p]
    return n


@numba.njit(cache=True, nogil=True)
def _difference_rows(lk, lg, d, d2, mask, i0, i1):
    # d = lk - lg, NaN where either is NaN or lg is infinite; d2 = d * d; mask = d finite
    for i in range(i0, i1):
        for j in range(lk.shape[1]):
            a, b = lk[i, j], lg[i, j]
            x = np.nan if (a != a or b != b or np.isinf(b)) else a - b
            d[i, j] = x
            d2[i, j] = x * x
            mask[i, j] = np.isfinite(x)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _passed_rows(m, q, n, z, rel, out, i0, i1):
    # out = rel where m < -z se, se = sqrt(max(q - m^2, 0) / n) (m finite), else +inf
    for i in range(i0, i1):
        for j in range(m.shape[1]):
            mm = m[i, j]
            se = np.sqrt(_nanmax(q[i, j] - mm * mm, 0.0) / n[i, j])
            out[i, j] = rel[i, j] if np.isfinite(mm) & (mm < (-z) * se) else np.inf


@numba.njit(cache=True, nogil=True, inline="always")
def _neighbourhood_mean_row(x, i, c, t, r, out_row):
    # row i of _neighbourhood_mean of x (H, W * C), rows in order: t, the running sums along axis 0,
    # advanced from row i - 1 to row i; r a row buffer
    h, n = x.shape
    w = n // c
    if i == 0:
        for q in range(n):
            t[q] = ((0.0 + _finite0(x[0, q])) + _finite0(x[0, q])) + _finite0(x[min(1, h - 1), q])
    else:
        a, b = x[min(i + 1, h - 1)], x[max(i - 2, 0)]
        for q in range(n):
            t[q] += _finite0(a[q]) - _finite0(b[q])
    for q in range(n):
        r[q] = t[q] / 3.0
    for ch in range(c):
        s = ((0.0 + r[ch]) + r[ch]) + r[min(1, w - 1) * c + ch]
        out_row[ch] = s / 3.0
        for j in range(1, w):
            s += r[min(j + 1, w - 1) * c + ch] - r[max(j - 2, 0) * c + ch]
            out_row[j * c + ch] = s / 3.0


@numba.njit(cache=True, nogil=True)
def _neighbourhood_mean(v, out):
    """``scipy.ndimage.uniform_filter(where(isfinite(v), v, 0), size=(3, 3, 1), mode="nearest")`` of
    ``v`` (H, W, C), term for term as scipy computes it (so bit-identical, tested): along axis 0, then
    axis 1, a running sum ``t`` of the 3 values under the window (edges repeated; first ``((0 + x_0) +
    x_0) + x_1``, then ``t += x_new - x_old``), each output ``t / 3``, the first pass stored as float64."""
    h, w, c = v.shape
    n = w * c
    t, r = np.empty(n), np.empty(n)
    for i in range(h):
        _neighbourhood_mean_row(v.reshape(h, n), i, c, t, r, out[i].reshape(n))


@numba.njit(cache=True, nogil=True, inline="always")
def _finite0(x):
    return x if np.isfinite(x) else 0.0


@numba.njit(cache=True, nogil=True)
def _biased(x, y, v, zb, has, out):
    """Per pixel with samples: any channel with ``|x - y| > zb sqrt(max(v, v_nb))`` (NaN as np.maximum),
    ``v_nb`` the :func:`_neighbourhood_mean` of ``v``, row by row (no image of it)."""
    h, w, c = x.shape
    n = w * c
    t, r, nb = np.empty(n), np.empty(n), np.empty(n)
    for i in range(h):
        _neighbourhood_mean_row(v.reshape(h, n), i, c, t, r, nb)
        for j in range(w):
            b = False
            for ch in range(c):
                if abs(x[i, j, ch] - y[i, j, ch]) > zb * np.sqrt(_nanmax(v[i, j, ch], nb[j * c + ch])):
                    b = True
            out[i, j] = b and has[i, j]


def _compact(choice, n):
    """``choice`` as the smallest integers that hold ``n`` candidates: the picks read it once per candidate."""
    return choice.astype(np.uint8) if n <= 256 else choice


def _region_guard(cands, den, choice, keep, sigma):
    """``choice`` with the pixel mean (0) where the chosen candidates' relative estimates minus the mean's,
    smoothed (``sigma``), exceed 0, except at ``keep``; the estimates unsmoothed and unfloored, each only
    where it is chosen."""
    h, w = choice.shape
    diff = np.empty((h, w))
    pick = _compact(choice, len(cands))
    for k, c in enumerate(cands):
        _pick_mean_c(pick, k, c.mse, den, diff)
    parallel_rows(_minus_finite_rows, (diff, _mean_c(cands[0].mse, den)), h)
    diff = MaskedSmoothing(sigma)([diff])[0]
    return np.where(np.isfinite(diff) & (diff > 0) & ~keep, 0, choice)


@numba.njit(cache=True, nogil=True)
def _minus_finite_rows(a, b, i0, i1):
    # a = a - b, each non-finite one read as NaN
    for i in range(i0, i1):
        for j in range(a.shape[1]):
            x, y = a[i, j], b[i, j]
            a[i, j] = (x if np.isfinite(x) else np.nan) - (y if np.isfinite(y) else np.nan)


def _picked(cands, rel, choice):
    """Per pixel, the chosen candidate's image, the channel mean of its unbiased estimate and its
    relative estimate (``rel[choice]``)."""
    h, w = choice.shape
    img = np.empty(cands[0].image.shape)
    raw_abs = np.empty((h, w))
    pick = _compact(choice, len(cands))
    for k, c in enumerate(cands):
        _pick_where(pick.ravel(), k, c.image, img)
        _pick_mean_c(pick, k, c.mse, None, raw_abs)
    return img, raw_abs, np.take_along_axis(rel, choice[None], axis=0)[0]


def _pick_where(choice, k, src, out):
    """``out[p] = src[p]`` where ``choice[p] == k`` (src and out (H, W, C) or (H, W), C-contiguous, raveled alike).

    Both as 2-D (pixels, values) views: one compiled kernel for images and maps (it was compiled for each).
    """
    m = choice.size
    if not out.flags.c_contiguous:
        raise ValueError("_pick_where writes into a C-contiguous out")
    _pick_rows(np.ascontiguousarray(choice), int(k), np.ascontiguousarray(src).reshape(m, -1),
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


def _no_push_in_heavy_tails(img: np.ndarray, y: np.ndarray, hi: np.ndarray, out: np.ndarray | None = None
                            ) -> np.ndarray:
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
    Written into ``out`` (default a new array; ``img`` itself may be given:
    each value reads only its own pixel of ``img``).
    """
    # one compiled pass (the numpy formulation, kept in the tests as the reference, was 1.2 s of
    # auto's 8 s at 1024^2)
    img = np.ascontiguousarray(img, dtype=np.float64)
    out = img.copy() if out is None else out
    y = np.ascontiguousarray(y, dtype=np.float64)
    hi = np.ascontiguousarray(hi, dtype=np.float64)
    # row blocks on the filters' thread pool (a parallel=True kernel cost 1.5 s of compilation on a first run)
    parallel_rows(_no_push_rows, (img, y, hi, HEAVY_TAIL, out), y.shape[0])
    return out


@numba.njit(cache=True, nogil=True)
def _no_push_rows(img, y, hi, heavy_tail, out, i0, i1):
    """:func:`_no_push_in_heavy_tails` per pixel and channel in rows [i0, i1) (``out`` starts as a copy of ``img``).

    The median of the 8 neighbours (edge-repeated; an empty neighbour's mean
    counts) is :func:`~mcrecon.filters.order.neighbour_median8`, as
    :func:`numpy.median` computes it; NaN anywhere among them makes it NaN,
    and a NaN median never reverts.  Computed for whole rows
    (:func:`~mcrecon.filters.order.neighbour_medians8`): the rule fires at
    half the values of a film with rare huge samples.
    """
    h, w, c = y.shape
    n = w * c
    med = np.empty(n)
    for i in range(i0, i1):
        neighbour_medians8(y, i, med[c:n - c] if w > 1 else med[:0])
        for j in (0, w - 1):
            for ch in range(c):
                med[j * c + ch] = neighbour_median8(y, i, j, ch)
        yr, ir, hr, orow = y[i].reshape(n), img[i].reshape(n), hi[i].reshape(n), out[i].reshape(n)
        for q in range(n):
            yc, oc, md = yr[q], ir[q], med[q]
            if hr[q] > heavy_tail * abs(yc) and oc != yc and ((yc > md and oc > yc) or (yc < md and oc < yc)):
                orow[q] = yc


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
