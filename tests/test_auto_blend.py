"""auto's global default blended with its runner-up: a convex combination weighted by the pair's summed
error estimates, whose own estimate follows from the exact two-point identity (``methods/auto/blend.py``)."""

import numpy as np

from mcrecon.methods.auto.blend import blend_default, blend_weight, blended
from mcrecon.methods.auto.features import Candidate
from mcrecon.methods.auto.selection import _global_prior


def _noisy_pair(h=48, w=48, sd=0.05, seed=0):
    """Two unbiased reconstructions of a flat 0.5 with independent errors of equal variance ``sd^2`` and
    exact estimates of it, the pixel mean (variance 4 sd^2) first."""
    rng = np.random.default_rng(seed)
    mu = np.full((h, w, 3), 0.5)
    v = np.full((h, w, 3), 4 * sd * sd)
    y = mu + rng.normal(0, 2 * sd, mu.shape)
    a = mu + rng.normal(0, sd, mu.shape)
    b = mu + rng.normal(0, sd, mu.shape)
    est = np.full(mu.shape, sd * sd)
    return mu, y, v, [Candidate("box", y.copy(), v.copy()), Candidate("gauss1", a, est),
                      Candidate("nlm", b, est.copy())]


def test_blend_of_two_unbiased_candidates_of_equal_variance_halves_it_and_estimates_it():
    mu, y, v, cands = _noisy_pair()
    a, b = cands[1], cands[2]
    n = a.image.size
    d = float(np.sum((a.image - b.image) ** 2))
    w = blend_weight(float(a.mse.sum()), float(b.mse.sum()), d)
    assert abs(w - 0.5) < 0.05
    m = blended(a, b, w)
    true = float(np.sum((m.image - mu) ** 2)) / n
    assert true < 0.55 * 0.05 ** 2  # the analytic best: half the variance
    assert abs(float(m.mse.sum()) / n - true) < 0.05 * true  # the identity's estimate, unbiased
    assert m.name == "gauss1" and not m.feature


def test_blend_weight_is_the_analytic_optimum_and_keeps_a_candidate_that_holds_the_other_alone():
    mu, y, v, cands = _noisy_pair()
    a, b = cands[1], cands[2]
    # b biased by 0.2 (its estimate says so): the least squared error of w a + (1 - w) b is at
    # w = (sd^2 + 0.04) / (2 sd^2 + 0.04)
    worse = Candidate("nlm", b.image + 0.2, b.mse + 0.04)
    d = float(np.sum((a.image - worse.image) ** 2))
    w = blend_weight(float(a.mse.sum()), float(worse.mse.sum()), d)
    assert abs(w - (0.0025 + 0.04) / (0.005 + 0.04)) < 0.01
    # b = a plus independent noise: a holds everything b knows, the blend gives b nothing
    rng = np.random.default_rng(1)
    noisier = Candidate("nlm", a.image + rng.normal(0, 0.05, a.image.shape), a.mse + 0.0025)
    d = float(np.sum((a.image - noisier.image) ** 2))
    assert blend_weight(float(a.mse.sum()), float(noisier.mse.sum()), d) > 0.98
    assert blend_weight(1.0, 1.0, 0.0) == 1.0  # identical images: nothing to gain


def test_a_guarded_runner_up_owes_its_standard_errors():
    # a runner-up whose estimate is the noisier one (a black box beside Stein estimates) gets less weight
    # the larger the standard error of the summed difference it must overcome
    assert blend_weight(10.0, 10.0, 20.0, penalty=0.0) == 0.5
    assert blend_weight(10.0, 10.0, 20.0, penalty=6.0) == 0.65
    assert blend_weight(10.0, 10.0, 20.0, penalty=40.0) == 1.0
    mu, y, v, cands = _noisy_pair()
    vote = np.ones(y.shape[:2], bool)
    den = np.ones(y.shape)
    sums = [float(c.mse.mean(axis=2).sum()) for c in cands]
    b, r, w = blend_default(cands, 1, sums, vote, den, {2: 1.0}, lambda k: 1e6)
    assert b is None and r == 2 and w == 1.0
    b, r, w = blend_default(cands, 1, sums, vote, den, {2: 1.0}, lambda k: 0.0)
    assert b is not None and 0.4 < w < 0.6


def test_global_prior_outputs_the_blend_of_two_equal_candidates():
    mu, y, v, cands = _noisy_pair()
    h, w = y.shape[:2]
    count = np.full((h, w), 16)
    bounds = (y - 1.0, y + 1.0)
    plain = np.zeros((h, w), np.int64)
    errs = {}
    for blend in (False, True):
        cs = list(cands)
        raw = [c.mse.mean(axis=2) / 0.25 for c in cs]
        got, held = _global_prior(cs, lambda k: cs[k].mse.mean(axis=2) / 0.25, np.stack(raw), plain, y, v,
                                  count, bounds, 2.0, 3.0, 4.0, blend=blend)
        assert held.all()
        g = int(got[0, 0])
        errs[blend] = float(np.mean((cs[g].image - mu) ** 2))
    assert errs[True] < 0.6 * errs[False]
