"""A built-in scene's log is rendered and written in blocks: the file holds the rows of the one-shot write.

``write_scene_log`` streams blocks of samples (memory bounded by a block and the
image); whatever the block size, every attribute, dataset, dtype, HDF5 chunk shape
and row equals the log written whole from :func:`render_uniform`'s reply.
"""

import h5py
import numpy as np
import pytest

from mcrecon.io import write_log
from mcrecon.io.logformat import cast_positions
from mcrecon.renderers.scenes import SceneRenderer, get_scene, reference_image, render_uniform, write_scene_log


def _one_shot(path, scene, *, width, height, spp, seed, features, sampler):
    """The log as written from the whole reply held in memory (the layout write_scene_log keeps)."""
    sc = get_scene(scene)
    b = render_uniform(sc, width=width, height=height, spp=spp, seed=seed, features=features, sampler=sampler)
    meta = {"renderer": "mcrecon.scenes", "scene": sc.name, "seed": seed,
            "settings": {"width": width, "height": height, "spp": spp, "quadrature": 32, "n_dims": sc.n_dims}}
    if b.features:
        meta["settings"]["features"] = list(b.features)
    if sampler != "independent":
        meta["settings"]["sampler"] = sampler
    f32 = {k: np.asarray(v, np.float32) for k, v in b.features.items()} if b.features else None
    return write_log(path, cast_positions(b.positions, np.float32), np.asarray(b.values, np.float32), width=width,
                     height=height, channels=sc.channels, features=f32,
                     reference=reference_image(sc, width, height), metadata=meta,
                     sampler=None if sampler == "independent" else sampler)


def _contents(path) -> dict:
    out = {}
    with h5py.File(path, "r") as f:
        out["/"] = {k: (np.asarray(v).tolist() if not isinstance(v, str) else v) for k, v in f.attrs.items()}

        def visit(name, obj):
            if isinstance(obj, h5py.Dataset):
                out[name] = (obj.dtype.str, obj.shape, obj.chunks, obj.maxshape, obj.fletcher32, obj[...].tobytes(),
                             dict(obj.attrs))
        f.visititems(visit)
    return out


@pytest.mark.parametrize("scene,sampler,features", [("checker_wall", "independent", True),
                                                    ("checker_dof", "sobol", True),
                                                    ("motion_blur", "independent", False),
                                                    ("soft_shadow", "sobol", None)])
def test_blocks_of_any_size_write_the_one_shot_log(tmp_path, scene, sampler, features):
    kw = dict(width=13, height=7, spp=5, seed=3, features=features, sampler=sampler)
    whole = _contents(_one_shot(tmp_path / "whole.h5", scene, **kw))
    for block in (1, 17, 13 * 5, 10_000):
        got = _contents(write_scene_log(scene, tmp_path / f"b{block}.h5", block_samples=block, **kw))
        assert got.keys() == whole.keys()
        for k in whole:
            assert got[k] == whole[k], (block, k)


def test_uniform_rows_are_the_rows_of_the_whole_reply():
    for sampler in ("independent", "sobol"):
        r = SceneRenderer("checker_spot", width=9, height=4, seed=1, features=True, sampler=sampler)
        whole = render_uniform("checker_spot", width=9, height=4, spp=3, seed=1, features=True, sampler=sampler)
        for a, b in ((0, 108), (5, 6), (7, 61), (100, 108), (40, 40)):
            part = r.uniform_rows(3, a, b)
            assert np.array_equal(part.positions, whole.positions[a:b])
            assert np.array_equal(part.values, whole.values[a:b])
            for name, arr in whole.features.items():
                assert np.array_equal(part.features[name], arr[a:b])
