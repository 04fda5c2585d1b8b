"""A stratified run's final image reads the prefix-block halves of its log, as the offline
reconstruction of that log does: the run's image is its log's, whatever the sampler."""

from __future__ import annotations

import numpy as np
import pytest

import mcrecon
from mcrecon.io import read_log
from mcrecon.methods import get_method
from mcrecon.renderers.scenes import SceneRenderer, get_scene


@pytest.mark.parametrize("sampler", ["sobol", "independent"])
def test_an_adaptive_runs_image_is_the_offline_reconstruction_of_its_log(tmp_path, sampler):
    log = tmp_path / "run.h5"
    renderer = SceneRenderer(get_scene("soft_shadow"), width=24, height=24, seed=3, sampler=sampler)
    run = mcrecon.adapt(renderer, get_method("auto"), spp=16, seed=2, progress=False, track_error=False, log=log)
    assert read_log(log).sampler == sampler
    offline = mcrecon.reconstruct(log, method="auto")
    assert np.array_equal(np.asarray(run.image), np.asarray(offline))
    if sampler == "sobol":
        # the run's halves are the log's prefix blocks (each pixel's first ceil(n / 2) samples in half a)
        halves = run.run.halves
        assert halves.sampler == "sobol"
        assert np.array_equal(halves.a.count, (run.stats.count + 1) // 2)


def test_a_stratified_run_without_a_log_keeps_a_private_one_and_removes_it(tmp_path, monkeypatch):
    """Without ``log`` a Sobol run of a half-buffer method reads prefix-block halves from a temporary
    log (the image of the same run with a log), which is gone when the run returns."""
    import tempfile
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    args = dict(spp=16, seed=2, progress=False, track_error=False)
    scene = lambda: SceneRenderer(get_scene("soft_shadow"), width=24, height=24, seed=3, sampler="sobol")  # noqa: E731
    private = mcrecon.adapt(scene(), get_method("auto"), **args)
    logged = mcrecon.adapt(scene(), get_method("auto"), log=tmp_path / "kept" / "run.h5", **args)
    assert private.log is None and np.array_equal(private.image, logged.image)
    assert private.run.halves.sampler == "sobol"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["kept"]
