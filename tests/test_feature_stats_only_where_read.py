"""The driver's statistics keep the per-sample features only for a method that reads statistics.

``splat`` (``requires.statistics`` False) reads the features of each round in
``observe``: the run's statistics keep no feature sums for it (nothing reads
them), while its rounds still come with the checked features, so its image
is the one it makes with the statistics keeping them.  A method that reads
statistics (``box`` with features kept) still finds them there.
"""

import dataclasses

import numpy as np

from mcrecon import get_method
from mcrecon.adaptive import rounds
from mcrecon.adaptive.run import adapt, resume
from mcrecon.core.requests import SampleBatch

from helpers import jittered_renderer

W, H = 12, 8


def _renderer():
    def shade(pos, rng, req):  # the values, an albedo (one half brighter) and a depth with every sample
        val = np.repeat(0.3 + 0.5 * (pos[:, :1] > W / 2), 3, axis=1) * rng.uniform(0.5, 1.5, (len(pos), 1))
        alb = np.where(pos[:, :1] > W / 2, 0.8, 0.2) * np.ones((1, 3))
        return SampleBatch(pos, val, {"albedo": alb, "depth": 1.0 + pos[:, 1] / H})

    return jittered_renderer(shade, width=W, height=H, name="feature stats test renderer")


def _observed(monkeypatch):
    seen = []
    orig = rounds._observe

    def spy(ctx, batch, *a, **k):
        seen.append(sorted(batch.features or {}))
        return orig(ctx, batch, *a, **k)

    monkeypatch.setattr(rounds, "_observe", spy)
    return seen


def test_splat_rounds_carry_features_the_statistics_do_not_keep(monkeypatch, tmp_path):
    seen = _observed(monkeypatch)
    log = tmp_path / "s.h5"
    res = adapt(_renderer(), get_method("splat", initial_spp=1), spp=4, seed=2, log=str(log), progress=False,
                max_rounds=2)
    assert seen and all(f == ["albedo", "depth"] for f in seen)
    assert not res.stats.features
    seen.clear()
    done = resume(str(log), _renderer(), progress=False)  # the replay checks them against the same layout
    assert seen[:2] == [["albedo", "depth"]] * 2 and not done.stats.features
    ref = adapt(_renderer(), get_method("splat", initial_spp=1), spp=4, seed=2, progress=False)
    assert np.array_equal(done.image, ref.image)


def test_a_statistics_method_still_finds_the_features():
    class FeatureBox(type(get_method("box"))):  # reads statistics, with the features
        requires = dataclasses.replace(get_method("box").requires, features="optional")

    res = adapt(_renderer(), FeatureBox(), spp=2, seed=2, progress=False, pipeline=False)
    assert sorted(res.stats.features) == ["albedo", "depth"]
