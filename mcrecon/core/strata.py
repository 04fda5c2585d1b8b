"""A stratification-aware estimate of each pixel mean's error: the prefix halves of its sample sequence.

A renderer with a stratified sampler (an Owen-scrambled Sobol sequence per
pixel, continued round after round from the request's ``first_index``)
gives pixel means whose error is often far below ``s^2 / n``: the sample
variance counts the spread of the integrand over the pixel, which the
strata cancel.  An allocation driven by ``s^2 / n`` then sends samples
where they pay least (edges a net already resolves).

:class:`PrefixHalves` follows every pixel's samples in stream order (its
sequence order) and keeps the two halves of the longest power-of-two
prefix, ``[0, 2^(m-1))`` and ``[2^(m-1), 2^m)``: each an aligned block, so
each is itself a net of the sequence, and together they are the net the
pixel mean stands on.  (The halves of :mod:`mcrecon.core.halves` alternate
sample by sample: samples ``2j`` and ``2j + 1`` of a Sobol sequence sit in
opposite halves of the pixel in every dimension, so those halves' means
differ by the integrand's left-right difference, not by noise.)
``((m_A - m_B) / 2)^2`` estimates the variance of the prefix's mean
(exactly for independent samples; for a net it errs high, by the
net's gain from ``2^(m-1)`` to ``2^m`` samples, never low;
``tests/test_stratified_error.py`` checks both against brute force).
One such square is a one-degree-of-freedom estimate, so
:meth:`PrefixHalves.gain` pools it over a small neighbourhood as a ratio to
the sample variance's ``s^2 / n``: the *stratification gain* ``g`` in
``(0, 1]``, with which a pixel mean's variance is ``g s^2 / n``.
"""

from __future__ import annotations

import numba
import numpy as np

from ..filters.box import box_mean

__all__ = ["PrefixHalves", "stratified_gain", "prefix_halves_of", "halves_gain", "GAIN_RADIUS", "GAIN_FLOOR"]

#: Neighbourhood (box of 2 r + 1 pixels a side) over which the halves' squared difference and
#: ``s^2 / n`` are summed before their ratio is taken: 25 pixels x the channels of one-degree
#: estimates keep the ratio's noise near 15 %, small next to the gains it measures (5-50x).
GAIN_RADIUS = 2
#: Standard deviations (of the ratio, were the samples independent) added to the pooled ratio:
#: a neighbourhood's gain below 1 is taken only where it is more than chance.
UCB_SIGMAS = 2.0
#: Smallest gain: a neighbourhood whose halves agree by chance does not stop its pixels' sampling.
GAIN_FLOOR = 1.0 / 32.0


@numba.njit(cache=True, nogil=True)
def _add_kernel(pix, val, counter, s_first, s_second, s_cur, n_first, n_second, n_cur):
    # sample k of pixel p (its k-th in stream order) goes to the block [2^j, 2^(j+1)) it starts
    # or continues; when k is a power of two, the prefix [0, k) is complete: its two halves become
    # (first, second) and a new block starts.  Non-finite values take their index, not a place.
    n_ch = val.shape[1]
    for i in range(pix.size):
        p = pix[i]
        k = counter[p]
        counter[p] = k + 1
        if k >= 1 and (k & (k - 1)) == 0:
            for c in range(n_ch):
                s_first[p, c] += s_second[p, c]
                s_second[p, c] = s_cur[p, c]
                s_cur[p, c] = 0.0
            n_first[p] += n_second[p]
            n_second[p] = n_cur[p]
            n_cur[p] = 0
        finite = True
        for c in range(n_ch):
            if not np.isfinite(val[i, c]):
                finite = False
        if finite:
            for c in range(n_ch):
                s_cur[p, c] += val[i, c]
            n_cur[p] += 1


