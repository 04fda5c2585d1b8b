"""auto's tile proxy: the regression candidates are computed over the whole image only where a few tiles say
they can win (option ``regression_proxy``)."""

import numpy as np
import pytest

from mcrecon.core.halves import split_halves
from mcrecon.core.samples import SampleSet
from mcrecon.methods import get_method
from mcrecon.methods.auto import proxy
from mcrecon.methods.base import MethodInputs

N = 48
SPP = 8


def _scene(kind, seed=0, spp=SPP):
    """Halves of an N x N film with albedo and normal: ``linear``, the colour a linear function of a
    textured albedo (the regressions fit it exactly); ``uncorrelated``, a flat colour whose features are
    fresh noise at every sample (nothing for a regression to fit)."""
    rng = np.random.default_rng(seed)
    n = N * N * spp
    pix = np.repeat(np.arange(N * N), spp)
    pos = np.stack([pix % N + rng.random(n), pix // N + rng.random(n)], axis=1)
    if kind == "linear":
        texture = rng.random((N * N, 3)) * 0.8 + 0.1
        albedo = texture[pix]
        colour = 0.1 + 2.0 * albedo
    else:
        albedo = rng.random((n, 3))
        colour = np.full((n, 3), 0.5)
    normal = rng.normal(size=(n, 3)) if kind != "linear" else np.tile([0.0, 0.0, 1.0], (n, 1))
    values = colour * rng.exponential(size=(n, 1))
    ss = SampleSet(pos, values, width=N, height=N, features={"albedo": albedo, "normal": normal})
    return split_halves(ss, features=("albedo", "normal"))


@pytest.fixture
def small_tiles(monkeypatch):
    # four 8 x 8 tiles grown by 12 px on a 48^2 film: the proxy is normally kept to frames of ~400^2 and more
    monkeypatch.setattr(proxy, "TILE", 8)
    monkeypatch.setattr(proxy, "HALO", 12)
    monkeypatch.setattr(proxy, "MAX_AREA", 100.0)


def _run(hv, threshold):
    m = get_method("auto", regression_proxy=threshold)
    run = m.start(N, N)
    img = m.reconstruct_run(run, MethodInputs(hv.merged(), None, None, halves=hv))
    return img, run


def _calls(monkeypatch):
    from mcrecon.filters import regression

    seen, orig = [], regression.collaborative_regression

    def spy(img, *a, **kw):
        seen.append((img[0] if isinstance(img, (list, tuple)) else img).shape[:2])   # colours given apart
        return orig(img, *a, **kw)

    monkeypatch.setattr(regression, "collaborative_regression", spy)
    return seen


def test_the_proxy_skips_the_regressions_where_the_features_say_nothing(small_tiles, monkeypatch):
    seen = _calls(monkeypatch)
    # at 32 spp the widest Gaussians have the tiles' least summed estimates: no regression is the
    # default's or its blend partner's candidate
    _, run = _run(_scene("uncorrelated", seed=2, spp=32), 0.05)
    assert run.regression_share is not None and run.regression_share < 0.05
    assert not run.regression_verdict.computes(0.05)
    assert not any(n.startswith(("nfor", "mix")) for n in run.candidate_names)
    # the regression ran on the proxy's mosaic of grown tiles only, never on the whole film
    side = proxy.TILE + 2 * proxy.HALO
    assert seen and all(s[1] == side for s in seen)


def test_the_proxy_computes_the_regressions_where_they_win_and_the_image_is_unchanged(small_tiles):
    hv = _scene("linear")
    img, run = _run(hv, 0.05)
    assert run.regression_share > 0.5
    assert "nfor" in run.candidate_names
    ref, ref_run = _run(hv, None)
    assert ref_run.regression_share is None
    np.testing.assert_array_equal(img, ref)


def test_proxy_windows_fit_the_image_and_are_left_out_on_small_ones():
    assert proxy.proxy_windows(128, 128) is None   # four grown 64^2 tiles would cover more than the frame
    w = proxy.proxy_windows(1080, 1920)
    assert len(w) == len(set(w)) >= proxy.MIN_TILES
    for y0, x0 in w:
        assert proxy.HALO <= y0 <= 1080 - proxy.HALO - proxy.TILE
        assert proxy.HALO <= x0 <= 1920 - proxy.HALO - proxy.TILE
    assert w == proxy.proxy_windows(1080, 1920)


def test_the_proxy_computes_the_regressions_where_one_has_the_least_summed_estimate_on_the_tiles(small_tiles):
    # the tiles' choice gives the regressions no pixel, yet one of them has the least summed estimate
    # there: the whole frame's global prior, whose margin a frame clears more easily than a few tiles,
    # may make it the default, so they are computed (the image is the proxy-off one)
    hv = _scene("uncorrelated")
    img, run = _run(hv, 0.05)
    assert run.regression_share < 0.05 and proxy.is_regression(run.regression_verdict.least)
    assert "nfor" in run.candidate_names
    ref, _ = _run(hv, None)
    np.testing.assert_array_equal(img, ref)


def test_the_verdict_computes_where_a_regression_may_be_the_default_or_its_blend_partner():
    V = proxy.Verdict
    assert V(0.2, "nlm", "gauss8", False).computes(0.1)
    assert V(0.0, "nfor_own", "nlm", False).computes(0.1) and V(0.0, "mix33", "oidn_aux", False).computes(0.1)
    # the runner-up is the default's blend partner, unless the default is a black box (its partner is one)
    assert V(0.0, "nlm", "nfor", False).computes(0.1)
    assert not V(0.0, "oidn_aux_halves", "nfor", True).computes(0.1)
    assert not V(0.05, "oidn_aux", "dnlm", True).computes(0.1)
