"""The array-level API: PixelStats.from_moments, mcrecon.restoration, mcrecon.reconstruct on every source."""

from __future__ import annotations

import doctest

import numpy as np
import pytest

import mcrecon
from mcrecon import PixelStats, SampleSet, restoration
from mcrecon.errors import InputError
from mcrecon.renderers.scenes import render_uniform, write_scene_log


@pytest.mark.parametrize("module", ["mcrecon.restoration", "mcrecon.offline.reconstruction", "mcrecon.core.stats",
                                    "mcrecon.core.samples"])
def test_examples_run(module):
    import importlib
    res = doctest.testmod(importlib.import_module(module), optionflags=doctest.ELLIPSIS)
    assert res.failed == 0 and res.attempted > 0


def _scene(w=24, h=20, spp=8, seed=0, dtype=np.float64):
    b = render_uniform("soft_shadow", width=w, height=h, spp=spp, seed=seed)
    return np.asarray(b.positions, dtype), np.asarray(b.values, dtype)


def test_from_moments_equals_the_statistics_of_the_samples():
    pos, val = _scene()
    st = PixelStats.from_samples(pos, val, width=24, height=20)
    var = st.sample_variance(undefined=0.0)
    mo = PixelStats.from_moments(st.mean, var, st.count)
    np.testing.assert_array_equal(mo.count, st.count)
    np.testing.assert_array_equal(mo.mean, st.mean)
    np.testing.assert_allclose(mo.m2, st.m2, rtol=1e-12, atol=1e-15)
    assert not mo.has_range and st.has_range
    # variance of the mean: the same statistics
    mo2 = PixelStats.from_moments(st.mean, var / st.count[..., None], st.count, variance_of="mean")
    np.testing.assert_allclose(mo2.m2, st.m2, rtol=1e-12, atol=1e-15)
    # the reconstruction from moments equals the one from samples (gem reads mean, variance, count)
    np.testing.assert_allclose(restoration.gem(mo), restoration.gem(st), rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("bad, field", [
    (dict(mean=np.full((4, 4, 3), np.nan)), "mean"),
    (dict(variance=-np.ones((4, 4, 3))), "variance"),
    (dict(variance=np.ones((4, 5, 3))), "variance"),
    (dict(count=np.full((4, 4), 2.5)), "count"),
    (dict(count=-np.ones((4, 4), int)), "count"),
    (dict(count=np.ones((4, 4), int)), "variance"),   # one sample but a variance
    (dict(variance_of="pixels"), "variance_of"),
])
def test_from_moments_refuses_bad_images(bad, field):
    args = dict(mean=np.ones((4, 4, 3)), variance=np.ones((4, 4, 3)), count=np.full((4, 4), 8))
    args.update(bad)
    with pytest.raises(InputError) as exc:
        PixelStats.from_moments(args.pop("mean"), args.pop("variance"), args.pop("count"), **args)
    assert exc.value.field == field


def test_empty_pixels_in_moments_are_ignored():
    mean = np.ones((3, 3, 1))
    mean[1, 1] = np.nan  # no sample there: its NaN is not data
    count = np.full((3, 3), 4)
    count[1, 1] = 0
    st = PixelStats.from_moments(mean, np.full((3, 3, 1), 0.5), count)
    assert st.count[1, 1] == 0 and st.mean[1, 1, 0] == 0
    with pytest.warns(mcrecon.McreconWarning, match="1 pixel"):
        assert np.isfinite(restoration.box(st)).all()


@pytest.mark.parametrize("name", ["box", "gem", "awr"])
def test_float32_in_float32_out_and_float64_in_float64_out(name):
    for dtype in (np.float32, np.float64):
        pos, val = _scene(dtype=dtype)
        st = PixelStats.from_samples(pos, val, width=24, height=20)
        out = getattr(restoration, name)(st)
        assert out.dtype == dtype and out.shape == (20, 24, 3) and np.isfinite(out).all()
        # the same numbers as the method behind it
        np.testing.assert_array_equal(out, mcrecon.reconstruct(st, method=name).astype(dtype))


def test_splat_takes_samples_and_refuses_statistics():
    pos, val = _scene(dtype=np.float32)
    out = restoration.splat(SampleSet(pos, val, width=24, height=20))
    assert out.dtype == np.float32
    with pytest.raises(InputError, match="individual samples"):
        restoration.splat(PixelStats.from_samples(pos, val, width=24, height=20))


def test_validation_at_the_top():
    st = PixelStats(6, 5)
    for fn in (restoration.box, restoration.gem, restoration.awr):
        with pytest.raises(InputError, match="no pixel has a sample"):
            fn(st)
    pos, val = _scene()
    st = PixelStats.from_samples(pos, val, width=24, height=20)
    st.mean[3, 4, 1] = np.nan  # corrupted from outside
    for fn in (restoration.gem, restoration.awr):
        with pytest.raises(InputError, match="1 sampled pixel"):
            fn(st)
    with pytest.raises(InputError, match="gamma"):
        restoration.gem(PixelStats.from_samples(pos, val, width=24, height=20), gamma=0.5)
    with pytest.raises(InputError, match="unknown option; valid"):
        restoration.gem(PixelStats.from_samples(pos, val, width=24, height=20), sigma=2)
    # the message lists every valid option, not only those the call gave
    with pytest.raises(InputError, match="valid: .*confirm_stops.*gamma.*variant"):
        restoration.gem(PixelStats.from_samples(pos, val, width=24, height=20), gamma=0.3, gamm=0.2)
    with pytest.raises(InputError, match="expected PixelStats"):
        restoration.gem(np.zeros((4, 4, 3)))


def test_signature_lists_the_options():
    import inspect
    sig = inspect.signature(restoration.gem)
    assert sig.parameters["gamma"].default == 0.2
    assert sig.parameters["gamma"].kind is inspect.Parameter.KEYWORD_ONLY
    assert "References" in restoration.gem.__doc__ and "Examples" in restoration.gem.__doc__


def test_reconstruct_accepts_logs_samples_and_statistics(tmp_path):
    path = write_scene_log("caustic", tmp_path / "c.h5", width=16, height=12, spp=6, seed=1)
    log = mcrecon.read_log(path)
    chunk = log.read_all()
    samples = SampleSet(chunk.positions, chunk.values, width=16, height=12)
    stats = PixelStats.from_log(log)
    for name in ("box", "gem", "awr", "ci"):
        a = mcrecon.reconstruct(path, method=name)
        np.testing.assert_array_equal(mcrecon.reconstruct(log, method=name), a)
        np.testing.assert_array_equal(mcrecon.reconstruct(samples, method=name), a)
        np.testing.assert_array_equal(mcrecon.reconstruct(stats, method=name), a)
    a = mcrecon.reconstruct(path, method="splat")
    np.testing.assert_array_equal(mcrecon.reconstruct(samples, method="splat"), a)
    rec = mcrecon.reconstruct(path, method="gem", full=True)
    assert "selected_scale" in rec.diagnostics()
    with pytest.raises(InputError, match="expected a sample log path"):
        mcrecon.reconstruct(42, method="box")
    with pytest.raises(InputError, match="options go to get_method"):
        mcrecon.reconstruct(path, method=mcrecon.get_method("gem"), gamma=0.1)