class PrefixHalves:
    """The two halves of each pixel's longest power-of-two prefix of samples, kept as sums.

    Parameters
    ----------
    width, height : int
        The film.
    n_channels : int
        Channels of the values.

    Notes
    -----
    Three sums and counts per pixel and channel (24 bytes per pixel and
    channel plus the counts): the halves are rebuilt, not stored, as the
    prefix grows.  Positions floor to their pixel; a position off the film
    counts in the nearest border pixel (the statistics drop it).
    """

    def __init__(self, width: int, height: int, n_channels: int, *, window=None):
        # window (y0, y1, x0, x1): the prefix halves of those pixels of the film only, fed the film's batches
        # (every estimate is per pixel, in each pixel's order: the film's cropped to the window, bit for bit)
        self._film = (int(width), int(height))
        self._origin = (0, 0)
        if window is not None:
            y0, y1, x0, x1 = (int(v) for v in window)
            self._origin = (y0, x0)
            width, height = x1 - x0, y1 - y0
        self.width, self.height, self.n_channels = int(width), int(height), int(n_channels)
        npix = self.width * self.height
        self.counter = np.zeros(npix, np.int64)
        self._sums = np.zeros((3, npix, self.n_channels))
        self._counts = np.zeros((3, npix), np.int64)

    def add(self, positions, values) -> None:
        """Add a batch of samples in stream order (each pixel's samples in its sequence order)."""
        if values is None:
            return   # a reader's batch with no sample of this window (mcrecon.io.SampleLog.iter_chunks)
        pos = np.asarray(positions, dtype=np.float64)
        val = np.asarray(values, dtype=np.float64)
        if val.ndim == 1:
            val = val[:, None]
        if pos.shape[0] == 0:
            return
        fw, fh = self._film
        ix = np.clip(np.floor(np.nan_to_num(pos[:, 0], nan=0.0)), 0, fw - 1).astype(np.int64)
        iy = np.clip(np.floor(np.nan_to_num(pos[:, 1], nan=0.0)), 0, fh - 1).astype(np.int64)
        if (fw, fh) != (self.width, self.height):  # a window: its pixels' samples, each pixel's in order
            oy, ox = self._origin
            iy, ix = iy - oy, ix - ox
            inside = (iy >= 0) & (iy < self.height) & (ix >= 0) & (ix < self.width)
            iy, ix, val = iy[inside], ix[inside], val[inside]
        s, n = self._sums, self._counts
        _add_kernel(iy * self.width + ix, np.ascontiguousarray(val), self.counter, s[0], s[1], s[2], n[0], n[1], n[2])

    def crop(self, y0: int, y1: int, x0: int, x1: int) -> "PrefixHalves":
        """The prefix halves of the pixels ``[y0:y1, x0:x1]`` (copies): every estimate is per pixel, so a
        crop's equals the crop of the film's, bit for bit (a tile of a tiled reconstruction)."""
        h, w = y1 - y0, x1 - x0
        out = PrefixHalves(w, h, self.n_channels)
        grid = lambda a: a.reshape(a.shape[:-1] + (self.height, self.width))[..., y0:y1, x0:x1]  # noqa: E731
        out.counter[:] = grid(self.counter).reshape(-1)
        out._counts[:] = grid(self._counts).reshape(3, -1)
        out._sums[:] = np.moveaxis(grid(np.moveaxis(self._sums, 2, 1)), 1, -1).reshape(3, -1, self.n_channels)
        return out

    def halves(self):
        """``(mean_a, mean_b, n_a, n_b)``: the means (H, W, C) and counts (H, W) of the two halves.

        A pixel whose count is a power of two has its whole sequence as the
        prefix (halves: the blocks before and the block after its middle);
        otherwise the prefix is the last completed one.  Halves without a
        finite sample have count 0 (and mean 0).
        """
        npix, nc = self._sums.shape[1:]
        mean_a, mean_b = np.empty((npix, nc)), np.empty((npix, nc))
        n_a, n_b = np.empty(npix, np.int64), np.empty(npix, np.int64)
        _halves_kernel(self.counter, self._sums, self._counts, mean_a, mean_b, n_a, n_b)
        shape = (self.height, self.width)
        return (mean_a.reshape(shape + (nc,)), mean_b.reshape(shape + (nc,)), n_a.reshape(shape),
                n_b.reshape(shape))

    def mean_variance(self, count: np.ndarray) -> np.ndarray:
        """(H, W, C): each pixel mean's variance from its prefix halves alone, NaN where a half is empty.

        ``((m_A - m_B) / 2)^2``, the variance of the prefix's mean, times
        ``n_prefix / count``: the variance of a mean of ``count`` samples
        were its samples independent (exact for them; for a net it errs
        high, never low).  A one-degree-of-freedom estimate per pixel and
        channel, but one that a selection driven by ``s^2 / n`` did not see:
        the sample variance of all the samples carries the luck that made
        the selection, the halves' difference far less of it.
        """
        mean_a, mean_b, n_a, n_b = self.halves()
        n = np.asarray(count, dtype=np.float64).reshape(self.height, self.width)
        ok = (n_a > 0) & (n_b > 0) & (n > 0)
        scale = np.divide(n_a + n_b, n, out=np.zeros_like(n), where=ok)
        out = (0.5 * (mean_a - mean_b)) ** 2 * scale[..., None]
        return np.where(ok[..., None], out, np.nan)

    def gain(self, sample_variance: np.ndarray, *, radius: int = GAIN_RADIUS, floor: float = GAIN_FLOOR) -> np.ndarray:
        """Stratification gain (H, W) in ``[floor, 1]``: a pixel mean's variance is ``gain * s^2 / n``.

        The ratio, summed over the channels and a ``2 radius + 1`` box, of the
        halves' squared half-difference to what it would be for independent
        samples, ``s^2 (1 / n_a + 1 / n_b) / 4`` with ``sample_variance``
        (H, W, C) the pixels' ``s^2`` over all their samples.  Pixels whose
        neighbourhood has no pixel with both halves (fewer than two samples)
        or no sample variance get 1 (nothing known: ``s^2 / n`` as it is).
        The ratio's upper two-sigma bound is taken, capped at 1: for
        independent samples the ratio's expectation is 1, and its chance
        dips below 1 are noise, not a gain.
        """
        mean_a, mean_b, n_a, n_b = self.halves()
        return halves_gain(mean_a, mean_b, n_a, n_b, sample_variance, radius=radius, floor=floor)


