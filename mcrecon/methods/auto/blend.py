"""auto's blend of the global prior's default with its runner-up: a convex combination whose weight
minimises the pair's summed error estimate over the image.

For two reconstructions ``a`` and ``b`` of the same pixel and any weight ``w`` the identity

    (w a + (1 - w) b - mu)^2 = w (a - mu)^2 + (1 - w) (b - mu)^2 - w (1 - w) (a - b)^2

holds exactly (the variance of a two-point distribution), so from unbiased estimates ``M_a``, ``M_b`` of
the two squared errors ``w M_a + (1 - w) M_b - w (1 - w) (a - b)^2`` is unbiased for the blend's, the
last term known without noise.  Summed over the image (``S_a``, ``S_b``, ``D``) it is least at
``w = 1/2 - (S_a - S_b) / (2 D)``: two candidates of equal error whose errors differ (``D`` large) are
worth averaging; one far better than the other (``|S_a - S_b|`` near ``D``) keeps all the weight.
"""

from __future__ import annotations

import numpy as np

from .features import Candidate
from .passes import _means, _stored

#: The least weight worth a blend: below it the default stays the candidate itself (bit for bit).
MIN_WEIGHT = 0.02
#: Standard errors of the summed difference added to the runner-up's sum before the weight is computed
#: (Z_GLOBAL's: at 0.25 a flat field's even blend with a black box costs 1.5x on one seed of four).
Z_BLEND = 0.5


def blend_weight(s_a: float, s_b: float, d: float, penalty: float = 0.0) -> float:
    """The weight of ``a`` in the blend of least summed estimate ``w S_a + (1 - w) S_b - w (1 - w) D``,
    in [0, 1]; ``penalty`` is added to ``S_b`` first (the evidence ``b`` still owes: its guard's standard
    errors of the summed difference).  1 where ``D`` is not positive (the two agree: nothing to gain)."""
    if not d > 0 or not np.isfinite(s_a) or not np.isfinite(s_b):
        return 1.0
    return float(np.clip(0.5 - (s_a - (s_b + penalty)) / (2.0 * d), 0.0, 1.0))


def blended(a: Candidate, b: Candidate, w: float) -> Candidate:
    """``w a + (1 - w) b`` with the unbiased estimate of its squared error (the identity above, per pixel and
    channel); where ``b``'s value or estimate is undefined the pixel keeps ``a``'s.  Named and flagged as
    ``a`` (the selection's rules for ``a``, a black box's wide interval among them, apply to it)."""
    # in place, one image-sized temporary at a time (the global prior is auto's peak stage at 1080p);
    # the same operations, in the same order, as the three expressions written out, in float64 whatever
    # the candidates are stored in (the result is stored as they are: .passes._stored)
    f64 = np.float64
    img = np.multiply(a.image, w, dtype=f64)
    img += np.multiply(b.image, 1.0 - w, dtype=f64)
    img = _stored(img)
    mse = np.multiply(a.mse, w, dtype=f64)
    mse += np.multiply(b.mse, 1.0 - w, dtype=f64)
    d2 = np.subtract(a.image, b.image, dtype=f64)
    d2 *= d2
    d2 *= w * (1.0 - w)
    mse -= d2
    del d2
    mse = _stored(mse)
    bad = ~(np.isfinite(b.image) & np.isfinite(b.mse))
    if bad.any():
        img = np.where(bad, a.image, img)
        mse = np.where(bad, a.mse, mse)
    return Candidate(a.name, img, mse, a.feature)


def blend_default(cands, g: int, sums, vote: np.ndarray, den_loo: np.ndarray, guards: dict, se_of, v=None,
                  cap=None, among=None) -> tuple:
    """The global default ``g`` blended with the runner-up (the other candidate of least summed estimate,
    the pixel mean left out; with ``among``, one of those indices): ``(candidate, runner_up, w)``, or
    ``(None, r, 1.0)`` where the weight of ``g`` comes out above ``1 - MIN_WEIGHT``.

    ``sums``: each candidate's summed relative estimate over the voters ``vote``; ``den_loo`` the
    relative denominator they were divided by, each estimate capped at ``cap * v`` first (the squared
    differences are capped alike); ``guards``: index -> standard errors a guarded candidate must
    undercut by; ``se_of(k)``: the standard error of the summed difference of candidate ``k``'s
    estimates and ``g``'s.  The runner-up's sum is raised by :data:`Z_BLEND` of those standard errors,
    and by the difference of the two guards' where it is guarded more strictly than ``g`` (its estimate
    is then the noisier one: a cross-validated black box beside Stein estimates): the weight it gets
    must not rest on the noise of the sums (on a flat field every candidate's error lies far below it,
    and an even blend with a black box the guard kept out costs 4x).
    """
    others = [k for k in range(len(cands)) if k != g and not (k == 0 and cands[0].name == "box")
              and (among is None or k in among)]
    if not others:
        return None, -1, 1.0
    r = min(others, key=lambda k: sums[k])
    z = Z_BLEND + max(guards.get(r, 0.0) - guards.get(g, 0.0), 0.0)
    penalty = z * se_of(r) if z > 0 else 0.0
    # the squared differences capped as the estimates were (``cap`` times ``v``): against estimates capped
    # where a candidate is wild, an uncapped D would credit the blend with a spread the sums never charged
    d = np.subtract(cands[g].image, cands[r].image, dtype=np.float64)
    d *= d
    d = _means([d], den_loo, v, cap)[0]
    d = float(np.sum(np.where(vote & np.isfinite(d), d, 0.0)))
    w = blend_weight(sums[g], sums[r], d, penalty if np.isfinite(penalty) else np.inf)
    if w > 1.0 - MIN_WEIGHT:
        return None, r, 1.0
    return blended(cands[g], cands[r], w), r, w
