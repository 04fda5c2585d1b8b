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

import dataclasses
import itertools

import numpy as np

from .features import Candidate
from .passes import _means, _stored

#: The least weight worth a blend: below it the default stays the candidate itself (bit for bit).
MIN_WEIGHT = 0.02
#: Standard errors of the summed difference added to the runner-up's sum before the weight is computed
#: (Z_GLOBAL's: at 0.25 a flat field's even blend with a black box costs 1.5x on one seed of four).
Z_BLEND = 0.5
#: The most candidates a blend mixes: the default and the others of least summed estimate.
BLEND_SIZE = 3


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


def simplex_weights(s: np.ndarray, d: np.ndarray) -> np.ndarray:
    """The weights ``w`` on the simplex (``w >= 0``, ``sum w = 1``) of least ``w.s - w.D.w / 2``: the summed
    estimate of the blend ``sum_k w_k x_k`` from the candidates' summed estimates ``s`` (K,) and their
    summed squared differences ``D`` (K, K), by the identity ``(sum w_k x_k - mu)^2 = sum w_k (x_k - mu)^2
    - sum_{j<k} w_j w_k (x_j - x_k)^2``.

    Exact for the few candidates a blend mixes: the least of the stationary points of every face of the
    simplex that lie on it (a quadratic's least value on a polytope is one of them, whether or not the
    capped ``D`` keeps it convex); ties to the face met first, the vertices first, the first candidate
    first."""
    s = np.asarray(s, np.float64)
    d = np.asarray(d, np.float64)
    k = s.size
    best_w = np.zeros(k)
    best_w[int(np.argmin(s))] = 1.0
    best = float(s.min())
    for size in range(2, k + 1):
        for face in itertools.combinations(range(k), size):
            f = list(face)
            # stationary on the face's affine hull: D_ff w + lam 1 = s_f, 1.w = 1
            a = np.zeros((size + 1, size + 1))
            a[:size, :size] = d[np.ix_(f, f)]
            a[:size, size] = 1.0
            a[size, :size] = 1.0
            b = np.append(s[f], 1.0)
            try:
                sol = np.linalg.solve(a, b)
            except np.linalg.LinAlgError:
                continue
            w = sol[:size]
            if not np.all(np.isfinite(w)) or np.any(w <= 0.0):
                continue
            full = np.zeros(k)
            full[f] = w
            obj = float(full @ s - 0.5 * full @ d @ full)
            if obj < best - 1e-12 * max(abs(best), 1.0):
                best, best_w = obj, full
    return best_w


def mixed(parts, w) -> Candidate:
    """``sum_k w_k parts[k]`` with the unbiased estimate of its squared error ``sum_k w_k (M_k - (x_k -
    x)^2)`` (``x`` the blend: the identity of :func:`simplex_weights`, per pixel and channel), in float64;
    where a partner's value or estimate is undefined the pixel keeps the first's.  Named and flagged as the
    first (:func:`blended`'s rule)."""
    a = parts[0]
    f64 = np.float64
    img = np.zeros(a.image.shape, f64)
    for c, wk in zip(parts, w):
        img += np.multiply(c.image, wk, dtype=f64)
    mse = np.zeros(a.image.shape, f64)
    for c, wk in zip(parts, w):
        d2 = np.subtract(c.image, img, dtype=f64)
        d2 *= d2
        d2 = np.subtract(c.mse, d2, dtype=f64)
        d2 *= wk
        mse += d2
        del d2
    img, mse = _stored(img), _stored(mse)
    bad = np.zeros(a.image.shape, bool)
    for c in parts[1:]:
        bad |= ~(np.isfinite(c.image) & np.isfinite(c.mse))
    if bad.any():
        img = np.where(bad, a.image, img)
        mse = np.where(bad, a.mse, mse)
    return Candidate(a.name, img, mse, a.feature)


