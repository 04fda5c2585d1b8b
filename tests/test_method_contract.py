"""The method contract: immutable configuration, per-run state, declared inputs, one validation path."""

from __future__ import annotations

import ast
import importlib.util
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

import mcrecon
from mcrecon.adaptive.run import adapt, resume
from mcrecon.errors import InputError, McreconWarning
from mcrecon.methods import METHODS, Option, get_method
from mcrecon.core.metrics import relative_mse
from mcrecon.renderers.scenes import SceneRenderer, reference_image, write_scene_log

ROOT = Path(__file__).resolve().parents[1]


def _example_module():
    spec = importlib.util.spec_from_file_location("example_method", ROOT / "docs/methods/example_method.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


# ------------------------------------------------------------------ reuse
def _quiet(fn):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", McreconWarning)
        return fn()


@pytest.mark.parametrize("name", sorted(METHODS))
def test_one_method_object_serves_any_number_of_runs(name, tmp_path):
    """Reusing a method object, in any order, gives what fresh objects give (the bug: splat
    rendered 0 samples on its second run and returned the first run's image)."""
    # a method that requires features gets the textured scenes, which render them
    feat = get_method(name).requires.features == "required"
    sa, sb, sc = ("checker_wall", "checker_spot", "checker_dof") if feat else ("soft_shadow", "caustic", "flat")
    ra = SceneRenderer(sa, width=12, height=10, seed=1)
    rb = SceneRenderer(sb, width=9, height=11, seed=2)
    fresh_a = _quiet(lambda: adapt(ra, get_method(name), spp=8, seed=3, progress=False))
    fresh_b = _quiet(lambda: adapt(rb, get_method(name), spp=8, seed=4, progress=False))
    m = get_method(name)
    runs = [(rb, 4, fresh_b), (ra, 3, fresh_a), (rb, 4, fresh_b), (ra, 3, fresh_a)]
    for renderer, seed, fresh in runs:
        res = _quiet(lambda: adapt(renderer, m, spp=8, seed=seed, progress=False))
        np.testing.assert_array_equal(res.image, fresh.image)
        np.testing.assert_array_equal(res.counts, fresh.counts)
        assert res.stopped == fresh.stopped
    # offline too: two logs of different sizes, alternately
    la = write_scene_log(sa, tmp_path / "a.h5", width=12, height=10, spp=6, seed=1)
    lb = write_scene_log(sc, tmp_path / "b.h5", width=7, height=5, spp=6, seed=2)
    want_a = _quiet(lambda: mcrecon.reconstruct(la, method=name))
    want_b = _quiet(lambda: mcrecon.reconstruct(lb, method=name))
    for path, want in ((lb, want_b), (la, want_a), (lb, want_b)):
        np.testing.assert_array_equal(_quiet(lambda: mcrecon.reconstruct(path, method=m)), want)


@pytest.mark.parametrize("name", sorted(METHODS))
def test_methods_are_immutable_and_validate_options_once(name):
    m = get_method(name)
    with pytest.raises(AttributeError, match="fixed once built"):
        m.params_copy = 1
    with pytest.raises(TypeError):
        m.params["x"] = 1
    with pytest.raises(InputError, match="unknown option; valid"):
        get_method(name, no_such_option=1)
    for opt in m.options:  # every option's own default passes its own validation
        assert get_method(name, **{opt.name: opt.default}).params[opt.name] == opt.default


@pytest.mark.parametrize("name", sorted(METHODS))
def test_variants_preset_valid_options_and_explicit_options_win(name):
    cls = get_method(name).__class__
    opts = {o.name: o for o in cls.options}
    if "variant" not in opts:
        assert not cls.variants, f"{name} has variants but no variant option"
        return
    assert set(opts["variant"].choices) == set(cls.variants) and "paper" in cls.variants
    for variant, presets in cls.variants.items():
        m = get_method(name, variant=variant)
        assert m.params["variant"] == variant
        for oname, value in presets.items():
            assert oname in opts, f"{name} variant {variant} presets unknown option {oname}"
            assert opts[oname].convert(value, "t") == value  # presets pass the option's own validation
            assert m.params[oname] == value == cls.option_default(oname, variant)
        for oname, opt in opts.items():  # what a variant does not preset keeps the option's default
            if oname not in presets and oname != "variant":
                assert m.params[oname] == opt.default
        for oname, value in presets.items():  # an explicit option wins over the variant's preset
            other = opts[oname].default
            if other != value:
                assert get_method(name, variant=variant, **{oname: other}).params[oname] == other


def test_variant_presets_apply_only_to_options_not_given():
    from mcrecon.methods import Method, variant_option

    class Toy(Method):
        name = "toy"
        variants = {"robust": {}, "paper": {"k": 3, "mode": "b"}}
        options = (variant_option(variants), Option("k", int, 1, "k", min=1),
                   Option("mode", str, "a", "mode", ("a", "b")))

    assert dict(Toy().params) == {"variant": "robust", "k": 1, "mode": "a"}
    assert dict(Toy(variant="paper").params) == {"variant": "paper", "k": 3, "mode": "b"}
    assert dict(Toy(variant="paper", k=2).params) == {"variant": "paper", "k": 2, "mode": "b"}
    with pytest.raises(InputError, match="valid: robust, paper"):
        Toy(variant="nope")
    with pytest.raises(ValueError, match="paper"):
        variant_option({"robust": {}})


def test_option_conversion_bounds_and_messages():
    o = Option("k", int, 2, "a count", min=1)
    assert o.convert("4", "m") == 4 and o.convert(4.0, "m") == 4
    assert o.convert(2**53 + 1, "m") == 2**53 + 1 and o.convert(str(2**60 + 1), "m") == 2**60 + 1
    for bad in ("4.5", 0, True, float("nan"), "x", None):
        with pytest.raises(InputError, match=r"expected an integer >= 1"):
            o.convert(bad, "m")
    f = Option("g", float, 0.2, "rate", min=0.0, max=0.4, min_open=True, max_open=True, note="calibrated there")
    assert f.convert("0.3", "m") == 0.3
    with pytest.raises(InputError, match=r"0 < g < 0.4 \(calibrated there\)"):
        f.convert(0.4, "m")
    n = Option("t", float, None, "target", min=0.0, min_open=True)
    assert n.convert(None, "m") is None and n.convert("none", "m") is None
    c = Option("mode", str, "a", "mode", choices=("a", "b"))
    with pytest.raises(InputError, match="valid: a, b"):
        c.convert("z", "m")
    b = Option("flag", bool, False, "switch")
    assert b.convert("yes", "m") is True and b.convert(0, "m") is False


# ------------------------------------------------------------------ layering
def _imports(path: Path) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            names.add("." * node.level + (node.module or ""))
    return names


def _outside_methods(name: str, path: Path) -> str | None:
    """``name`` (as :func:`_imports` gives it) of ``path`` as a module path under mcrecon, if it leaves mcrecon/methods."""
    if not name.startswith("."):
        return name[len("mcrecon."):] if name.startswith("mcrecon.") else None
    level = len(name) - len(name.lstrip("."))
    package = path.relative_to(ROOT).parent.parts  # ("mcrecon", "methods", ...)
    base = package[:len(package) - level + 1]
    if base[:2] == ("mcrecon", "methods"):
        return None
    return ".".join(base[1:] + tuple(p for p in name.lstrip(".").split(".") if p))


def test_no_method_module_imports_h5py_the_io_layer_or_a_renderer():
    # Methods see renderers only through the request/batch types of renderers.protocol.
    for path in sorted((ROOT / "mcrecon/methods").rglob("*.py")):
        bad = set()
        for n in _imports(path):
            if n == "h5py" or n.startswith("h5py."):
                bad.add(n)
                continue
            mod = _outside_methods(n, path)
            if mod is None:
                continue
            top = mod.split(".")[0]
            if top in ("io", "driver", "cli") or (top == "renderers" and mod != "renderers.protocol"):
                bad.add(n)
        assert not bad, f"{path.relative_to(ROOT)} imports {sorted(bad)}"


# ------------------------------------------------------------------ declared inputs
def test_declared_inputs_are_what_the_reader_supplies(tmp_path):
    assert get_method("splat").requires.samples and not get_method("splat").requires.statistics
    assert get_method("gem").requires.subpixels == 0
    assert get_method("gem", subpixel_exact_below=1.0).requires.subpixels == 4
    assert get_method("gem", oracle=1).requires.reference == "required"
    path = write_scene_log("soft_shadow", tmp_path / "s.h5", width=10, height=8, spp=4)
    rec = mcrecon.reconstruct(path, method="gem", subpixel_exact_below=1.0, full=True)
    # gem reads the log's prefix halves (guard_halves, stratified_gain), not the samples
    assert rec.inputs.stats.subpixels == 4 and rec.inputs.samples is None and rec.inputs.reference is None
    assert rec.inputs.strata is not None and (rec.inputs.strata.height, rec.inputs.strata.width) == (8, 10)
    assert get_method("gem").requires.prefix_halves and not get_method("gem", variant="paper").requires.prefix_halves
    assert mcrecon.reconstruct(path, method="gem", variant="paper", full=True).inputs.strata is None
    assert mcrecon.reconstruct(rec.inputs.stats, method="gem", full=True).inputs.strata is None
    rec = mcrecon.reconstruct(path, method="gem", oracle=1, full=True)
    np.testing.assert_array_equal(rec.inputs.reference, reference_image("soft_shadow", 10, 8))
    rec = mcrecon.reconstruct(path, method="splat", full=True)
    assert rec.inputs.stats is None and rec.inputs.samples is not None


def test_resume_replays_rounds_only_into_methods_that_observe_samples(tmp_path, monkeypatch):
    calls = []
    from mcrecon.methods.splat import SplatMethod
    from mcrecon.methods.base import Method
    orig = SplatMethod.observe
    monkeypatch.setattr(Method, "observe", lambda self, run, batch, r: calls.append(("base", r)))
    monkeypatch.setattr(SplatMethod, "observe", lambda self, run, batch, r: (calls.append(("splat", r)),
                                                                            orig(self, run, batch, r)))
    r = SceneRenderer("flat", width=6, height=6, seed=0)
    for name in ("box", "gem", "splat"):
        calls.clear()
        adapt(r, name, spp=9, seed=1, log=tmp_path / f"{name}.h5", max_rounds=2, progress=False)
        calls.clear()
        _quiet(lambda: resume(tmp_path / f"{name}.h5", r, progress=False))
        assert (name == "splat") == bool(calls), (name, calls)


# ------------------------------------------------------------------ the documented example
def test_the_contract_documents_example_method_runs(tmp_path):
    mod = _example_module()
    m = mod.BlurMethod(size=3)
    with pytest.raises(InputError, match="odd"):
        mod.BlurMethod(size=4)
    r = SceneRenderer("soft_shadow", width=24, height=20, seed=0)
    ref = reference_image("soft_shadow", 24, 20)
    res = adapt(r, m, spp=8, seed=5, reference=ref, log=tmp_path / "run.h5", progress=False)
    assert res.stats.n_samples == 8 * 24 * 20 and res.run.priority.shape == (20, 24)
    assert res.counts.std() > 0  # adaptive: not uniform
    assert set(res.diagnostics()) == {"spp", "priority"}
    again = adapt(r, m, spp=8, seed=5, reference=ref, progress=False)  # reused object, same result
    np.testing.assert_array_equal(again.image, res.image)
    offline = mcrecon.reconstruct(tmp_path / "run.h5", method=m)
    np.testing.assert_array_equal(offline, res.image)
    from scipy import ndimage
    np.testing.assert_array_equal(offline, ndimage.uniform_filter(res.stats.mean, size=(3, 3, 1), mode="nearest"))
    # on a flat noisy scene the 3x3 mean beats the pixel mean
    flat = write_scene_log("flat", tmp_path / "flat.h5", width=16, height=16, spp=4, seed=2)
    fref = reference_image("flat", 16, 16)
    assert relative_mse(mcrecon.reconstruct(flat, method=m), fref) < \
        0.16 * relative_mse(mcrecon.reconstruct(flat, method="box"), fref)  # measured 0.135; 15 % margin
    # registered, a stopped run resumes from its log alone and ends as the uninterrupted one
    from mcrecon import methods as registry

    before = dict(registry.METHODS)
    try:
        registry.register_method("blur", mod.BlurMethod)
        adapt(r, m, spp=8, seed=5, reference=ref, log=tmp_path / "part.h5", progress=False, max_rounds=2)
        done = resume(tmp_path / "part.h5", r, progress=False)
        np.testing.assert_array_equal(done.image, res.image)
    finally:
        registry.METHODS.clear()
        registry.METHODS.update(before)
        registry._CLASSES.clear()
    # the contract page promises a complete example under 80 lines
    assert len((ROOT / "docs/methods/example_method.py").read_text().splitlines()) < 80


# ------------------------------------------------------------------ registering a user's method
def test_register_method_adds_a_class_or_a_path_and_refuses_clashes():
    import mcrecon
    from mcrecon import methods as registry
    from mcrecon.methods.box import BoxMethod

    class Halved(BoxMethod):
        name = "halved_test"

        def reconstruct_run(self, run, inputs):
            return super().reconstruct_run(run, inputs) * 0.5

    before = dict(registry.METHODS)
    try:
        registry.register_method("halved_test", Halved)
        assert "halved_test" in mcrecon.available_methods()
        st = mcrecon.PixelStats.from_moments(np.full((2, 3, 3), 4.0), np.ones((2, 3, 3)), np.full((2, 3), 2))
        np.testing.assert_array_equal(mcrecon.reconstruct(st, method="halved_test"), 2.0)
        # a path is imported on first use; its class must carry the registered name
        registry.register_method("box_path_test", "mcrecon.methods.box:BoxMethod")
        with pytest.raises(InputError, match="box_path_test.*not available.*name is 'box'"):
            mcrecon.get_method("box_path_test")
        with pytest.raises(InputError, match="registered already"):
            registry.register_method("gem", type("GemToo", (Halved,), {"name": "gem"}))  # a built-in stays

        class HalvedToo(Halved):
            name = "halved_test"

        with pytest.raises(InputError, match="replace=True"):
            registry.register_method("halved_test", HalvedToo)
        registry.register_method("halved_test", HalvedToo, replace=True)
        assert type(mcrecon.get_method("halved_test")) is HalvedToo
        # the log records the method's own name and --resume looks it up: the two must agree
        with pytest.raises(InputError, match="Halved.name is 'halved_test'.*--resume"):
            registry.register_method("other_name", Halved)
        with pytest.raises(InputError, match="not a subclass"):
            registry.register_method("nope", dict)
    finally:
        registry.METHODS.clear()
        registry.METHODS.update(before)
        registry._CLASSES.clear()


def test_an_entry_point_in_the_methods_group_registers_a_method(tmp_path, monkeypatch):
    """A package declaring ``[project.entry-points."mcrecon.methods"]`` is found without editing the registry."""
    from mcrecon import methods as registry

    pkg = tmp_path / "userblur"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("from mcrecon.methods.box import BoxMethod\n\n"
                                     "class UserBlur(BoxMethod):\n    name = 'userblur'\n")
    dist = tmp_path / "userblur-1.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: userblur\nVersion: 1.0\n")
    (dist / "entry_points.txt").write_text("[mcrecon.methods]\nuserblur = userblur:UserBlur\n"
                                           "gem = userblur:UserBlur\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    before = dict(registry.METHODS)
    monkeypatch.setattr(registry, "_entry_points_read", False)
    try:
        with pytest.warns(McreconWarning, match="gem.*taken"):
            names = registry.available_methods()
        assert "userblur" in names
        assert registry.get_method("userblur").name == "userblur"
        assert registry.METHODS["gem"] == before["gem"]
    finally:
        registry.METHODS.clear()
        registry.METHODS.update(before)
