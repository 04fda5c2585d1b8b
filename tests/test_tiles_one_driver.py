"""One tile driver: `reconstruct --tile` and `mcrecon.distributed.reconstruct_tiled` cut the same tiles, refuse
with the same messages and, without a cluster, run the same code (half buffers included)."""

from __future__ import annotations

import numpy as np
import pytest

import mcrecon
from mcrecon.core.stats import PixelStats
from mcrecon.distributed import tiles as D
from mcrecon.errors import InputError
from mcrecon.offline import tiles as T
from mcrecon.renderers.scenes import get_scene, write_scene_log

from test_tiles_offline import HalvesBlur


@pytest.fixture(scope="module")
def feature_log(tmp_path_factory):
    d = tmp_path_factory.mktemp("one_driver")
    return write_scene_log(get_scene("checker_wall"), d / "f.h5", width=40, height=30, spp=4, seed=2, features=True,
                           reference=False)


def test_distributed_tiles_are_the_offline_windows():
    assert D.tile_windows is T.tile_windows
    even = list(T.tile_windows(50, 37, 16, 5))
    assert [inner for _, inner in even][:4] == [(0, 12, 0, 12), (0, 12, 12, 25), (0, 12, 25, 37), (0, 12, 37, 50)]
    # dask.array's chunks (map_tiles): tiles start at multiples of the tile side, the last one the remainder
    dask = [inner for _, inner in T.tile_windows(50, 37, 16, 5, even=False)]
    assert dask[:4] == [(0, 16, 0, 16), (0, 16, 16, 32), (0, 16, 32, 48), (0, 16, 48, 50)]


def test_one_refusal_for_every_tiled_path(feature_log):
    st = PixelStats.from_log(mcrecon.read_log(feature_log))
    said = []
    for call in (lambda: mcrecon.reconstruct(st, method="awr", tile=8),
                 lambda: D.reconstruct_tiled(st, method="awr", tile=8),
                 lambda: D.reconstruct_tiled(feature_log, method="awr", tile=8)):
        with pytest.raises(InputError, match="depends on the whole image") as e:
            call()
        said.append(str(e.value).split(": ", 1)[1])
    assert len(set(said)) == 1
    thin = st.copy()
    thin.count[3, 4] = 0
    for call in (lambda: mcrecon.reconstruct(thin, method="box", tile=8),
                 lambda: D.reconstruct_tiled(thin, method="box", tile=8)):
        with pytest.raises(InputError, match="1 pixel\\(s\\) without a sample"):
            call()


def test_distributed_tiles_of_half_buffers_equal_untiled(feature_log):
    """Without a client the distributed driver is reconstruct --tile's: a half-buffer method with a halo
    tiles from the log, bit for bit."""
    m = HalvesBlur()
    full = mcrecon.reconstruct(feature_log, method=m)
    assert np.array_equal(D.reconstruct_tiled(feature_log, method=m, tile=9), full)
