"""gem's final risk guard reads a second estimate of the pixel means' variance: the prefix halves of each
pixel's sample sequence, which the scale selection (driven by s^2 / n) did not see.  Offline from samples
and in an adaptive run alike, so an adaptive run's image stays its log's image."""

import numpy as np
import pytest

import mcrecon
from mcrecon.core.samples import SampleSet
from mcrecon.core.stats import PixelStats
from mcrecon.core.strata import PrefixHalves, prefix_halves_of
from mcrecon.errors import InputError
from mcrecon.methods.gem.guard import risk_guard
from mcrecon.methods.gem.selection import _filter_bank
from mcrecon.filters.gaussian import TRUNCATE, final_sigmas


def _samples(w=24, h=20, spp=16, seed=0):
    rng = np.random.default_rng(seed)
    iy, ix = np.divmod(np.tile(np.arange(w * h), spp), w)       # round after round: each pixel in its order
    pos = np.stack([ix + rng.random(ix.size), iy + rng.random(iy.size)], axis=1)
    base = 0.5 + 0.4 * (ix > w // 2)                             # an edge, and noise of sd 0.3
    val = (base[:, None] + 0.3 * rng.standard_normal((ix.size, 3))).astype(np.float32)
    return SampleSet(pos.astype(np.float32), val, width=w, height=h)


def test_prefix_mean_variance_is_unbiased_for_independent_samples():
    src = _samples(w=32, h=32, spp=16)
    ph = prefix_halves_of(src)
    st = PixelStats.from_samples(src.positions, src.values, width=32, height=32)
    hv = ph.mean_variance(st.count)
    assert hv.shape == (32, 32, 3) and np.isfinite(hv).all()
    # E[((m_A - m_B) / 2)^2] = sigma^2 / 16 for 16 independent samples of sd 0.3 (3072 one-degree terms)
    assert abs(hv.mean() / (0.09 / 16) - 1.0) < 0.1


def test_prefix_mean_variance_unknown_without_two_halves():
    ph = PrefixHalves(2, 1, 1)
    ph.add(np.array([[0.5, 0.5], [0.5, 0.5], [1.5, 0.5]]), np.array([[1.0], [3.0], [2.0]]))
    hv = ph.mean_variance(np.array([[2, 1]]))
    assert hv[0, 0, 0] == pytest.approx(1.0) and np.isnan(hv[0, 1, 0])   # ((1 - 3) / 2)^2 x 2 / 2


def test_risk_guard_reads_the_given_variance():
    src = _samples()
    st = PixelStats.from_samples(src.positions, src.values, width=24, height=20)
    mv = st.sample_variance(undefined=0.0) / st.count[..., None]
    bank = _filter_bank(st.mean, mv, st.count, final_sigmas(4), subpixels=4, per_channel=True,
                        with_n_eff=False, sub=None, exact_below=0.0, truncate=TRUNCATE)
    coarse = np.full(st.count.shape, 3)
    img = np.asarray(bank.values[3])
    default = risk_guard(bank, coarse, img, st.count, radius=2.0)
    assert (default[:, :4] == 3).all() and (default[:, -3:] == 3).all()   # away from the edge smoothing saves
    # pixel means without error: every filter only adds bias, so every pixel keeps its mean
    zero = risk_guard(bank, coarse, img, st.count, radius=2.0, mean_variance=np.zeros_like(mv))
    assert (zero == 0).all()
    # unknown (NaN) entries fall back on the bank's variance
    nan = risk_guard(bank, coarse, img, st.count, radius=2.0, mean_variance=np.full_like(mv, np.nan))
    assert np.array_equal(nan, default)
    with pytest.raises(InputError, match="mean_variance"):
        risk_guard(bank, coarse, img, st.count, radius=2.0, mean_variance=mv[..., :2])


def test_offline_gem_reads_the_samples_prefix_halves(monkeypatch):
    import mcrecon.methods.gem.guard as guard

    seen, orig = [], guard.risk_guard

    def spy(*a, **kw):
        seen.append(kw.get("mean_variance"))
        return orig(*a, **kw)

    monkeypatch.setattr(guard, "risk_guard", spy)
    src = _samples(w=24, h=20, spp=8, seed=3)
    st = PixelStats.from_samples(src.positions, src.values, width=24, height=20)
    mcrecon.reconstruct(src, method="gem")
    mcrecon.reconstruct(st, method="gem")                       # no sample order: s^2 / n alone
    mcrecon.reconstruct(src, method="gem", guard_halves=0)
    assert [v is None for v in seen] == [False, True, True]
    ph = prefix_halves_of(src)
    v0 = st.sample_variance(undefined=0.0) / st.count[..., None]
    np.testing.assert_allclose(seen[0], 0.5 * (ph.mean_variance(st.count) + v0), rtol=1e-12)


def test_adaptive_image_is_its_logs_image(tmp_path, monkeypatch):
    import mcrecon.methods.gem.guard as guard
    from mcrecon.renderers.scenes import SceneRenderer

    seen, orig = [], guard.risk_guard

    def spy(*a, **kw):
        seen.append(kw.get("mean_variance"))
        return orig(*a, **kw)

    monkeypatch.setattr(guard, "risk_guard", spy)
    log = tmp_path / "run.h5"
    m = mcrecon.get_method("gem", iterations=2)
    res = mcrecon.adapt(SceneRenderer("checker_wall", width=32, height=24, seed=1, sampler="sobol"), m, spp=8,
                        seed=1, log=log, track_error=False, progress=False)
    again = mcrecon.reconstruct(log, method=m)
    assert len(seen) == 2 and seen[0] is not None and np.array_equal(seen[0], seen[1])
    assert np.array_equal(res.image, again)
