"""nfor in tiles: the film's feature scales handed to every tile, its halo and band grid give the untiled image
and maps bit for bit (`reconstruct --tile`, `mcrecon.distributed.reconstruct_tiled`)."""

from __future__ import annotations

import numpy as np
import pytest

import mcrecon
from mcrecon.distributed import tiles as D
from mcrecon.io import read_exr
from mcrecon.offline import tiles as T
from mcrecon.renderers.scenes import get_scene, write_scene_log

# every stage of the pipeline (two bandwidths, the selection, the second pass, the clamp) on small windows:
# halo 29, so that tiles of these films crop them
SMALL = dict(radius=2, patch=1, feature_radius=1, feature_patch=1)


def _log(tmp_path_factory, name, width, height):
    d = tmp_path_factory.mktemp("nfor_tiles")
    return write_scene_log(get_scene("checker_wall"), d / f"{name}.h5", width=width, height=height, spp=4, seed=2,
                           features=True, reference=False)


@pytest.fixture(scope="module")
def wide_log(tmp_path_factory):
    return _log(tmp_path_factory, "wide", 136, 40)


@pytest.fixture(scope="module")
def tall_log(tmp_path_factory):
    return _log(tmp_path_factory, "tall", 24, 80)


def _with(method, **attrs):
    for k, v in attrs.items():
        object.__setattr__(method, k, v)
    return method


def test_nfor_tiled_equals_untiled_with_maps(wide_log):
    m = mcrecon.get_method("nfor", **SMALL)
    assert m.halo(136, 40) == 29
    full = mcrecon.reconstruct(wide_log, method=m, full=True)
    tiled = mcrecon.reconstruct(wide_log, method=m, tile=46, full=True)   # 3 tiles, cropped in x
    assert np.array_equal(tiled.image, full.image)
    d_full, d_tiled = full.diagnostics(), tiled.diagnostics()
    assert sorted(d_full) == sorted(d_tiled) == ["estimated_mse", "sample_density", "selection"]
    for k in d_full:
        assert np.array_equal(d_tiled[k], d_full[k]), k
    # the film's feature scales are what makes it exact: each tile's own scale its ridge otherwise
    own = mcrecon.get_method("nfor", **SMALL)
    _with(own, for_tiles=lambda inputs, each_tile=None: own)   # each tile standardises by its own means and deviations
    assert not np.array_equal(mcrecon.reconstruct(wide_log, method=own, tile=46), full.image)


def test_nfor_halo_is_tight_where_the_second_pass_reads_the_first(wide_log):
    """With one bandwidth the image reads the first pass's features through the second pass's guide: a halo
    one pixel smaller than the declared one changes the image."""
    opts = dict(radius=4, patch=2, feature_radius=0, feature_patch=0, bandwidths="0.5", safeguard=None)
    m = mcrecon.get_method("nfor", **opts)
    h = m.halo(136, 40)
    assert h == 20
    full = mcrecon.reconstruct(wide_log, method=m, diagnostics=False)
    assert np.array_equal(mcrecon.reconstruct(wide_log, method=m, tile=80), full)
    small = _with(mcrecon.get_method("nfor", **opts), halo=lambda w, hh: h - 1)
    assert not np.array_equal(mcrecon.reconstruct(wide_log, method=small, tile=80), full)


def test_nfor_tiles_start_on_the_films_bands(tall_log):
    """The kernels' running sums and collaborative sums go band by band from a tile's first row: the grown
    tiles start on the film's bands (tile_grid), and elsewhere the sums round otherwise."""
    opts = dict(radius=1, patch=0, feature_radius=0, feature_patch=0, bandwidths="0.5", second_pass=False)
    m = mcrecon.get_method("nfor", **opts)
    assert m.halo(24, 80) == 11 and m.tile_grid() == (16, 1)
    assert [o[0] for o, _ in T.tile_windows(24, 80, 24, 11, grid=m.tile_grid())] == [0, 0, 16, 48]
    full = mcrecon.reconstruct(tall_log, method=m, full=True)
    tiled = mcrecon.reconstruct(tall_log, method=m, tile=24, full=True)   # 4 tiles of 20 rows
    assert np.array_equal(tiled.image, full.image)
    assert np.array_equal(tiled.diagnostics()["estimated_mse"], full.diagnostics()["estimated_mse"])
    anywhere = _with(mcrecon.get_method("nfor", **opts), tile_grid=lambda: (1, 1))
    assert not np.array_equal(mcrecon.reconstruct(tall_log, method=anywhere, tile=24), full.image)
    # a stride's grid of windows is anchored too: rows lcm(16, 3), columns 3
    assert mcrecon.get_method("nfor", stride=3).tile_grid() == (48, 3)


@pytest.fixture(scope="module")
def tiny_log(tmp_path_factory):
    return _log(tmp_path_factory, "tiny", 32, 24)


def test_nfor_default_halo_and_one_tile_driver(tall_log, tiny_log, tmp_path, cli):
    m = mcrecon.get_method("nfor")
    # 2 r + f + the selection (2 x 9 + 1 + the first pass: 2 r + the prefilter's 5 + 3): 65
    assert m.halo(1920, 1080) == 65
    small = mcrecon.get_method("nfor", **SMALL)
    full = mcrecon.reconstruct(tall_log, method=small)
    assert np.array_equal(D.reconstruct_tiled(tall_log, method=small, tile=40), full)
    out_full, out_tiled = tmp_path / "full.exr", tmp_path / "tiled.exr"
    assert cli(["reconstruct", str(tiny_log), "--method", "nfor", "-o", str(out_full)])[0] == 0
    code, _, err = cli(["reconstruct", str(tiny_log), "--method", "nfor", "--tile", "16", "-o", str(out_tiled)])
    assert code == 0, err
    assert np.array_equal(read_exr(out_tiled)[0], read_exr(out_full)[0])
