"""The built-in scenes' parameters: defaults bit-identical, expectations exact for drawn parameters, specs
that rebuild the same scene, and bad values refused."""

from __future__ import annotations

import numpy as np
import pytest

from mcrecon.errors import InputError
from mcrecon.renderers import renderer_from_spec, reference_from_spec
from mcrecon.renderers import scenes as S
from mcrecon.renderers.scenes.params import PARAMS, defaults


def _draw(name, rng):
    """Parameters drawn inside each one's range, away from the edges (log-uniform for wide ranges)."""
    out = {}
    for k, (d, lo, hi, _) in PARAMS[name].items():
        if k == "speed":
            lo, hi = 0.3, 1.2
        if lo > 0 and hi / lo > 50:
            lo, hi = max(lo, d / 5), min(hi, d * 5) if d > 0 else hi
            out[k] = float(np.exp(rng.uniform(np.log(lo), np.log(hi))))
        else:
            out[k] = float(lo + (hi - lo) * rng.uniform(0.15, 0.85))
    return out


def _points(n, rng):
    return rng.random(n), rng.random(n)


@pytest.mark.parametrize("name", S.scene_names())
def test_default_parameters_give_the_constant_scene_bit_for_bit(name):
    rng = np.random.default_rng(1)
    base = S.get_scene(name)
    same = S.get_scene(name, params=defaults(name))
    assert same.params == {} and base.params == {}
    x, y = _points(500, rng)
    u = rng.random((500, base.n_dims))
    assert np.array_equal(base.radiance(x, y, u), same.radiance(x, y, u))
    assert np.array_equal(base.expected(x, y), same.expected(x, y))
    f0, f1 = base.features(x, y, u), same.features(x, y, u)
    assert all(np.array_equal(f0[k], f1[k]) for k in f0)


@pytest.mark.parametrize("name", [n for n in S.scene_names()])
def test_monte_carlo_mean_matches_the_closed_form_for_drawn_parameters(name):
    rng = np.random.default_rng(len(name) * 7919)
    params = _draw(name, rng)
    sc = S.get_scene(name, params)
    assert sc.params                                   # the draw is not the default scene
    n_pts, n_u = 40, 20000
    x, y = _points(n_pts, rng)
    xs, ys = np.repeat(x, n_u), np.repeat(y, n_u)
    u = rng.random((xs.size, sc.n_dims))
    vals = sc.radiance(xs, ys, u).reshape(n_pts, n_u, 3)
    mean, se = vals.mean(axis=1), vals.std(axis=1) / np.sqrt(n_u)
    exp = sc.expected(x, y)
    assert np.all(np.abs(mean - exp) <= 5 * se + 1e-12 * (1 + np.abs(exp))), (params, mean, exp)
    feats = sc.features(xs, ys, u)
    fexp = sc.expected_features(x, y)
    for k in feats:
        fv = feats[k].reshape(n_pts, n_u, -1)
        fm, fse = fv.mean(axis=1), fv.std(axis=1) / np.sqrt(n_u)
        assert np.all(np.abs(fm - fexp[k]) <= 5 * fse + 1e-12), (k, params)


@pytest.mark.parametrize("name", S.scene_names())
def test_pixel_means_converge_to_the_parametrised_reference(name):
    rng = np.random.default_rng(len(name))
    sc = S.get_scene(name, _draw(name, rng))
    w, h, spp = 16, 12, 3000
    ref = S.reference_image(sc, w, h, quadrature=128)
    b = S.render_uniform(sc, width=w, height=h, spp=spp, seed=3)
    idx = np.floor(b.positions[:, 1]).astype(int) * w + np.floor(b.positions[:, 0]).astype(int)
    mean = np.stack([np.bincount(idx, b.values[:, c], w * h) / spp for c in range(3)], 1).reshape(h, w, 3)
    sq = np.stack([np.bincount(idx, b.values[:, c] ** 2, w * h) / spp for c in range(3)], 1).reshape(h, w, 3)
    se = np.sqrt(np.maximum(sq - mean ** 2, 0) / spp)
    # 5 standard errors, and the midpoint rule's error at q = 128 (a fraction of a percent of a jump)
    assert np.all(np.abs(mean - ref) <= 5 * se + 2e-3 * np.abs(ref).max()), np.abs(mean - ref).max()
    assert not np.array_equal(ref, S.reference_image(name, w, h, quadrature=128))      # the parameters change the reference


