"""nfor's bound on a pixel whose brightness rests on one sample that no neighbour's sample confirms."""

from __future__ import annotations

import numpy as np

from ...core.stats import PixelStats

__all__ = ["isolated_sample_bounds", "leave_out_isolated"]


def _neighbours_extreme(x: np.ndarray, has: np.ndarray, fill: float, take) -> np.ndarray:
    """Per pixel and channel, ``take`` (np.maximum or np.minimum) of ``x`` over its 8 neighbours that hold
    a sample; ``fill`` where none does.  (H, W, C) in and out."""
    h, w = has.shape
    out = np.full(x.shape, -fill)  # the neutral element of ``take``
    seen = np.zeros((h, w), bool)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dy == 0 and dx == 0:
                continue
            dst = (slice(max(0, -dy), h - max(0, dy)), slice(max(0, -dx), w - max(0, dx)))
            src = (slice(max(0, dy), h - max(0, -dy)), slice(max(0, dx), w - max(0, -dx)))
            ok = has[src]
            out[dst] = np.where(ok[..., None], take(out[dst], x[src]), out[dst])
            seen[dst] |= ok
    out[~seen] = fill
    return out


def isolated_sample_bounds(stats: PixelStats, k: float) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel and channel, the interval a result may take when its largest (smallest) sample is left out
    unless a neighbour saw one as far out.

    The upper bound is ``max(largest sample of the 8 neighbours, mean of
    the pixel's other samples + k standard errors of that mean)``, with
    "other" all but the pixel's largest sample; the lower bound likewise
    with the smallest.  A result above it rests on a sample brighter than
    every one of the 8 n samples around it and than the pixel's other
    samples explain: a brightness seen with a frequency below about 1 / (8 n),
    where leaving it out costs a squared bias ``(p v)^2`` below the variance
    ``p v^2 / n`` that keeping it leaves.  NL-means weights find no patch
    like such a pixel's, so the regression keeps its value; the confidence
    clamp around its own mean keeps it too (its own variance is the
    firefly's).  A pixel whose samples agree with one another (a one-pixel
    highlight) keeps its own interval: the mean of its other samples plus
    k standard errors covers it.  Pixels with fewer than three samples, or
    without a sampled neighbour, or statistics without a sample range, get
    no bound (``-inf``, ``inf``).  Returns (lo, hi), (H, W, C) each.
    """
    shape = stats.mean.shape
    lo = np.full(shape, -np.inf)
    hi = np.full(shape, np.inf)
    if not stats.has_range:
        return lo, hi
    n = stats.count.astype(np.float64)[..., None]
    has = stats.count > 0
    ok = np.broadcast_to(n >= 3, shape)
    if not ok.any():
        return lo, hi
    nn = np.maximum(n, 3.0)
    m, m2 = stats.mean, stats.m2
    with np.errstate(invalid="ignore", over="ignore"):
        for x, sign, take, fill, out in ((stats.max, 1.0, np.maximum, np.inf, hi),
                                         (stats.min, -1.0, np.minimum, -np.inf, lo)):
            rest = (nn * m - x) / (nn - 1.0)  # the mean of the other samples (Welford's step undone)
            rest_m2 = np.maximum(m2 - (x - m) * (x - rest), 0.0)
            se = np.sqrt(rest_m2 / (nn - 2.0) / (nn - 1.0))
            own = rest + sign * k * se
            nb = _neighbours_extreme(x, has, fill, take)
            bound = take(nb, own)
            out[...] = np.where(ok & np.isfinite(bound), bound, fill)
    return lo, hi


def leave_out_isolated(image: np.ndarray, stats: PixelStats, k: float) -> np.ndarray:
    """``image`` (H, W, C) clipped to the :func:`isolated_sample_bounds` interval's end where its pixel's mean
    lies beyond that end and the result keeps more than half, and at most all, of the mean's excess (summed
    over the channels; in place; returned).

    A filter that gives the pixel no more weight than the rest of its window
    together keeps at most half of what the pixel's mean holds beyond the
    bound; a result that keeps more rests on the pixel's own samples (the
    NL-means weights found no patch like it).  A result that pooled a wide
    window whose 3 x 3 samples happened to miss a rare bright component
    the window sees elsewhere (a light found by one sample in 80) keeps
    less, or lies beyond the pixel's own mean, and stays.
    """
    lo, hi = isolated_sample_bounds(stats, k)
    m = stats.mean
    with np.errstate(invalid="ignore"):
        for end, sign in ((hi, 1.0), (lo, -1.0)):
            # judged per pixel on the channels' sums (one sample's colour moves them together; a decision
            # per channel would keep some channels and cut others, a coloured dot)
            ex_m = (sign * (m - end)).sum(axis=2)
            ex_i = (sign * (image - end)).sum(axis=2)
            act = np.isfinite(ex_m) & (ex_m > 0) & (ex_i > 0.5 * ex_m) & (ex_i <= ex_m)
            if act.any():
                sel = image[act]
                image[act] = np.minimum(sel, end[act]) if sign > 0 else np.maximum(sel, end[act])
    return image
