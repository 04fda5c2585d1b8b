"""Where the samples show no structure beyond noise (a constant image under homogeneous noise), an adaptive
round is uniform: any allocation would rank pixels by their noise and can only lose to a uniform render of the
same budget (gem's Sobol flat scene otherwise errs 100x uniform's), so gem, awr and auto end at its counts."""

from __future__ import annotations

import numpy as np
import pytest

import mcrecon
from mcrecon.core.nets import even_round, shows_structure
from mcrecon.core.stats import PixelStats
from mcrecon.methods import get_method
from mcrecon.methods.base import Method

from helpers import jittered_renderer

W = H = 16


def _stats(values_of, spp=4, seed=0):
    rng = np.random.default_rng(seed)
    pix = np.repeat(np.arange(W * H), spp)
    pos = np.stack([pix % W + rng.random(pix.size), pix // W + rng.random(pix.size)], axis=1)
    st = PixelStats(W, H)
    st.add(pos, values_of(pos, rng))
    return st


@pytest.mark.parametrize("seed", range(5))
def test_homogeneous_noise_shows_no_structure(seed):
    assert not shows_structure(_stats(lambda pos, rng: rng.uniform(0.0, 1.0, (len(pos), 3)), seed=seed))
    assert not shows_structure(_stats(lambda pos, rng: 3.0 + rng.normal(0.0, 0.5, (len(pos), 3)), seed=seed))


def _edge(pos, rng):
    return np.where(pos[:, :1] < W / 2, 0.4, 0.6) + rng.uniform(-0.5, 0.5, (len(pos), 3))


def _uneven_noise(pos, rng):
    return 0.5 + np.where(pos[:, :1] < W / 2, 0.2, 0.5) * rng.uniform(-1, 1, (len(pos), 3))


def test_an_edge_or_uneven_noise_is_structure():
    assert shows_structure(_stats(_edge))
    assert shows_structure(_stats(_uneven_noise))


class _State:
    def __init__(self, count, sampler):
        self.stats = type("S", (), {"count": count})()
        self.pending, self.sampler, self.rng = None, sampler, np.random.default_rng(0)


@pytest.mark.parametrize("sampler", ["sobol", "independent"])
def test_even_round_reaches_uniform_counts(sampler):
    count = np.full((H, W), 4, np.int64)
    count[0, :3] = 8
    out = even_round(_State(count, sampler), 28 * W * H - 12)
    assert np.array_equal(count + out, np.full((H, W), 32))


def _flat(sampler):
    film = jittered_renderer(lambda pos, rng, req: rng.uniform(0.0, 1.0, (len(pos), 3)), width=W, height=H)
    film.sampler = sampler
    return film


def _counts(name, sampler):
    m = get_method(name, candidates="box,gauss") if name == "auto" else get_method(name)
    return mcrecon.adapt(_flat(sampler), m, spp=32, seed=1, progress=False, track_error=False).stats.count


@pytest.mark.parametrize("sampler", ["sobol", "independent"])
@pytest.mark.parametrize("name", ["gem", "awr", "auto"])
def test_adaptive_run_without_structure_ends_uniform(name, sampler):
    assert np.array_equal(_counts(name, sampler), np.full((H, W), 32))


def test_without_the_test_gem_spends_unevenly(monkeypatch):
    monkeypatch.setattr(Method, "structure_test", False)
    assert np.ptp(_counts("gem", "sobol")) > 0


def test_the_paper_variants_plan_as_their_papers_do():
    for name in ("gem", "awr"):
        m = get_method(name, variant="paper")
        c = mcrecon.adapt(_flat("sobol"), m, spp=32, seed=1, progress=False, track_error=False).stats.count
        assert np.ptp(c) > 0, name


def _dispersions_numpy(stats):
    """The two dispersion statistics written out in numpy (the brute force the compiled passes must equal)."""
    n = stats.count.astype(np.float64)
    ok = n >= 2
    n = n[ok][:, None]
    k = n - 1.0
    mean, m2 = stats.mean[ok], stats.m2[ok]
    sigma2 = m2.sum(axis=0) / k.sum()
    mbar = (n * mean).sum(axis=0) / n.sum()
    t_mean = np.mean(n * (mean - mbar) ** 2 / sigma2, axis=0)
    t_var = np.mean(k * (m2 / (k * sigma2) - 1.0) ** 2 / 2.0, axis=0)
    return sigma2, mbar, t_mean, t_var, int(ok.sum()), float(k.min())


@pytest.mark.parametrize("values_of", [_edge, _uneven_noise, lambda pos, rng: rng.normal(2.0, 0.5, (len(pos), 3))])
def test_compiled_dispersions_equal_numpy(values_of):
    from mcrecon.core.nets import _dispersions, _pooled_sums

    st = _stats(values_of, spp=3, seed=4)
    st.count[::7] = 1                                # pixels of one sample take no part
    st.count[::11] = 0
    sigma2, mbar, t_mean, t_var, n_ok, k_min = _dispersions_numpy(st)
    c = st.mean.shape[-1]
    args = (st.count.reshape(-1), st.mean.reshape(-1, c), st.m2.reshape(-1, c))
    got_n, k_sum, got_kmin, n_sum, m2_sum, nm_sum, lo, hi = _pooled_sums(*args)
    assert (got_n, got_kmin) == (n_ok, k_min)
    np.testing.assert_allclose(m2_sum / k_sum, sigma2, rtol=1e-12)
    np.testing.assert_allclose(nm_sum / n_sum, mbar, rtol=1e-12)
    ok = st.count >= 2
    np.testing.assert_array_equal(lo, st.mean[ok].min(axis=0))
    np.testing.assert_array_equal(hi, st.mean[ok].max(axis=0))
    tm, tv = _dispersions(*args, sigma2, mbar, np.ones(c, bool))
    np.testing.assert_allclose(tm, t_mean, rtol=1e-10)
    np.testing.assert_allclose(tv, t_var, rtol=1e-10)
