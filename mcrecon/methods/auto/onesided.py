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
``(1 - p) / p`` (9 at p = 0.1) whatever ``b`` and ``h``; exponential samples have about ``ln n`` (3 at 32
spp), Gaussian noise about 1.
"""

from __future__ import annotations

import numpy as np

__all__ = ["ONE_SIDED", "HEAVY_VOTE", "one_sided", "heavy_vote"]

#: A pixel's samples have a one-sided tail where, in some channel, their maximum lies above their mean by more
#: than this many times the mean's excess over their minimum.  Share of the pixels with samples (128^2 or
#: 48^2, 32 spp; docs/methods/auto.md, "A heavy vote"): exponential samples on a texture 0.003-0.020 (8-32 spp),
#: the tuning spot-light walls whose light a sample in ten finds 0.70-0.73, Cycles' studio 0.34.
ONE_SIDED = 6.0
#: The vote is heavy (read as thin) where the voters with a one-sided tail exceed this share of the pixels with
#: samples.  Of the pixels with samples, not of the voters: a ring of rare samples on exact zeros has few
#: voters, nearly all of them one-sided (0.04-0.06 of the pixels with samples).  Measured at 128^2, 32 spp:
#: checker_spot-7 and -9 0.64-0.67 (seeds 0-3 in the docs), Cycles' studio 0.32, glossy_hdr 0.19, every other
#: tuning scene with a full vote at most 0.15.
HEAVY_VOTE = 0.45


def one_sided(stats) -> np.ndarray | None:
    """The pixels whose own samples have a one-sided tail (:data:`ONE_SIDED`), in some channel ``max - mean >
    ONE_SIDED (mean - min)`` and ``mean > min``, (H, W) bool; None for statistics without a per-pixel sample
    range (built from moments)."""
    if not getattr(stats, "has_range", False):
        return None
    y = stats.mean
    with np.errstate(invalid="ignore"):
        # mean > min: where every sample is the same the mean can round below them, and its excess, negative,
        # would make any maximum one-sided (an hdr scene's dim background: half its pixels)
        return ((stats.max - y > ONE_SIDED * (y - stats.min)) & (y > stats.min)).any(axis=2)


def heavy_vote(vote: np.ndarray, heavy: np.ndarray | None, count: np.ndarray) -> bool:
    """Whether more than :data:`HEAVY_VOTE` of the pixels with samples (``count > 0``) vote (``vote``) with a
    one-sided tail (``heavy``, :func:`one_sided`); False without ``heavy``."""
    if heavy is None:
        return False
    return int(np.count_nonzero(vote & heavy)) > HEAVY_VOTE * int(np.count_nonzero(count > 0))
