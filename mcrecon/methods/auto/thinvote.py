"""A thin vote: the share of the global prior's possible voters below which its default is a black box.

Where most pixels have rare huge samples around, the pixels left to vote are those whose neighbourhoods
missed the light, a selection by their own samples; :func:`.selection._global_prior` then takes the
black box of least crossed vote (:func:`.selection.crossed_sum`) as its default (docs/methods/auto.md,
"A thin vote").
"""

from __future__ import annotations

import numpy as np

from ...core.halves import mean_variances
from ...core.safeguard import sample_range_bounds
from .apart import left_out
from .onesided import heavy_vote, one_sided

__all__ = ["THIN_VOTE", "PLAN_THIN_VOTE", "thin_vote_shown"]

#: The share of the pixels that could vote (:func:`_could_vote`) below which the global prior's vote is thin:
#: there the default is a ``steady`` candidate (a black box) whatever the other candidates' sums, without its
#: guard: the one of least crossed vote (:func:`.selection.crossed_sum`, :func:`_thin_default`), and it is not blended
#: (``_global_prior(thin_vote=)``; 0: never).  The voters are then the pixels whose neighbourhoods missed a
#: rare light the rest of the image found, a selection by their own samples that biases their estimates: a
#: filter of those samples scored by Stein's estimate looks better than it is, a black box cross-validated
#: against a half that missed the light worse (the tuning spotlit texture, 85 % of the pixels left out: the
#: pixel mean's summed estimate there 0.58 of its true error, OIDN + albedo + normal's 4.7 times).  The
#: tuning half's shares: the spotlit texture 0.15, cycles-window 0.52, caustic-0 0.59-0.62 (by seed), then
#: caustic-2 0.89, cycles-glossy_hdr 0.93, mitsuba-floor_spheres 0.94, cycles-studio 0.95.  0.6, not 0.75
#: (which takes every caustic-0 seed): a ring of rare samples on exact zeros (tests/test_auto.py) lies
#: between the two, and an OIDN default's 5 x 5 sample range lights its pixels whose 3 x 3 neighbourhood
#: holds only zeros.
THIN_VOTE = 0.6
#: The share below which an adaptive round reads the vote as thin (:func:`thin_vote_shown`,
#: ``AutoMethod.even_under_rare``): below :data:`THIN_VOTE` by a margin, as a scene whose share lies near the threshold
#: switches between the two rules with the render seed and the round (caustic-0 0.59-0.62).  With 0.6 the caustics' last
#: rounds went even where their allocation pays: Sobol, 128^2, 32 spp, adaptive over uniform caustic-0 0.764 against
#: 0.728 (last round 0.58), the default caustic 0.826 against 0.727 (4 seeds), held-out caustic-1 0.136 against 0.114;
#: with 0.5 these are unchanged and the spotlit texture's rounds still go even (0.46, 0.32, 0.19 after the first).
PLAN_THIN_VOTE = 0.5


def _thin_default(cands, steady, sums) -> int:
    """A thin vote's default: among the steady candidates, those whose crossed vote (:func:`.selection.crossed_sum`) is
    the least, then the least sum among them (the two candidates of one filter's halves share it); the
    least sum of all where none has one."""
    scored = [k for k in steady if cands[k].crossed is not None and np.isfinite(cands[k].crossed)]
    if scored:
        best = min(cands[k].crossed for k in scored)
        steady = [k for k in scored if cands[k].crossed == best]
    return min(steady, key=lambda k: sums[k])


def _could_vote(v, count, safeguard) -> int:
    """The pixels the global prior's vote could hold but for rare huge samples: with samples and, where the
    safeguard is on (its pins leave them out of the vote), some variance in a channel.  Exact dark pixels
    (every sample 0) are not left out by a rare light and do not make a vote thin."""
    has = count > 0
    if safeguard is not None:
        has &= (v > 0).any(axis=2)
    return int(np.count_nonzero(has))


def thin_vote_shown(stats, halves, safeguard, *, share: float | None = None) -> bool:
    """Whether the global prior's vote on these statistics is thin by a margin: fewer than ``share`` (default
    :data:`PLAN_THIN_VOTE`) of the pixels that could vote (:func:`_could_vote`) are left in it by the rare-sample
    and bright-pixel tests (:func:`.apart.left_out`, on the variances the selection reads:
    :func:`~mcrecon.core.halves.mean_variances` of ``halves``).  What an adaptive round reads
    (``AutoMethod.even_under_rare``), without the candidates: a pixel whose estimates are not finite counts as a voter
    here.  True too where the vote is heavy (:func:`.onesided.heavy_vote`, at the selection's
    :data:`.onesided.HEAVY_VOTE`).  False without halves."""
    count = stats.count
    if halves is None or not count.any():
        return False
    v = mean_variances(stats, halves)[0]
    apart = left_out(stats.mean, v, count, sample_range_bounds(stats)[1], safeguard is not None)[1]
    share = PLAN_THIN_VOTE if share is None else share
    vote = ~apart & (count > 0)
    return int(np.count_nonzero(vote)) < share * _could_vote(v, count, safeguard) \
        or heavy_vote(vote, one_sided(stats), count)