def halves_gain(mean_a, mean_b, n_a, n_b, sample_variance, *, radius: int = GAIN_RADIUS,
                floor: float = GAIN_FLOOR) -> np.ndarray:
    """Stratification gain (H, W) in ``[floor, 1]`` from two halves' means (H, W, C) and counts (H, W).

    :meth:`PrefixHalves.gain` of any two halves of each pixel's samples (the prefix-block halves of
    :func:`mcrecon.core.halves.split_halves` too); ``sample_variance`` (H, W, C): ``s^2`` of all of them.
    """
    ma, mb, var = (np.ascontiguousarray(x, dtype=np.float64) for x in (mean_a, mean_b, sample_variance))
    na, nb = (np.ascontiguousarray(x, dtype=np.float64) for x in (n_a, n_b))
    # the compiled pass reads every plane at the means' indices, unchecked: a shape apart would read past it
    if ma.ndim != 3 or not ma.shape[2] or mb.shape != ma.shape or var.shape != ma.shape or \
            na.shape != ma.shape[:2] or nb.shape != ma.shape[:2]:
        raise ValueError(f"halves_gain: means and sample variance (H, W, C >= 1), counts (H, W) expected, got "
                         f"{ma.shape}, {mb.shape}, {var.shape} and {na.shape}, {nb.shape}")
    h, w, nc = ma.shape
    d2, ref, ref2 = np.empty((h, w)), np.empty((h, w)), np.empty((h, w))
    _gain_planes(ma, mb, na, nb, var, d2, ref, ref2)
    r = int(radius)
    # scipy's uniform_filter(size=2 r + 1, mode="constant"), bit for bit (mcrecon.filters.box)
    num, den, den2 = (box_mean(a, r, "constant") for a in (d2, ref, ref2))
    out = np.empty((h, w))
    _gain_ratio(num, den, den2, float((2 * r + 1) ** 2), UCB_SIGMAS, float(floor), out)
    return out


