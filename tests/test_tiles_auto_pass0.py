"""auto in tiles, pass 0 from a log (mcrecon/methods/auto/tiled.py, ``_pass0_read``): OIDN's candidates from the
film's planes read band by band are the whole film's bit for bit, and no read asks for more than a band."""

from __future__ import annotations

import numpy as np
import pytest

import mcrecon.methods.auto.tiled as tiled
from mcrecon.methods import get_method
from mcrecon.offline.inputs import gather_inputs
from mcrecon.offline.tiles import FilmReader, film_inputs
from mcrecon.renderers.scenes import get_scene, write_scene_log

pytest.importorskip("pyoidn", reason="needs pyoidn (Intel OIDN), a dependency of mcrecon: pip install -e .")
pytestmark = pytest.mark.filterwarnings("ignore")

BANDS = [(0, 32), (32, 64), (64, 80), (80, 101)]


def _pass0(method, source, reader: bool):
    """The film of pass 0 from a reader of ``source`` band by band (recording the windows it reads), or from
    the film's inputs in memory (the untiled run's candidates): ``(film, windows)``."""
    windows = []
    if reader:
        inputs = film_inputs(source, method)
        assert isinstance(inputs, FilmReader)
        inputs.bands = BANDS
        read = inputs.read

        def recorded(window, method=None):
            windows.append(tuple(window))
            return read(window, method=method)

        inputs.read = recorded
    else:
        inputs = gather_inputs(source, method, merged=False)
    h, w = inputs.shape[:2]
    film = tiled.Film(tiled.FilmPlanes(h, w))
    (tiled._pass0_read if reader else tiled._pass0)(method, inputs, film)
    return film, windows


@pytest.mark.parametrize("scene, features, sampler", [("checker_spot", True, "independent"),
                                                      ("caustic", False, "sobol")])
def test_pass0_oidn_from_band_planes_is_the_films_bit_for_bit(tmp_path, scene, features, sampler):
    sc = get_scene(scene)
    log = write_scene_log(sc, tmp_path / "l.h5", width=73, height=101, spp=8, seed=3, features=features,
                          reference=False, sampler=sampler)
    method = get_method("auto", scales=4)
    banded, windows = _pass0(method, log, True)
    whole, _ = _pass0(method, log, False)
    # OIDN on all the samples and on each half, with the aux where there are features; the crossed votes
    names = [b[0] for b in whole.black]
    assert names == (["oidn_halves", "oidn_aux", "oidn_aux_halves"] if features else ["oidn", "oidn_halves"])
    assert banded.black == whole.black and all(b[2] is not None for b in whole.black)
    for k in range(len(whole.black)):
        for plane in (f"oidn_image{k}", f"oidn_mse{k}"):
            a, b = banded.planes.get(plane), whole.planes.get(plane)
            assert a.dtype == b.dtype and np.array_equal(a, b, equal_nan=True), plane
    # every read is a band grown by the prefilter's reach (from a 16-row kernel band): none the film's
    tallest = max(y1 - y0 for y0, y1 in BANDS) + 2 * tiled.PREFILTER_REACH + 15
    assert len(windows) == len(BANDS)
    assert all(y1 - y0 <= tallest and (x0, x1) == (0, 73) for y0, y1, x0, x1 in windows)
    assert max(y1 - y0 for y0, y1, _, _ in windows) < 101
