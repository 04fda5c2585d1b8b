"""auto's local test against the global default: z standard errors for all the other candidates together
(Sidak's correction, ``selection.local_z``), so that more candidates do not mean more pixels leaving
the default by chance."""

import numpy as np

from mcrecon.methods.auto import selection as sel
from mcrecon.methods.auto.features import Candidate
from mcrecon.methods.auto.selection import _global_prior, local_z


def test_local_z_is_z_for_one_test_and_sidak_for_several():
    assert local_z(3.0, 1) == 3.0
    assert abs(local_z(3.0, 11) - 3.667) < 2e-3
    assert local_z(3.0, 18) > local_z(3.0, 11) > local_z(3.0, 2) > 3.0


def _flat(h=96, w=96, alternatives=10, seed=3):
    """A flat field: the pixel mean, a default ``gauss`` of small error with an exact estimate, and
    ``alternatives`` worse candidates whose estimates are their true error plus independent noise."""
    rng = np.random.default_rng(seed)
    mu = np.full((h, w, 3), 0.5)
    v = np.full((h, w, 3), 0.01)
    y = mu + rng.normal(0, 0.1, mu.shape)
    cands = [Candidate("box", y.copy(), v.copy()),
             Candidate("gauss", mu + rng.normal(0, 0.01, mu.shape), np.full(mu.shape, 1e-4))]
    for i in range(alternatives):
        img = mu + rng.normal(0, 0.011, mu.shape)
        cands.append(Candidate(f"alt{i}", img, (img - mu) ** 2 + rng.normal(0, 1e-3, mu.shape)))
    return y, v, cands


def _left(y, v, cands):
    h, w = y.shape[:2]
    count = np.full((h, w), 32)
    raw = np.stack([c.mse.mean(axis=2) / 0.25 for c in cands])
    got, _ = _global_prior(list(cands), lambda k: raw[k], raw, np.ones((h, w), np.int64), y, v, count,
                           (y - 1.0, y + 1.0), 1.0, 3.0, 4.0, blend=False)
    assert np.median(got) == 1  # the default is the small-error candidate
    return float(np.mean(got != 1))


def test_more_candidates_do_not_take_more_pixels_from_the_default_by_chance(monkeypatch):
    y, v, cands = _flat()
    corrected = _left(y, v, cands)
    monkeypatch.setattr(sel, "local_z", lambda z, m: z)  # each test at z alone
    plain = _left(y, v, cands)
    assert corrected < 0.4 * plain  # measured: 0.005 against 0.024 of the pixels
