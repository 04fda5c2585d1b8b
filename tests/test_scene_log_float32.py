"""Built-in scene logs hold float32 samples, positions and features, like the renderer bridges write.

float64 doubles the log (100 bytes a sample with features) for digits no
reconstruction uses; every sample must stay in its pixel.
"""

import h5py
import numpy as np

from mcrecon.io import read_log
from mcrecon.renderers.scenes import get_scene, render_uniform, write_scene_log


def test_scene_log_is_float32_and_keeps_every_sample_in_its_pixel(tmp_path):
    path = write_scene_log("checker_wall", tmp_path / "s.h5", width=12, height=10, spp=4, seed=2, features=True,
                           reference=False)
    with h5py.File(path, "r") as f:
        assert f["positions"].dtype == np.float32 and f["values"].dtype == np.float32
        assert {n: f[f"features/{n}"].dtype for n in f["features"]} == {n: np.float32 for n in f["features"]}
        pos32, val32 = f["positions"][...], f["values"][...]
        feats32 = {n: f[f"features/{n}"][...] for n in f["features"]}
    b = render_uniform(get_scene("checker_wall"), width=12, height=10, spp=4, seed=2, features=True)
    assert np.array_equal(np.floor(pos32), np.floor(b.positions))
    np.testing.assert_allclose(pos32, b.positions, rtol=1e-6)
    assert np.array_equal(val32, b.values.astype(np.float32))
    for n, a in feats32.items():
        assert np.array_equal(a, np.asarray(b.features[n], np.float32))
    assert read_log(str(path)).n_samples == 12 * 10 * 4
