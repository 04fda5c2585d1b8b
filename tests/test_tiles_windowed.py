"""Statistics of a window of the film read from the whole sample stream (`gather_inputs(window=...)`): the film's
statistics cropped to the window bit for bit, whatever the sample order; the tiled driver reads a log band by band,
so no statistics of the whole film are held."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import mcrecon
from mcrecon.core.halves import Halves, split_halves
from mcrecon.core.samples import SampleSet
from mcrecon.core.stats import PixelStats
from mcrecon.core.strata import PrefixHalves
from mcrecon.errors import InputError
from mcrecon.io import read_log, write_log
from mcrecon.methods.base import Method, Requirements
from mcrecon.offline import tiles as T
from mcrecon.offline.inputs import gather_inputs
from mcrecon.renderers.scenes import get_scene, write_scene_log

W, H = 23, 17
WINDOWS = [(0, H, 0, W), (3, 11, 5, 19), (0, 1, 0, 1), (16, 17, 22, 23), (4, 9, 0, W)]


def _stream(seed=0, n=3000, order="shuffled", bad=True):
    """Samples of a W x H film with albedo and depth, in an order that breaks a pixel's runs (shuffled) or in
    pixel runs (a renderer's), with NaN and Inf values in a few samples."""
    rng = np.random.default_rng(seed)
    pix = rng.integers(0, W * H, n)
    if order == "runs":
        pix = np.sort(pix)
    pos = np.stack([pix % W + rng.random(n), pix // W + rng.random(n)], axis=1)
    val = rng.gamma(2.0, 1.0, (n, 3)) * (1 + pix[:, None] % 5)
    if bad:
        val[rng.integers(0, n, 9), rng.integers(0, 3, 9)] = np.nan
        val[rng.integers(0, n, 3), 0] = np.inf
    feats = {"albedo": rng.random((n, 3)), "depth": rng.random(n)}
    return pos, val, feats


def _batches(pos, val, feats, parts=4):
    cut = np.linspace(0, pos.shape[0], parts + 1).astype(int)
    return [(pos[a:b], val[a:b], {k: f[a:b] for k, f in feats.items()}) for a, b in zip(cut[:-1], cut[1:])]


def _same(a: PixelStats, b: PixelStats):
    assert (a.width, a.height) == (b.width, b.height)
    for name in ("count", "mean", "m2", "min", "max", "sub_sum", "sub_count"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            assert np.array_equal(x, y), name   # bit for bit (array_equal on float64: no tolerance)
    assert sorted(a.features) == sorted(b.features)
    for name in a.features:
        _same(a.features[name], b.features[name])


@pytest.mark.parametrize("order", ["shuffled", "runs"])
@pytest.mark.parametrize("nonfinite", ["drop", "zero"])
def test_window_statistics_are_the_films_crop(order, nonfinite):
    pos, val, feats = _stream(order=order)
    layout = {"albedo": 3, "depth": 1}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        film = PixelStats.from_batches(_batches(pos, val, feats), width=W, height=H, subpixels=4,
                                       nonfinite=nonfinite, features=layout)
        for win in WINDOWS:
            part = PixelStats.from_batches(_batches(pos, val, feats), width=W, height=H, subpixels=4,
                                           nonfinite=nonfinite, features=layout, window=win)
            _same(part.crop(0, part.height), film.crop(*win))
            assert part.count.shape == (win[1] - win[0], win[3] - win[2])
    # the runs are the film's: a window's own stream (other pixels' samples removed) joins a pixel's runs, and
    # the statistics of the shuffled stream then round otherwise -- the comparison above can fail
    if order == "shuffled" and nonfinite == "drop":
        y0, y1, x0, x1 = WINDOWS[1]
        keep = ((pos[:, 1] >= y0) & (pos[:, 1] < y1) & (pos[:, 0] >= x0) & (pos[:, 0] < x1)
                & np.isfinite(val).all(axis=1))
        own = PixelStats.from_samples(pos[keep] - [x0, y0], val[keep], width=x1 - x0, height=y1 - y0)
        assert np.array_equal(own.count, film.count[y0:y1, x0:x1])
        assert not np.array_equal(own.m2, film.m2[y0:y1, x0:x1])


@pytest.mark.parametrize("sampler", ["independent", "sobol"])
def test_window_halves_are_the_films_crop(sampler):
    pos, val, feats = _stream(seed=1)
    src = SampleSet(pos, val, width=W, height=H, features=feats, sampler=sampler,
                    rounds=np.repeat(np.arange(3), [1000, 1000, 1000]))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        film = split_halves(src, features="all")
        for win in WINDOWS:
            part = split_halves(src, features="all", window=win)
            for half in (0, 1):
                _same(part[half].crop(0, part[half].height), film[half].crop(*win))
        # batches added one by one, the NaN batches through the reference path
        win = WINDOWS[1]
        h = Halves.empty(W, H, ("R", "G", "B"), features={"albedo": 3, "depth": 1}, window=win)
        h.totals, h.sampler = film.totals, film.sampler
        for p, v, f in _batches(pos, val, feats, parts=5):
            h.add(p, v, features=f)
    for half in (0, 1):
        _same(h[half].crop(0, h[half].height), film[half].crop(*win))


def test_window_prefix_halves_are_the_films_crop():
    pos, val, _ = _stream(seed=2, bad=False)
    film = PrefixHalves(W, H, 3)
    part = PrefixHalves(W, H, 3, window=WINDOWS[1])
    for p, v, _ in _batches(pos, val, {}):
        film.add(p, v)
        part.add(p, v)
    crop = film.crop(*WINDOWS[1])
    for a, b in zip(part.halves(), crop.halves()):
        assert np.array_equal(a, b)


def test_window_of_a_log_and_refusals(tmp_path):
    pos, val, feats = _stream(seed=3, bad=False, order="runs")   # a renderer's order: chunks of a few rows
    log = read_log(write_log(tmp_path / "w.h5", pos, val, width=W, height=H, features=feats,
                             reference=np.ones((H, W, 3))))
    m = mcrecon.get_method("nfor")
    film = gather_inputs(log, m, merged=False)
    win = WINDOWS[1]
    part = gather_inputs(log, m, merged=False, window=win)
    for half in (0, 1):
        _same(part.halves[half], film.halves[half].crop(*win))
    assert part.shape == (win[1] - win[0], win[3] - win[2], 3)
    box = gather_inputs(log, mcrecon.get_method("box"), window=win)
    _same(box.stats.crop(0, box.stats.height), PixelStats.from_log(log).crop(*win))
    # read in chunks of 700 rows: the features of chunks without a sample in the window are not read
    from mcrecon.io.reader import SampleLog
    real, read_feats = SampleLog.iter_chunks, []

    def small_chunks(self, **k):
        for ch in real(self, **{**k, "chunk_size": 700}):
            read_feats.append(ch.values is not None)
            assert (ch.features is None) == (ch.values is None) or not k.get("features")
            yield ch

    SampleLog.iter_chunks = small_chunks
    try:
        chunked = gather_inputs(log, m, merged=False, window=win)
        film_chunked = gather_inputs(log, m, merged=False)
        box_chunked = gather_inputs(log, mcrecon.get_method("gem"), window=(0, 2, 0, W))
        gem_film = gather_inputs(log, mcrecon.get_method("gem"))
        # a NaN in a chunk beyond the window is refused by the band that reads it, under 'raise'
        bad_val = val.copy()
        bad_val[-1, 0] = np.nan
        bad = read_log(write_log(tmp_path / "bad.h5", pos, bad_val, width=W, height=H))
        gather_inputs(bad, mcrecon.get_method("box"), nonfinite="raise", window=(0, 2, 0, W))
        with pytest.raises(InputError, match="NaN|non-finite|Inf"):
            gather_inputs(bad, mcrecon.get_method("box"), nonfinite="raise", window=(H - 2, H, 0, W))
    finally:
        SampleLog.iter_chunks = real
    assert not all(read_feats)   # chunks of 700 samples in pixel order: most miss the window, read no values
    for half in (0, 1):
        _same(chunked.halves[half], film_chunked.halves[half].crop(*win))
    _same(box_chunked.stats.crop(0, 2), gem_film.stats.crop(0, 2))
    assert np.array_equal(box_chunked.strata.halves()[0], gem_film.strata.crop(0, 2, 0, W).halves()[0])
    with pytest.raises(InputError, match="window"):
        gather_inputs(PixelStats.from_log(log), mcrecon.get_method("box"), window=win)
    with pytest.raises(InputError, match="window"):
        PixelStats.window_of(W, H, (0, H + 1, 0, W))


@pytest.fixture(scope="module")
def film_log(tmp_path_factory):
    d = tmp_path_factory.mktemp("tiles_windowed")
    return write_scene_log(get_scene("checker_wall"), d / "f.h5", width=96, height=64, spp=4, seed=5, features=True,
                           reference=False)


@pytest.mark.parametrize("method, options", [
    ("box", {}),
    ("gem", {"final_scales": 2, "risk_guard": 0}),   # halo 15
    ("nfor", {"radius": 1, "patch": 0, "feature_radius": 0, "feature_patch": 0, "bandwidths": "0.5",
              "second_pass": False}),   # halo 11, bands of 16 rows
])
def test_tiles_read_bands_not_the_film(film_log, method, options, monkeypatch):
    """96 x 64 in tiles of 32: the image is the untiled one bit for bit, and the statistics are read a band of
    tiles (its rows grown by the halo) at a time: no statistics of the whole film are built."""
    m = mcrecon.get_method(method, **options)
    assert m.halo(96, 64) <= 15
    full = mcrecon.reconstruct(film_log, method=m, full=True)
    built, reads = [], []
    real_init, real_read = PixelStats.__init__, T.FilmReader.read

    def init(self, width, height, *a, **k):
        built.append((int(height), int(width)))
        real_init(self, width, height, *a, **k)

    def read(self, window):
        reads.append(tuple(window))
        return real_read(self, window)

    monkeypatch.setattr(PixelStats, "__init__", init)
    monkeypatch.setattr(T.FilmReader, "read", read)
    tiled = mcrecon.reconstruct(film_log, method=m, tile=32, full=True)
    assert np.array_equal(tiled.image, full.image)
    # the sanity line, added band by band from the bands' statistics, is the film's
    assert tiled.sanity() == full.sanity()
    halo = m.halo(96, 64)
    grid = m.tile_grid()[0]
    tile_reads = reads[-2:]   # the two bands of tiles (nfor first reads the film's feature planes band by band)
    for y0, y1, x0, x1 in tile_reads:
        assert (x0, x1) == (0, 96) and y1 - y0 <= 32 + 2 * max(halo, 1) + grid - 1
    assert len(reads) == (4 if method == "nfor" else 2)
    assert (64, 96) not in built   # no statistics of the whole film, neither colour nor features (nor sanity's)
    if method == "nfor":
        assert reads[:2] == [(0, 32, 0, 96), (32, 64, 0, 96)]   # the feature planes: the bands without halos


def test_streamed_tiles_refuse_thin_bands_and_whole_image_methods(tmp_path, film_log):
    rng = np.random.default_rng(4)
    n = 4 * 40 * 30
    pos = rng.random((n, 2)) * [40, 30]
    pos[pos[:, 1] >= 20, 1] = 3.5   # rows 20..29 sampled nowhere: every pixel there is empty
    path = write_log(tmp_path / "thin.h5", pos, rng.random((n, 3)), width=40, height=30)
    with pytest.raises(InputError, match="in a band of tiles without a sample"):
        mcrecon.reconstruct(path, method="box", tile=10)
    for name, opts in (("auto", {"regression_proxy": 0.1}), ("awr", {})):   # auto tiles without the proxy
        with pytest.raises(InputError, match="whole image"):
            mcrecon.reconstruct(film_log, method=name, tile=32, **opts)


class Sharpen(Method):
    """Pixel means sharpened over 3 x 3 (halo 1): leaves the samples' range, below 0 too (the sanity line)."""

    name = "sharpen"
    requires = Requirements()

    def halo(self, width, height):
        return 1

    def reconstruct_run(self, run, inputs):
        from scipy import ndimage
        mean = inputs.stats.mean
        return 2.0 * mean - ndimage.correlate(mean, np.full((3, 3, 1), 1 / 9), mode="nearest")


def test_sanity_line_added_band_by_band(tmp_path):
    rng = np.random.default_rng(0)
    pix = np.sort(np.concatenate([np.repeat(np.arange(48 * 40), 3), rng.integers(0, 48 * 40, 4000)]))
    pos = np.stack([pix % 48 + rng.random(pix.size), pix // 48 + rng.random(pix.size)], axis=1)
    val = rng.gamma(0.5, 1.0, (pix.size, 3)) * (1 + 3 * (pix[:, None] // 48 > 20))
    path = write_log(tmp_path / "noise.h5", pos, val, width=48, height=40)
    full = mcrecon.reconstruct(path, method=Sharpen(), full=True)
    s = full.sanity()
    assert s["overshoot_pixels"] > 0 and s["negative_pixels"] > 0 and s["max_overshoot"] > 0
    for tile in (7, 16, 40):
        tiled = mcrecon.reconstruct(path, method=Sharpen(), tile=tile, full=True)
        assert np.array_equal(tiled.image, full.image)
        assert tiled.sanity() == s
