"""The scene renderer's rate throttle (benchmarks): the same samples, at most ``rate`` samples per second."""

from __future__ import annotations

import numpy as np
import pytest

from mcrecon.errors import InputError
from mcrecon.renderers import scenes
from mcrecon.renderers.scenes import ENV_SCENE_RATE, SceneRenderer, render_uniform


def test_throttled_renderer_sleeps_the_rest_of_n_over_rate_and_gives_the_same_samples(monkeypatch):
    slept = []
    monkeypatch.setattr(scenes.time, "sleep", slept.append)
    monkeypatch.delenv(ENV_SCENE_RATE, raising=False)
    plain = render_uniform("flat", width=8, height=6, spp=4, seed=1)
    assert slept == []                                  # no rate: no sleep
    monkeypatch.setenv(ENV_SCENE_RATE, "100")           # 192 samples at 100/s: 1.92 s in all
    slow = render_uniform("flat", width=8, height=6, spp=4, seed=1)
    assert len(slept) == 1 and 0 < slept[0] <= 192 / 100
    assert np.array_equal(plain.positions, slow.positions) and np.array_equal(plain.values, slow.values)
    assert SceneRenderer("flat", rate=5e5).rate == 5e5  # the argument wins over the environment


@pytest.mark.parametrize("rate", [0, -1.0, float("nan"), float("inf"), "fast", True])
def test_bad_rate_is_one_input_error(rate, monkeypatch):
    monkeypatch.delenv(ENV_SCENE_RATE, raising=False)
    with pytest.raises(InputError, match="rate"):
        SceneRenderer("flat", rate=rate)
    monkeypatch.setenv(ENV_SCENE_RATE, str(rate))
    if rate is not True:
        with pytest.raises(InputError, match=ENV_SCENE_RATE):
            SceneRenderer("flat")
