"""auto's global default blended with the two other candidates of least summed estimate: the weights on
the simplex of least summed estimate of the blend (``methods/auto/blend.py``)."""

import functools
import itertools

import numpy as np

from mcrecon.methods.auto import blend as bl
from mcrecon.methods.auto.blend import blend_default, blend_weight, mixed, simplex_weights
from mcrecon.methods.auto.features import Candidate


def _noisy_three(h=32, w=32, sd=0.05, seed=1):
    """Three unbiased reconstructions of a flat 0.5 with independent errors of variance ``sd^2`` and exact
    estimates of it, after the pixel mean."""
    rng = np.random.default_rng(seed)
    mu = np.full((h, w, 3), 0.5)
    v = np.full((h, w, 3), 4 * sd * sd)
    y = mu + rng.normal(0, 2 * sd, mu.shape)
    est = np.full(mu.shape, sd * sd)
    out = [Candidate("box", y.copy(), v.copy())]
    for name in ("gauss1", "nlm", "dnlm"):
        out.append(Candidate(name, mu + rng.normal(0, sd, mu.shape), est.copy()))
    return mu, y, v, out


@functools.lru_cache
def _simplex_grid(k, n):
    c = np.array([c for c in itertools.product(range(n + 1), repeat=k - 1) if sum(c) <= n])
    return np.column_stack([c, n - c.sum(axis=1)]) / n


def _grid_best(s, d, n=40):
    """The least of ``w.s - w.D.w / 2`` over the simplex points of step ``1/n`` (all at once)."""
    w = _simplex_grid(len(s), n)
    return float(np.min(w @ s - 0.5 * np.einsum("pi,ij,pj->p", w, d, w)))


def test_simplex_weights_are_the_least_of_the_blend_estimate_and_the_pair_formula_for_two():
    rng = np.random.default_rng(0)
    for _ in range(10):
        p = rng.normal(size=(4, 2))
        d = ((p[:, None] - p[None]) ** 2).sum(-1) * rng.uniform(0.5, 3)
        s = rng.uniform(1, 3, 4)
        w = simplex_weights(s, d)
        assert abs(w.sum() - 1) < 1e-12 and (w >= 0).all()
        assert w @ s - 0.5 * w @ d @ w <= _grid_best(s, d) + 1e-12
    s, d = np.array([10.0, 12.0]), np.array([[0.0, 20.0], [20.0, 0.0]])
    assert abs(simplex_weights(s, d)[0] - blend_weight(10.0, 12.0, 20.0)) < 1e-12


def test_three_equal_candidates_are_averaged_and_the_estimate_of_the_mix_is_unbiased():
    mu, y, v, cands = _noisy_three()
    vote = np.ones(y.shape[:2], bool)
    den = np.ones(y.shape)
    sums = [float(c.mse.mean(axis=2).sum()) for c in cands]
    b, r, w = blend_default(cands, 1, sums, vote, den, {}, lambda k: 0.0)
    assert b is not None and b.name == "gauss1" and abs(w - 1 / 3) < 0.05
    true = float(np.mean((b.image - mu) ** 2))
    assert true < 0.4 * 0.05 ** 2  # a third of one candidate's variance (a pair: a half)
    assert abs(float(b.mse.mean()) - true) < 0.05 * true
    # with the blend of two only (the pair rule) the error is a half of one candidate's
    size = bl.BLEND_SIZE
    try:
        bl.BLEND_SIZE = 2
        b2, _, _ = blend_default(cands, 1, sums, vote, den, {}, lambda k: 0.0)
    finally:
        bl.BLEND_SIZE = size
    assert float(np.mean((b2.image - mu) ** 2)) > 0.45 * 0.05 ** 2


def test_a_pair_optimum_is_the_pair_blend_bit_for_bit():
    mu, y, v, cands = _noisy_three()
    vote = np.ones(y.shape[:2], bool)
    den = np.ones(y.shape)
    sums = [float(c.mse.mean(axis=2).sum()) for c in cands]
    # the third's sum raised by its (here huge) standard error: it gets no weight
    b, r, w = blend_default(cands, 1, sums, vote, den, {}, lambda k: 1e6 if k == 3 else 0.0)
    ref = bl.blended(cands[1], cands[2], w)
    assert r == 2 and np.array_equal(b.image, ref.image) and np.array_equal(b.mse, ref.mse)
    m = mixed([cands[1], cands[2]], [w, 1 - w])
    assert np.allclose(m.image, ref.image) and np.allclose(m.mse, ref.mse, atol=1e-9)


def test_the_proxy_computes_the_regressions_where_one_may_be_a_later_blend_partner():
    from mcrecon.methods.auto import proxy
    V = proxy.Verdict
    assert V(0.0, "nlm", "oidn_halves", False, ("nfor",)).computes(0.1)
    assert not V(0.0, "nlm", "oidn_halves", False, ("gauss8",)).computes(0.1)
    assert not V(0.0, "oidn_aux", "oidn_aux_halves", True, ("nfor",)).computes(0.1)  # partners: black boxes
