"""auto in tiles (``reconstruct --tile N``): the untiled image bit for bit (mcrecon/methods/auto/tiled.py)."""

from __future__ import annotations

import numpy as np
import pytest

import mcrecon
import mcrecon.methods.auto.tiled as tiled_mod
from mcrecon.errors import InputError
from mcrecon.io import read_exr
from mcrecon.methods import get_method
from mcrecon.renderers.scenes import get_scene, write_scene_log

pytestmark = pytest.mark.filterwarnings("ignore")


_UNTILED: dict = {}


def _untiled(log, **opts):
    """The untiled image, computed once per film and options for the tests of this module."""
    key = (str(log), tuple(sorted(opts.items())))
    if key not in _UNTILED:
        _UNTILED[key] = mcrecon.reconstruct(log, method="auto", **opts)
    return _UNTILED[key]


def _log(tmp_path_factory, scene, w, h, features, spp=8, seed=4):
    d = tmp_path_factory.mktemp(f"tiles_auto_{scene}")
    return write_scene_log(get_scene(scene), d / "l.h5", width=w, height=h, spp=spp, seed=seed, features=features,
                           reference=False)


# The films are as small as keeps what the tests check: tiles of 40-50 px grown by the candidates' reach (25 px at
# 4 scales) still end inside the film at an interior seam and are clipped at its edges, the feature film's default
# is a blend of feature candidates, and checker_spot's vote is thin (136x104 films cost twice the CPU seconds).
@pytest.fixture(scope="module")
def wall_features(tmp_path_factory):
    return _log(tmp_path_factory, "checker_wall", 88, 72, True)


@pytest.fixture(scope="module")
def spot_features(tmp_path_factory):
    """A small light on a texture: rare huge samples, the global prior's thin vote."""
    return _log(tmp_path_factory, "checker_spot", 88, 72, True)


@pytest.fixture(scope="module")
def caustic(tmp_path_factory):
    """Rare huge samples without features (the firefly rule, the black box where they are), odd size."""
    return _log(tmp_path_factory, "caustic", 89, 71, False)


def _within_rounding(tiled, full):
    """The tiled image within 1e-6 relative of the untiled one (and at most a few pixels apart from it at all).

    Where the selection reads a running sum (the black box default's wide interval, scipy's uniform_filter of
    the 5 x 5 per-sample variance; the bias test's 3 x 3 mean of the variance), a tile sums from its own first
    row and column, the film from its: the last bits of those sums differ, and the clamp's interval with
    them (docs/performance.md, "auto in tiles")."""
    assert np.all(np.isfinite(tiled)) and tiled.shape == full.shape
    rel = np.abs(tiled - full) / np.maximum(np.abs(full), 1e-12)
    assert rel.max() <= 1e-6
    assert np.count_nonzero((tiled != full).any(axis=2)) <= 0.01 * full.shape[0] * full.shape[1]


def _films(monkeypatch):
    """The film passes the tiled runs make (to check what they decided)."""
    got = []
    orig = tiled_mod.film_pass

    def spy(*a, **k):
        got.append(orig(*a, **k))
        return got[-1]

    monkeypatch.setattr(tiled_mod, "film_pass", spy)
    return got


def test_auto_tiled_equals_untiled_with_features(wall_features, monkeypatch):
    films = _films(monkeypatch)
    full = _untiled(wall_features, scales=4)
    tiled = mcrecon.reconstruct(wall_features, method="auto", scales=4, tile=40)
    assert np.array_equal(tiled, full)
    film = films[-1]
    # the feature candidates ran in the tiles, and the default is a blend decided on the film's sums
    assert "nfor" in film.names and "dnlm" in film.names and "oidn_aux" in film.names
    assert film.default.g is not None and film.default.blend is not None
    assert film.scales[0] is not None and film.units[0] is not None


def test_auto_tiled_equals_untiled_thin_vote(spot_features, monkeypatch):
    films = _films(monkeypatch)
    full = _untiled(spot_features, scales=4)
    _within_rounding(mcrecon.reconstruct(spot_features, method="auto", scales=4, tile=48), full)
    film = films[-1]   # the film's vote is thin: its default an OIDN candidate by the crossed vote
    assert film.default.thin and film.names[film.default.g].startswith("oidn")


def test_auto_tiled_equals_untiled_colour_only_odd_size(caustic):
    full = _untiled(caustic, scales=4)
    tiled = mcrecon.reconstruct(caustic, method="auto", scales=4, tile=33)
    _within_rounding(tiled, full)
    # the distributed driver without a client is reconstruct --tile's loop
    from mcrecon.distributed import reconstruct_tiled
    assert np.array_equal(reconstruct_tiled(caustic, method="auto", tile=33, scales=4), tiled)
    # without features, and without the global prior: the plain per-pixel choice
    full = mcrecon.reconstruct(caustic, method="auto", scales=4, global_prior=None, feature_candidates="none")
    assert np.array_equal(mcrecon.reconstruct(caustic, method="auto", scales=4, global_prior=None,
                                              feature_candidates="none", tile=50), full)


def test_auto_tiles_need_the_film_pass(wall_features, monkeypatch):
    """The candidates' reach matters: tiles whose candidates see too little context change the image (the
    equalities above can fail)."""
    from mcrecon.methods.auto.method import AutoMethod

    full = _untiled(wall_features, scales=4)
    monkeypatch.setattr(AutoMethod, "candidate_reach", lambda self: 4)
    assert not np.array_equal(mcrecon.reconstruct(wall_features, method="auto", scales=4, tile=40), full)


def test_auto_tile_refusals(caustic):
    for opts in ({"candidates": "box,gauss,awr"}, {"regression_proxy": 0.1}):
        with pytest.raises(InputError, match="whole image"):
            mcrecon.reconstruct(caustic, method="auto", tile=40, **opts)
    with pytest.raises(InputError, match="tile"):
        get_method("auto").for_tiles(None)


def test_cli_auto_tile(caustic, tmp_path, cli):
    """The CLI's tiled image (a float32 EXR) is the untiled one of the same options, as stored."""
    tiled = tmp_path / "tiled.exr"
    code, out, err = cli(["reconstruct", str(caustic), "--method", "auto", "--scales", "4", "--tile", "40", "-o",
                          str(tiled)])
    assert code == 0, err
    full = _untiled(caustic, scales=4).astype(np.float32).astype(np.float64)
    _within_rounding(read_exr(tiled)[0].astype(np.float64), full)