def test_each_parameter_changes_its_scene():
    # a sampling parameter (a hit probability) changes the samples, not the expectation
    rng = np.random.default_rng(5)
    x, y = _points(4000, rng)
    for name, table in PARAMS.items():
        sc = S.get_scene(name)
        u = rng.random((x.size, sc.n_dims))
        base = np.concatenate([sc.expected(x, y), sc.radiance(x, y, u)])
        for k, (d, lo, hi, _) in table.items():
            v = 1.2 if k == "speed" else (d + 0.3 * (hi - d) if hi > d else d - 0.3 * (d - lo))
            other = S.get_scene(name, {k: v})
            assert not np.array_equal(np.concatenate([other.expected(x, y), other.radiance(x, y, u)]), base), \
                (name, k)


def test_exposure_and_power_scale_what_they_should():
    x, y = _points(300, np.random.default_rng(2))
    e1 = S.get_scene("caustic").expected(x, y)
    np.testing.assert_allclose(S.get_scene("caustic", exposure=3.0).expected(x, y), 3.0 * e1, rtol=1e-15)
    np.testing.assert_allclose(S.reference_image(S.get_scene("hdr", exposure=0.5), 8, 8),
                               0.5 * S.reference_image("hdr", 8, 8), rtol=1e-15)
    # the hdr emitter's power: the emitter region scales, the rest stays
    a = S.get_scene("hdr").expected(np.array([0.3, 0.1]), np.array([0.3, 0.9]))
    b = S.get_scene("hdr", power=5000.0).expected(np.array([0.3, 0.1]), np.array([0.3, 0.9]))
    np.testing.assert_allclose(b[0], 10 * a[0], rtol=1e-14)
    np.testing.assert_array_equal(b[1], a[1])


def test_parameters_as_keywords_or_dict_are_the_same_scene():
    a = S.get_scene("checker_spot", hit_probability=0.1, light_power=2)
    b = S.get_scene("checker_spot", params={"light_power": 2.0, "hit_probability": 0.1})
    assert a.params == b.params == {"hit_probability": 0.1, "light_power": 2.0}
    assert "hit_probability" in repr(a)


def test_spec_records_non_default_parameters_and_rebuilds_the_same_scene():
    sc = S.get_scene("caustic", power=2.5, ring_width=1.5)
    r = S.SceneRenderer(sc, width=12, height=10, seed=4)
    spec = r.spec()
    assert spec["params"] == {"power": 2.5, "ring_width": 1.5}
    again = renderer_from_spec(spec)
    assert again.scene.params == sc.params
    np.testing.assert_array_equal(reference_from_spec(spec), S.reference_image(sc, 12, 10))
    assert "params" not in S.SceneRenderer("caustic", width=12, height=10).spec()   # defaults: as before


def test_resume_renders_the_parametrised_scene(tmp_path):
    import mcrecon

    sc = S.get_scene("soft_shadow", light_power=2.0, texture_scale=2.0)
    log = tmp_path / "run.h5"
    mcrecon.adapt(S.SceneRenderer(sc, width=16, height=16), "gem", spp=4, log=log, progress=False)
    spec = mcrecon.read_log(log).run_settings["renderer_spec"]
    assert spec["params"] == {"light_power": 2.0, "texture_scale": 2.0}
    assert renderer_from_spec(spec).scene.params == sc.params


def test_scene_log_metadata_names_the_parameters(tmp_path):
    import mcrecon

    S.write_scene_log(S.get_scene("flat", exposure=2.0), tmp_path / "f.h5", width=4, height=4, spp=2)
    meta = mcrecon.read_log(tmp_path / "f.h5").metadata
    assert meta["params"] == {"exposure": 2.0}
    S.write_scene_log("flat", tmp_path / "g.h5", width=4, height=4, spp=2)
    assert "params" not in mcrecon.read_log(tmp_path / "g.h5").metadata


@pytest.mark.parametrize("kwargs, field", [
    ({"bogus": 1.0}, "params.bogus"),
    ({"power": -1.0}, "params.power"),
    ({"power": float("nan")}, "params.power"),
    ({"power": "big"}, "params.power"),
    ({"power": True}, "params.power"),
])
def test_bad_parameters_are_refused_with_the_field_named(kwargs, field):
    with pytest.raises(InputError) as e:
        S.get_scene("caustic", **kwargs)
    assert e.value.field == field


def test_a_speed_that_makes_objects_overlap_is_refused():
    with pytest.raises(InputError, match="overlap"):
        S.get_scene("motion_blur", speed=1.4)


def test_spec_with_bad_parameters_is_refused():
    from mcrecon.renderers import check_spec

    with pytest.raises(InputError):
        check_spec({"kind": "scene", "scene": "flat", "width": 4, "height": 4, "params": {"power": 2.0}})
    with pytest.raises(InputError):
        check_spec({"kind": "scene", "scene": "flat", "width": 4, "height": 4, "params": [1, 2]})
