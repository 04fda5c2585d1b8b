"""Tiles of films with mixed sample counts reproduce the untiled image: a pixel with one sample (in a half, or in
all) borrows a variance from its 3 x 3 neighbours, else the film's average (mcrecon.core.fill.mean_variance_policy),
which each tile is given (PixelStats.film_fill, mcrecon.offline.tiles.FilmFill); a pixel without a sample is
refused."""

from __future__ import annotations

import numpy as np
import pytest

import mcrecon
from mcrecon.core.fill import FilmRange, FilmRangeSum, mean_variance_policy, variance_defined
from mcrecon.core.samples import SampleSet
from mcrecon.core.stats import PixelStats
from mcrecon.errors import InputError
from mcrecon.io import write_log
from mcrecon.offline import tiles as T

pytestmark = pytest.mark.filterwarnings("ignore")


def _samples(w, h, base, corner, seed=0, features=False):
    """``base`` samples a pixel, ``corner`` in the film's 6 x 6 top-left corner (the only pixels with two or more
    when ``base`` is 1), shuffled; values with a horizontal gradient and gamma noise."""
    rng = np.random.default_rng(seed)
    counts = np.full((h, w), base)
    counts[:6, :6] = corner
    pix = np.repeat(np.arange(w * h), counts.ravel())
    rng.shuffle(pix)
    n = pix.size
    pos = np.stack([pix % w + rng.random(n), pix // w + rng.random(n)], 1)
    x = pos[:, 0] / w
    val = np.stack([0.5 + 0.5 * np.sin(8 * x), 0.3 + 0 * x, 0.2 + 0.2 * x], 1) * rng.gamma(2.0, 0.5, (n, 1))
    feats = None
    if features:
        feats = {"albedo": np.stack([0.5 + 0.5 * np.sin(8 * x)] * 3, 1) + 0.01 * rng.standard_normal((n, 3)),
                 "normal": np.tile([0.0, 0.0, 1.0], (n, 1)) + 0.01 * rng.standard_normal((n, 3)),
                 "depth": (1 + x)[:, None] + 0.01 * rng.standard_normal((n, 1))}
    return pos, val, feats


def _sample_set(w, h, base, corner, **kw):
    pos, val, feats = _samples(w, h, base, corner, **kw)
    return SampleSet(pos, val, width=w, height=h, features=feats)


def test_film_range_added_band_by_band_is_the_films_bit_for_bit():
    """Several channels (summed one after the other) and one (a depth: summed pairwise, over more than numpy's
    blocks of 128 values)."""
    rng = np.random.default_rng(3)
    for i in range(40):
        h, w = (int(v) for v in rng.integers(1, 80, 2))
        values = rng.random((h, w, 1 + 2 * (i % 2))) * 10.0 ** rng.uniform(-6, 6, (h, w, 1))
        defined = rng.random((h, w)) < rng.random()
        total = FilmRangeSum()
        cuts = sorted({0, h, *(int(c) for c in rng.integers(0, h, 3))})
        for y0, y1 in zip(cuts[:-1], cuts[1:]):
            total.add(values[y0:y1], defined[y0:y1])
        got = total.result()
        if not defined.any():
            assert got == FilmRange(None, None, None)
            continue
        assert np.array_equal(got.mean, values[defined].mean(axis=0))
        assert np.array_equal(got.lo, values[defined].min(axis=0))
        assert np.array_equal(got.hi, values[defined].max(axis=0))


def test_a_crop_given_the_films_values_fills_as_the_film():
    """1 spp but for a 2-spp corner: away from it a pixel's variance is the film's average, which a crop without
    the corner does not hold (it would take its own fallback, the spread of its pixel values)."""
    pos, val, _ = _samples(40, 30, 1, 2)
    st = PixelStats(40, 30)
    st.add(pos, val)
    full = mean_variance_policy(st)
    crop = st.crop(10, 30, 12, 40)
    film = FilmRangeSum()
    film.add(*variance_defined(st))
    got = mean_variance_policy(crop, film=film.result())
    assert np.array_equal(got[1:-1, 1:-1], full[11:29, 13:39])
    # the value reaches the crop through its statistics too (what the tile driver sets), and lazily
    crop.film_fill = film.result
    assert np.array_equal(mean_variance_policy(crop), got)
    # without it the crop's own fallback differs
    assert not np.allclose(mean_variance_policy(st.crop(10, 30, 12, 40))[1:-1, 1:-1], full[11:29, 13:39])
    # untiled, the value is the statistics' own: the default is unchanged
    assert np.array_equal(mean_variance_policy(st, film=film.result()), full)


GEM = {"final_scales": 4, "risk_guard": 2.0}   # halo 33: a tile of 24 in a 96-wide film sees part of it


@pytest.mark.parametrize("method, options", [("gem", GEM), ("box", {}), ("ci", {})])
def test_statistics_methods_tiled_equal_untiled_with_one_sample_pixels(tmp_path, method, options):
    """1 spp but for a 4-spp corner (gem: the tiles away from it fill every pixel from the film's average)."""
    m = mcrecon.get_method(method, **options)
    w, h, tile = 96, 64, 24
    assert m.halo(w, h) * 2 + tile < w
    pos, val, _ = _samples(w, h, 1, 4, seed=1)
    src = SampleSet(pos, val, width=w, height=h)
    full = mcrecon.reconstruct(src, method=m)
    assert np.array_equal(mcrecon.reconstruct(src, method=m, tile=tile), full)     # read band by band
    log = write_log(tmp_path / "mixed.h5", pos, val, width=w, height=h)
    assert np.array_equal(mcrecon.reconstruct(str(log), method=m, tile=tile), full)   # a log, band by band
    st = PixelStats(w, h)   # statistics in memory (gem: without the samples' order, so without prefix halves)
    st.add(pos, val)
    assert np.array_equal(mcrecon.reconstruct(st, method=m, tile=tile), mcrecon.reconstruct(st, method=m))


def test_gem_tiles_need_the_films_values(monkeypatch):
    """The films above need the film's values: tiles left to their own fallback change gem's image."""
    m = mcrecon.get_method("gem", **GEM)
    src = _sample_set(96, 64, 1, 4, seed=1)
    full = mcrecon.reconstruct(src, method=m)
    monkeypatch.setattr(T.FilmFill, "mark", lambda self, sub: sub)
    assert not np.array_equal(mcrecon.reconstruct(src, method=m, tile=24), full)


def test_tiles_refuse_pixels_without_a_sample(tmp_path):
    pos, val, feats = _samples(12, 10, 1, 2, features=True)
    keep = ~((pos[:, 0] >= 5) & (pos[:, 0] < 6) & (pos[:, 1] >= 7) & (pos[:, 1] < 8))   # pixel (5, 7) empty
    path = write_log(tmp_path / "hole.h5", pos[keep], val[keep], width=12, height=10,
                     features={k: v[keep] for k, v in feats.items()})
    with pytest.raises(InputError, match="1 pixel.* without a sample: .*nearest sampled pixel"):
        mcrecon.reconstruct(path, method="box", tile=4)
    # a one-sample pixel with a half-buffer method: its other half is empty
    with pytest.raises(InputError, match="without a sample in one of its halves"):
        mcrecon.reconstruct(path, method="nfor", tile=4)


@pytest.fixture(scope="module")
def halves_log(tmp_path_factory):
    """2 spp (one sample in each half) but for a 4-spp corner, with features: the only pixels of a half with two
    samples are in the corner, so a half's variance away from it is the film's average."""
    pos, val, feats = _samples(64, 48, 2, 4, features=True)
    return str(write_log(tmp_path_factory.mktemp("tiles_fill") / "mixed.h5", pos, val, width=64, height=48,
                         features=feats))


def test_auto_tiled_equals_untiled_with_one_sample_halves(halves_log):
    """A log read band by band (3047 of the 3072 pixels moved, by up to 7 %, when each tile and band took its own
    average: the halves' variance and their features', pass 0's prefilter included; a SampleSet is read by the
    same FilmReader)."""
    full = mcrecon.reconstruct(halves_log, method="auto")
    assert np.array_equal(mcrecon.reconstruct(halves_log, method="auto", tile=32), full)