@numba.njit(cache=True, nogil=True)
def _halves_kernel(counter, s, c, mean_a, mean_b, n_a, n_b):
    # a pixel whose count is a power of two (>= 2): the halves are blocks 0 + 1 and block 2, else blocks 0
    # and 1; each mean sum / max(count, 1)
    npix, nc = mean_a.shape
    for p in range(npix):
        n = counter[p]
        pow2 = n >= 2 and (n & (n - 1)) == 0
        na = c[0, p] + c[1, p] if pow2 else c[0, p]
        nb = c[2, p] if pow2 else c[1, p]
        n_a[p] = na
        n_b[p] = nb
        for ch in range(nc):
            sa = s[0, p, ch] + s[1, p, ch] if pow2 else s[0, p, ch]
            sb = s[2, p, ch] if pow2 else s[1, p, ch]
            mean_a[p, ch] = sa / max(na, 1)
            mean_b[p, ch] = sb / max(nb, 1)


@numba.njit(cache=True, nogil=True)
def _gain_planes(mean_a, mean_b, n_a, n_b, var, d2, ref, ref2):
    # where both halves hold samples: d2 = sum_c ((m_a - m_b) / 2)^2 and inv = 1 / n_a + 1 / n_b (else 0);
    # ref = sum_c s^2 * inv * 0.25 and ref2 = ref^2; the channel sums left to right, as numpy's
    h, w, nc = mean_a.shape
    for i in range(h):
        for j in range(w):
            ok = n_a[i, j] > 0 and n_b[i, j] > 0
            inv = 0.0
            e = 0.0
            if ok:
                inv = 1.0 / max(n_a[i, j], 1.0) + 1.0 / max(n_b[i, j], 1.0)
                for ch in range(nc):
                    t = 0.5 * (mean_a[i, j, ch] - mean_b[i, j, ch])
                    e = t * t if ch == 0 else e + t * t
            sv = var[i, j, 0]
            for ch in range(1, nc):
                sv += var[i, j, ch]
            d2[i, j] = e
            rf = sv * inv * 0.25
            ref[i, j] = rf
            ref2[i, j] = rf * rf


@numba.njit(cache=True, nogil=True)
def _gain_ratio(num, den, den2, n_box, ucb, floor, out):
    # g = num / den and the ratio's relative sd sqrt(2 max(den2, 0) / n_box) / den where den > 1e-300
    # (else 1 and 0); out = clip(g (1 + ucb sd), floor, 1) as numpy clips (a NaN stays NaN)
    h, w = num.shape
    for i in range(h):
        for j in range(w):
            d = den[i, j]
            g = 1.0
            sd = 0.0
            if d > 1e-300:
                g = num[i, j] / d
                q = den2[i, j]
                q = q if (q > 0.0 or q != q) else 0.0
                sd = np.sqrt(2.0 * q / n_box) / d
            x = g * (1.0 + ucb * sd)
            if x == x:
                x = x if x > floor else floor
                x = x if x < 1.0 else 1.0
            out[i, j] = x


def prefix_halves_of(source, *, chunk_size: int = 1 << 20) -> PrefixHalves:
    """The :class:`PrefixHalves` of a sample source (a ``SampleSet`` or a sample log), its rows in stored order.

    A log written by an adaptive run or a renderer bridge stores each
    pixel's samples in its sequence order (round after round); rows in
    another order make the halves random halves, whose estimate is that of
    independent samples (high for a net, never low).  Non-finite values
    take their index and no place, as in an adaptive run.
    """
    out = PrefixHalves(source.width, source.height, len(source.channels))
    for chunk in source.iter_chunks(chunk_size=chunk_size, with_round=False):
        out.add(chunk.positions, chunk.values)
    return out


def stratified_gain(state) -> np.ndarray | None:
    """The stratification gain (H, W) of an adaptive plan's committed samples, or None without prefix halves.

    ``state`` is an :class:`~mcrecon.methods.base.AdaptiveState`: its
    ``strata`` (:class:`PrefixHalves`) against its statistics' sample variance.
    """
    if getattr(state, "strata", None) is None:
        return None
    return state.strata.gain(state.stats.sample_variance(undefined=0.0))
