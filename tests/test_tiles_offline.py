"""`reconstruct(..., tile=N)` / `mcrecon reconstruct --tile N`: tiles with halos give the untiled image, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

import mcrecon
from mcrecon.core.stats import PixelStats
from mcrecon.errors import InputError
from mcrecon.io import read_exr, read_log, write_log
from mcrecon.methods.base import Method, Requirements
from mcrecon.offline import tiles as T
from mcrecon.renderers.scenes import get_scene, write_scene_log


@pytest.fixture(scope="module")
def scene_log(tmp_path_factory):
    d = tmp_path_factory.mktemp("tiles_offline")
    return write_scene_log(get_scene("soft_shadow"), d / "t.h5", width=104, height=88, spp=4, seed=3, reference=False)


@pytest.fixture(scope="module")
def feature_log(tmp_path_factory):
    """A log with per-sample features (albedo, normal, depth), every pixel 4 samples: 2 in each half."""
    d = tmp_path_factory.mktemp("tiles_features")
    return write_scene_log(get_scene("checker_wall"), d / "f.h5", width=72, height=56, spp=4, seed=2, features=True,
                           reference=False)


class HalvesBlur(Method):
    """A half-buffer method with a halo: each half's mean blurred over 5x5, cross-weighted by the other half's
    albedo and the merged variance (reads the halves, their merge and a feature, as NFOR does)."""

    name = "halves_blur"
    requires = Requirements(samples=True, half_buffers=True, features="required")

    def halo(self, width, height):
        return 4  # two 5x5 passes

    def reconstruct_run(self, run, inputs):
        a, b = inputs.halves
        st = inputs.stats
        g = a.features["albedo"].mean * b.features["albedo"].mean + st.mean_variance(undefined=0.0)
        # a correlation sums each pixel's window on its own (a running sum would round by its place in the row)
        blur = lambda x: ndimage.correlate(x, np.full((5, 5, 1), 1 / 25), mode="nearest")  # noqa: E731
        out = blur(blur(0.5 * (a.mean + b.mean)) * (1.0 + g))
        run.diagnostics = {"weight": g.mean(axis=2), "scalar": np.float64(1.0)}
        return out


@pytest.mark.parametrize("method, options, tile", [
    ("box", {}, 24),
    ("gem", {"final_scales": 4, "risk_guard": 2.0}, 32),   # halo 33: tiles in the middle see part of the film
])
def test_statistics_methods_tiled_equal_untiled(scene_log, method, options, tile):
    m = mcrecon.get_method(method, **options)
    st = PixelStats.from_log(read_log(scene_log))
    assert 2 * m.halo(st.width, st.height) + tile < st.width
    full = mcrecon.reconstruct(scene_log, method=m, full=True)
    tiled = mcrecon.reconstruct(scene_log, method=m, tile=tile, full=True)
    assert np.array_equal(tiled.image, full.image)
    # pixel statistics alone (no sample order, so gem's guard reads s^2 / n alone): tiled equals untiled too
    assert np.array_equal(mcrecon.reconstruct(st, method=m, tile=tile), mcrecon.reconstruct(st, method=m))
    d_full, d_tiled = full.diagnostics(), tiled.diagnostics()
    assert sorted(d_full) == sorted(d_tiled)
    for k in d_full:
        assert np.array_equal(d_tiled[k], d_full[k], equal_nan=True), k
    # a caller that reads no maps holds none of the film's size
    bare = mcrecon.reconstruct(scene_log, method=m, tile=tile, full=True, diagnostics=False)
    assert np.array_equal(bare.image, full.image) and bare.diagnostics() == {}


def test_gem_tiles_read_the_crops_of_the_films_prefix_halves(scene_log):
    """gem's guard reads the samples' prefix halves: every tiled path hands each tile the crop of the film's."""
    from mcrecon.core.strata import prefix_halves_of
    from mcrecon.distributed import tiles as D

    m = mcrecon.get_method("gem", final_scales=4, risk_guard=2.0)
    assert m.requires.prefix_halves
    full = mcrecon.reconstruct(scene_log, method=m)
    # the halves change this image: the comparisons below can fail
    off = mcrecon.get_method("gem", final_scales=4, risk_guard=2.0, guard_halves=0)
    assert not np.array_equal(full, mcrecon.reconstruct(scene_log, method=off))
    assert np.array_equal(mcrecon.reconstruct(scene_log, method=m, tile=32), full)
    assert np.array_equal(D.reconstruct_tiled(scene_log, method=m, tile=32), full)
    ph = prefix_halves_of(read_log(scene_log))
    st = PixelStats.from_log(read_log(scene_log))
    crop = ph.crop(5, 40, 11, 60)
    assert (crop.height, crop.width) == (35, 49)
    assert np.array_equal(crop.mean_variance(st.count[5:40, 11:60]), ph.mean_variance(st.count)[5:40, 11:60],
                          equal_nan=True)
    for a, b in zip(crop.halves(), ph.halves()):
        assert np.array_equal(a, b[5:40, 11:60])


