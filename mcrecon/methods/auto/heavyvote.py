"""A heavy vote: most of the global prior's voters have rare huge samples around, and its default is a black box.

The global prior's vote (:func:`.selection.summed_estimates`) leaves out the pixels whose 3 x 3 sample
maximum exceeds :data:`.selection.HEAVY_PRIOR` (30) times their mean; a light found by one sample in ten
(a spotlight on a texture) passes under that test and leaves nearly every pixel voting, each with
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

#: The share of the voters with rare huge samples around (some channel's 3 x 3 sample maximum above
#: :data:`HEAVY_TAIL` times the pixel's mean) above which the global prior's vote is heavy, and taken as a
#: thin one (``_global_prior(heavy_vote=)``; None: never).  The corpus's tuning half (128^2, 32 spp) where
#: the vote is not thin: at most 0.27 (caustic-0, mitsuba-floor_spheres), and 0.63-0.70 on the spotlit
#: textures whose light a sample in 10-20 finds, where the capped sums made NFOR the default at 2 x the
#: error of OIDN + albedo + normal.
HEAVY_VOTE = 0.5


def _heavy_vote(vote: np.ndarray, y: np.ndarray, hi: np.ndarray, share: float | None = None) -> bool:
    """Whether more than ``share`` (default :data:`HEAVY_VOTE`; None there: never) of the voting pixels
    ``vote`` (H, W) have rare huge samples around: in some channel the 3 x 3 sample maximum ``hi`` above
    :data:`HEAVY_TAIL` times ``|y|`` (the pixel means; (H, W, C))."""
    share = HEAVY_VOTE if share is None else share
    n = int(np.count_nonzero(vote))
    if share is None or n == 0:
        return False
    heavy = (hi[vote] > HEAVY_TAIL * np.abs(y[vote])).any(axis=-1)
    return bool(np.count_nonzero(heavy) > share * n)
