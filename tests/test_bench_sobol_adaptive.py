"""benchmarks/bench_sobol_adaptive.py: the uniform side of the adaptive / uniform ratio is the renderer's own
uniform render (its seed, sampler and features), for the built-in scenes and the corpus's Mitsuba entries."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import bench_sobol_adaptive as B  # noqa: E402
import corpus  # noqa: E402


@pytest.mark.parametrize("sampler", ["sobol", "independent"])
def test_builtin_uniform_side_declares_the_renderers_sampler_and_features(sampler):
    make = B.scene_maker("soft_shadow", 16, 12, sampler, features=True)
    u = B._uniform(make, 4, 3)
    assert u.sampler == sampler and u.features is not None and "albedo" in u.features
    pix = np.floor(u.positions[:, 1]).astype(int) * 16 + np.floor(u.positions[:, 0]).astype(int)
    assert np.array_equal(np.bincount(pix, minlength=16 * 12), np.full(16 * 12, 4))
    assert B._uniform(make, 4, 3) is u            # kept for the next method spec at this seed
    assert not np.array_equal(B._uniform(make, 4, 4).values, u.values)
    B._uniform.cache_clear()


def test_external_seeds_avoid_the_references():
    """Mitsuba's runs seed the requests from the entry's seed (its reference: 987654); Cycles' runs save the
    scene with seeds from the entry's seed + 2 (its reference renders with seed + 1)."""
    for e in corpus.scenes("all", ["mitsuba", "cycles"]):
        seeds = [B.run_seed0(e) + s for s in range(4)]
        assert (e.seed + 1 not in seeds) if e.renderer == "cycles" else (seeds[0] == e.seed)


def test_mitsuba_entry_uniform_side_is_the_bridges_render_of_the_run_seed():
    from mcrecon.renderers.mitsuba import mitsuba_available

    ok, why = mitsuba_available()
    if not ok:
        pytest.skip(f"Mitsuba bridge unavailable: {why}")
    (e,) = corpus.scenes("all", ["mitsuba-cbox"])
    make = B.external_maker(e, 16)
    r, request_seed = make(5)
    assert (r.width, r.height, request_seed, r.sampler) == (16, 16, 5, "independent")
    u = B._uniform(make, 2, 5)
    assert u.sampler == "independent" and set(u.features) == {"albedo", "normal", "depth"}
    again = B._uniform.__wrapped__(make, 2, 5)
    assert np.array_equal(u.values, again.values)   # the run seed fixes the samples
    assert not np.array_equal(u.values, B._uniform.__wrapped__(make, 2, 6).values)
    B._uniform.cache_clear()
