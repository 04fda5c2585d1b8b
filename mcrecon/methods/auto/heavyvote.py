"""A heavy vote: many of the global prior's voters have rare huge samples around, and its default is a black box.

The global prior's vote (:func:`.selection.summed_estimates`) leaves out the pixels whose 3 x 3 sample
maximum exceeds :data:`.selection.HEAVY_PRIOR` (30) times their mean; a light found by one sample in ten
(a spotlight on a texture) passes under that test and leaves nearly every pixel voting, half of them or more with
rare huge samples around at :data:`.firefly.HEAVY_TAIL` (10).  Every voter's estimate is then ruled by the
samples that carry the light, and the capped sums (each estimate capped at ``(safeguard + 1)^2 v``)
lose the positive tail of those estimates, most for the filters that are wrong where the light is: the
sums rank the candidates in no useful order.  :func:`.selection._global_prior` treats such a vote as a
thin one (:mod:`.thinvote`): the black box of least crossed vote is the default (docs/methods/auto.md,
"A heavy vote").
"""

from __future__ import annotations

import numpy as np

from .firefly import HEAVY_TAIL

__all__ = ["HEAVY_VOTE"]

#: The share of the pixels with samples that vote with rare huge samples around (:func:`_heavy_vote`) above which
#: the global prior's vote is heavy, and taken as a thin one (``_global_prior``; None: never).  The corpus's
#: tuning half (128^2, 32 spp): 0.48-0.54 on the spotlit textures whose vote is not thin (a sample in 10-20
#: finds the light; on two the capped sums made NFOR the default at twice the error of OIDN + albedo +
#: normal), at most 0.17 elsewhere (mitsuba-floor_spheres; the caustics 0.05-0.08, the Cycles scenes where
#: the vote is full 0.09-0.11); a ring of rare samples on exact zeros (tests/test_auto.py) 0.04-0.06.
HEAVY_VOTE = 0.35


def _heavy_vote(vote: np.ndarray, y: np.ndarray, bounds, count: np.ndarray, share: float | None = None) -> bool:
    """Whether more than ``share`` (default :data:`HEAVY_VOTE`; None there: never) of the pixels with samples
    (``count > 0``) vote (``vote``, (H, W)) with rare huge samples around: in some channel the 3 x 3 sample
    maximum ``hi`` (``bounds = (lo, hi)``, the 3 x 3 sample range) above :data:`HEAVY_TAIL` times ``|y|``
    (the pixel means) and its excess over ``y`` above :data:`HEAVY_TAIL` times ``y - lo``: a one-sided
    tail.  Symmetric noise about a mean near zero (Gaussian samples on a dark background) passes the first
    test at most pixels and never the second.  Of the pixels with samples, not of the voters: where rare
    samples light a ring on exact zeros every voter is heavy, but the voters are a twentieth of the image."""
    share = HEAVY_VOTE if share is None else share
    has = int(np.count_nonzero(count > 0))
    if share is None or has == 0:
        return False
    lo, hi = bounds
    yv, lv, hv = y[vote], lo[vote], hi[vote]
    with np.errstate(invalid="ignore"):
        heavy = ((hv > HEAVY_TAIL * np.abs(yv)) & (hv - yv > HEAVY_TAIL * (yv - lv))).any(axis=-1)
    return bool(np.count_nonzero(heavy) > share * has)
