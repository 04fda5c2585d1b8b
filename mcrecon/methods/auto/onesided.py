"""A heavy vote: most of the global prior's voters hold rare huge samples of their own.

A light that about one sample in ten finds leaves nearly every pixel voting (the vote's rare-sample test,
:data:`.apart.HEAVY_PRIOR`, sees only the pixels whose samples missed it), each with a few huge samples
among small ones.  Over such voters the capped leave-one-out estimates lose their positive tails and every
Stein- or cross-validation-scored filter's sum falls far below its true error (the tuning checker_spot-7:
NFOR -366 and OIDN + albedo + normal on the halves -322 where the true sums are 165 and 38), so the sums
choose a regression where a black box is 4 x better.  :func:`.selection.prior_default` then reads the vote
as thin (:mod:`.thinvote`): its default is the black box of least crossed vote (docs/methods/auto.md, "A
heavy vote").

The test is each pixel's own sample range, not a neighbourhood's: on a texture a 3 x 3 maximum holds a
lighter square's samples, and exponential noise on a textured film passed a 3 x 3 test at half its pixels.
Within one pixel a base ``b`` plus ``h`` with probability ``p`` has ``(max - mean) / (mean - min)`` about
``(1 - p) / p`` (9 at p = 0.1) whatever ``b``, ``h`` and ``n``; Gaussian noise about 1; ``n`` samples of Exp(1)
have ``E[max] = H_n`` (the harmonic number) and ``E[min] = 1 / n``, a ratio ``(H_n - 1) / (1 - 1 / n)`` that
grows with ``n`` (3.2 at 32 spp, 5.8 at 512).  So above 32 samples the threshold grows with each pixel's own
count as that ratio (:func:`threshold`: ``ONE_SIDED r(n) / r(32)``, ``r(n) = (H_n - 1) / (1 - 1 / n)``; 8.5 at
128 spp, 11.1 at 512, 13.7 at 2048).  The regression proxy's textured film (48^2, seeds 0-2) counts 0.000 of its
pixels one-sided at 8 spp, 0.016-0.020 at 32, 0.005-0.008 at 128, 0.002-0.003 at 512, 0.001-0.002 at 2048 and
0.000-0.002 at 4096; with the constant 6: 0.10 at 128, 0.38 at 512, 0.85 at 2048, 0.98 at 4096 (a black-box
default from between 512 and 2048 spp).  At 32 samples and fewer the threshold stays ``ONE_SIDED`` (the same
bits; below the ratio would count 0.03 of that film at 8 spp).  A threshold moving by ``H_n - H_32`` (an
exponential maximum exceeds ``x`` with probability about ``n exp(-x)``) would keep the film's share flat
(0.02-0.035 from 32 to 4096 spp) but keeps the Bernoulli case counted far longer, and there it costs: the
tuning checker_spot-7 at 64^2 (auto with the heavy vote forced / kept out, relMSE over the pixel mean's) 0.070
/ 0.070 at 128 spp, 0.090 / 0.081 at 256, 0.159 / 0.109 at 512, 0.251 / 0.124 at 1024.  The Bernoulli case
keeps its ratio, so a light a sample in ten finds stops counting where its hits grow many: ``(n - k) / k`` above
the threshold holds for ``k`` about ``n / 10`` hits in 0.75 of the pixels at 32 spp, 0.60 at 128, 0.34 at 256,
0.10 at 512 (Binomial(n, 0.1)); checker_spot-7 at 64^2 counts 0.72 of its pixels at 32 spp, 0.63 at 128, 0.49
at 256 (its vote still heavy: 0.090), 0.37 at 512 (not: 0.109).  A rare light found some 40 times in a pixel
at 512 spp is not the failure the rule is for: the capped leave-one-out estimates rank well with many hits (the
measurements above).
"""

from __future__ import annotations

import numpy as np

__all__ = ["ONE_SIDED", "HEAVY_VOTE", "threshold", "one_sided", "heavy_vote"]

#: A pixel's samples have a one-sided tail where, in some channel, their maximum lies above their mean by more
#: than this many times the mean's excess over their minimum, at 32 samples and fewer; above, by more than
#: ``ONE_SIDED r(n) / r(32)`` times, ``r(n) = (H_n - 1) / (1 - 1 / n)`` (:func:`threshold`).
ONE_SIDED = 6.0
#: The vote is heavy (read as thin) where the voters with a one-sided tail exceed this share of the pixels with
#: samples.  Of the pixels with samples, not of the voters: a ring of rare samples on exact zeros has few
#: voters, nearly all of them one-sided (0.04-0.06 of the pixels with samples).  Shares measured at 128^2, 32 spp
#: (docs/methods/auto.md, "A heavy vote"): checker_spot-7 0.669-0.674 and checker_spot-9 0.633-0.642 (corpus
#: seeds 0-3), Cycles' studio 0.32, glossy_hdr 0.19, motion_blur-0 0.15, every other tuning scene with a full
#: vote at most 0.11; exponential samples on a texture (48^2) 0.000-0.020 from 8 to 4096 spp.
HEAVY_VOTE = 0.45


def _ratio(n: np.ndarray) -> np.ndarray:
    """``(H_n - 1) / (1 - 1 / n)``: ``E[max - mean] / E[mean - min]`` of ``n`` Exp(1) samples, ``H_n`` from its
    expansion ``ln n + gamma + 1 / (2 n) - 1 / (12 n^2)`` (within 1e-8 from n = 32)."""
    h = np.log(n) + np.euler_gamma + 1.0 / (2.0 * n) - 1.0 / (12.0 * n * n)
    return (h - 1.0) / (1.0 - 1.0 / n)


def threshold(count: np.ndarray) -> np.ndarray:
    """The one-sided threshold of pixels with ``count`` samples: :data:`ONE_SIDED` at 32 and fewer, ``ONE_SIDED
    r(n) / r(32)`` above (``r`` the exponential samples' ratio of the expected excesses, :func:`_ratio`), float64
    of ``count``'s shape."""
    n = np.maximum(np.asarray(count, np.float64), 32.0)
    return np.where(n > 32.0, ONE_SIDED * _ratio(n) / _ratio(np.float64(32.0)), ONE_SIDED)


def one_sided(stats) -> np.ndarray | None:
    """The pixels whose own samples have a one-sided tail, in some channel ``max - mean > t (mean - min)`` with
    ``t`` the pixel's :func:`threshold` of its count, and ``mean > min``, (H, W) bool; None for statistics without
    a per-pixel sample range (built from moments)."""
    if not getattr(stats, "has_range", False):
        return None
    y = stats.mean
    t = threshold(stats.count)[..., None]
    with np.errstate(invalid="ignore"):
        # mean > min: where every sample is the same the mean can round below them, and its excess, negative,
        # would make any maximum one-sided (an hdr scene's dim background: half its pixels)
        return ((stats.max - y > t * (y - stats.min)) & (y > stats.min)).any(axis=2)


def heavy_vote(vote: np.ndarray, heavy: np.ndarray | None, count: np.ndarray) -> bool:
    """Whether more than :data:`HEAVY_VOTE` of the pixels with samples (``count > 0``) vote (``vote``) with a
    one-sided tail (``heavy``, :func:`one_sided`); False without ``heavy``."""
    if heavy is None:
        return False
    return int(np.count_nonzero(vote & heavy)) > HEAVY_VOTE * int(np.count_nonzero(count > 0))