def blend_default(cands, g: int, sums, vote: np.ndarray, den_loo: np.ndarray, guards: dict, se_of, v=None,
                  cap=None, among=None, plan: bool = False) -> tuple:
    """The global default ``g`` blended with the other candidates of least summed estimate (up to
    :data:`BLEND_SIZE` in all, the pixel mean left out; with ``among``, those indices only):
    ``(candidate, runner_up, w)`` (``w`` the weight of ``g``), or ``(None, runner_up, 1.0)`` where that
    weight comes out above ``1 - MIN_WEIGHT``; with ``plan`` the :class:`Blend` in place of the candidate
    (None where there is none): what a tile applies to its own candidates.

    The weights are those of least summed estimate of the blend (:func:`simplex_weights`); where the
    optimum mixes ``g`` with one partner only, they are :func:`blend_weight`'s and the image
    :func:`blended`'s, bit for bit.  ``sums``: each candidate's summed relative estimate over the
    voters ``vote``; ``den_loo`` the relative denominator they were divided by, each estimate capped at
    ``cap * v`` first (the squared differences are capped alike); ``guards``: index -> standard errors a
    guarded candidate must undercut by; ``se_of(k)``: the standard error of the summed difference of
    candidate ``k``'s estimates and ``g``'s.  Each partner's sum is raised by :data:`Z_BLEND` of those
    standard errors, and by the difference of the two guards' where it is guarded more strictly than
    ``g`` (its estimate is then the noisier one: a cross-validated black box beside Stein estimates):
    the weight it gets must not rest on the noise of the sums (on a flat field every candidate's error
    lies far below it, and an even blend with a black box the guard kept out costs 4x).
    """
    others = [k for k in range(len(cands)) if k != g and not (k == 0 and cands[0].name == "box")
              and (among is None or k in among) and np.isfinite(sums[k])]
    if not others:
        return None, -1, 1.0
    others = sorted(others, key=lambda k: sums[k])[:BLEND_SIZE - 1]
    pen = []
    for r in others:
        z = Z_BLEND + max(guards.get(r, 0.0) - guards.get(g, 0.0), 0.0)
        p = z * se_of(r) if z > 0 else 0.0
        pen.append(p if np.isfinite(p) else np.inf)
    # the squared differences capped as the estimates were (``cap`` times ``v``): against estimates capped
    # where a candidate is wild, an uncapped D would credit the blend with a spread the sums never charged
    idx = [g] + others
    n = len(idx)
    dm = np.zeros((n, n))
    for a in range(n):
        for b in range(a + 1, n):
            d = np.subtract(cands[idx[a]].image, cands[idx[b]].image, dtype=np.float64)
            d *= d
            d = _means([d], den_loo, v, cap)[0]
            dm[a, b] = dm[b, a] = float(np.sum(np.where(vote & np.isfinite(d), d, 0.0)))
    s = np.array([sums[g]] + [sums[r] + p for r, p in zip(others, pen)])
    if not np.all(np.isfinite(s)):
        keep = [0] + [a for a in range(1, n) if np.isfinite(s[a])]
        idx, s, dm = [idx[a] for a in keep], s[keep], dm[np.ix_(keep, keep)]
    w = simplex_weights(s, dm) if len(idx) > 1 else np.ones(1)
    if w[0] > 1.0 - MIN_WEIGHT:
        return None, others[0], 1.0
    on = [a for a in range(len(idx)) if a == 0 or w[a] > 0.0]
    if len(on) == 2:  # one partner: the pair's own weight and blend, as two candidates always had
        a = on[1]
        wg = blend_weight(sums[g], sums[idx[a]], dm[0, a], dict(zip(others, pen))[idx[a]])
        if wg > 1.0 - MIN_WEIGHT:
            return None, others[0], 1.0
        blend = Blend((g, idx[a]), (wg,))
    else:
        blend = Blend(tuple(idx[a] for a in on), tuple(float(w[a]) for a in on))
    return (blend if plan else blend.of(cands)), others[0], blend.weight


@dataclasses.dataclass(frozen=True)
class Blend:
    """A blend of the global default ``parts[0]`` with ``parts[1:]`` (candidate indices), decided on the
    image's sums (:func:`blend_default`) and applied to any crop of the candidates (:meth:`of`: a tile's,
    the same values at its pixels).  ``weights``: the default's weight alone for a pair (:func:`blended`),
    every part's for more (:func:`mixed`)."""

    parts: tuple
    weights: tuple

    @property
    def weight(self) -> float:
        """The default's weight."""
        return float(self.weights[0])

    def of(self, cands) -> Candidate:
        """The blended candidate of ``cands`` (the blend's pixels: those of ``cands``)."""
        if len(self.parts) == 2 and len(self.weights) == 1:
            return blended(cands[self.parts[0]], cands[self.parts[1]], self.weights[0])
        return mixed([cands[k] for k in self.parts], list(self.weights))