def test_half_buffer_method_tiled_equal_untiled(feature_log):
    m = HalvesBlur()
    full = mcrecon.reconstruct(feature_log, method=m, full=True)
    tiled = mcrecon.reconstruct(feature_log, method=m, tile=9, full=True)   # 8 x 7 tiles of 9 x 8 pixels
    assert np.array_equal(tiled.image, full.image)
    assert np.array_equal(tiled.diagnostics()["weight"], full.diagnostics()["weight"])
    # what the caller gets beside the image: the samples, read band by band, not the film's statistics (the
    # sanity line streams them once more)
    assert tiled.inputs.stats is None and tiled.inputs.samples is not None
    assert tiled.sanity() == full.sanity()
    # with too small a halo the tiles' edges show: the comparison above can fail
    small = HalvesBlur()
    object.__setattr__(small, "halo", lambda w, h: 3)
    assert not np.array_equal(mcrecon.reconstruct(feature_log, method=small, tile=9), full.image)


def test_tiles_of_halves_hold_no_merged_film(feature_log, monkeypatch):
    """The merge with features is made per tile: no merge of the whole film's halves."""
    sizes = []
    real = PixelStats.merged

    def spy(self, other):
        sizes.append((self.height, self.width, bool(self.features)))
        return real(self, other)

    monkeypatch.setattr(PixelStats, "merged", spy)
    mcrecon.reconstruct(feature_log, method=HalvesBlur(), tile=16)
    assert (56, 72, True) not in sizes and any(f for _, _, f in sizes)


def test_tile_windows_cover_the_film_once():
    cover = np.zeros((37, 50), int)
    for (oy0, oy1, ox0, ox1), (y0, y1, x0, x1) in T.tile_windows(50, 37, 16, 5):
        cover[y0:y1, x0:x1] += 1
        assert y1 - y0 <= 16 and x1 - x0 <= 16
        assert (oy0, ox0) == (max(0, y0 - 5), max(0, x0 - 5)) and (oy1, ox1) == (min(37, y1 + 5), min(50, x1 + 5))
    assert (cover == 1).all()


def test_tile_refusals(scene_log, feature_log, tmp_path):
    for bad in (0, -3, 2.5, "512", True):
        with pytest.raises(InputError, match="tile"):
            mcrecon.reconstruct(scene_log, method="box", tile=bad)
    with pytest.raises(InputError, match="whole image"):
        mcrecon.reconstruct(scene_log, method="awr", tile=32)
    with pytest.raises(InputError, match="individual samples"):
        mcrecon.reconstruct(scene_log, method="splat", tile=32)
    # a pixel without a sample takes the nearest sampled pixel's value, however far, so no halo makes it local
    rng = np.random.default_rng(1)
    pos = rng.random((2 * 12 * 10, 2)) * [12, 10]   # 2 samples a pixel on average: some pixels hold none
    path = write_log(tmp_path / "thin.h5", pos, rng.random((pos.shape[0], 3)), width=12, height=10)
    with pytest.raises(InputError, match="without a sample"):
        mcrecon.reconstruct(path, method="box", tile=4)


def test_cli_tile_flag(scene_log, tmp_path, cli):
    out_full, out_tiled = tmp_path / "full.exr", tmp_path / "tiled.exr"
    assert cli(["reconstruct", str(scene_log), "--method", "box", "-o", str(out_full)])[0] == 0
    code, out, err = cli(["reconstruct", str(scene_log), "--method", "box", "--tile", "24", "-o", str(out_tiled)])
    assert code == 0, err
    assert np.array_equal(read_exr(out_tiled)[0], read_exr(out_full)[0])
    code, out, err = cli(["reconstruct", str(scene_log), "--method", "awr", "--tile", "24", "-o",
                          str(tmp_path / "awr.exr")])
    assert code == 2 and "tile" in err and not (tmp_path / "awr.exr").exists()
