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
grows with ``n`` (3.2 at 32 spp, 5.8 at 512).  So the threshold grows with each pixel's own count
(:func:`threshold`): ``ONE_SIDED + H_n - H_32`` above 32 samples.  An exponential maximum exceeds ``x`` with
probability about ``n exp(-x)``, so a threshold on it that moves by ``ln n ~ H_n`` keeps the share of
one-sided pixels flat (the regression proxy's textured film, seeds 0-2: 0.016-0.020 at 32 spp, 0.021-0.023 at
128, 0.027-0.031 at 512, 0.029-0.035 at 2048, 0.022-0.030 at 4096; with the constant 6: 0.10, 0.38, 0.85,
0.98: a black-box default from between 512 and 2048 spp).  Scaling by the ratio of the means instead
over-corrects (0.001-0.002 at 2048) and drops the Bernoulli case sooner.  At 32 samples and fewer the threshold
stays ``ONE_SIDED`` (exponential noise counts 0.000 at 8 spp).  The Bernoulli case keeps its ratio, so a light a
sample in ten finds stops counting where its hits grow many: ``(n - k) / k > ONE_SIDED + H_n - H_32`` holds for
``k`` about ``n / 10`` hits in 0.75 of the pixels at 32 spp, 0.73 at 256, 0.58 at 512 (some 50 hits), 0.31 at
1024 and 0.06 at 2048 (Binomial(n, 0.1)).  That is
not the failure the rule is for: with tens of hits in a pixel its rare samples are no longer rare to its own
variance, and the capped leave-one-out estimates keep their tails.
"""

from __future__ import annotations

import numpy as np

__all__ = ["ONE_SIDED", "HEAVY_VOTE", "threshold", "one_sided", "heavy_vote"]

#: A pixel's samples have a one-sided tail where, in some channel, their maximum lies above their mean by more
#: than this many times the mean's excess over their minimum, at 32 samples and fewer; above, by more than
#: ``ONE_SIDED + H_n - H_32`` times (:func:`threshold`).
ONE_SIDED = 6.0
#: The vote is heavy (read as thin) where the voters with a one-sided tail exceed this share of the pixels with
#: samples.  Of the pixels with samples, not of the voters: a ring of rare samples on exact zeros has few
#: voters, nearly all of them one-sided (0.04-0.06 of the pixels with samples).  Shares measured at 128^2, 32 spp
#: (docs/methods/auto.md, "A heavy vote"): checker_spot-7 0.669-0.674 and checker_spot-9 0.633-0.642 (corpus
#: seeds 0-3), Cycles' studio 0.32, glossy_hdr 0.19, motion_blur-0 0.15, every other tuning scene with a full
#: vote at most 0.11; exponential samples on a texture (48^2) 0.000-0.035 from 8 to 4096 spp.
HEAVY_VOTE = 0.45


def threshold(count: np.ndarray) -> np.ndarray:
    """The one-sided threshold of pixels with ``count`` samples: :data:`ONE_SIDED` at 32 and fewer, ``ONE_SIDED +
    H_n - H_32`` above (``H_n`` the harmonic number, from its expansion ``ln n + gamma + 1 / (2 n) - 1 / (12
    n^2)``, within 1e-8 there; gamma cancels), float64 of ``count``'s shape."""
    n = np.maximum(np.asarray(count, np.float64), 32.0)
    return ONE_SIDED + np.log(n / 32.0) + (1.0 / (2.0 * n) - 1.0 / (12.0 * n * n)) - (1.0 / 64.0 - 1.0 / 12288.0)


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
