"""The Python API's shape: one input type for ``Method.reconstruct``, one dispatcher, literal
``restoration`` signatures, exposure in stops, and ``dir()`` of each public module."""

from __future__ import annotations

import numpy as np
import pytest

import mcrecon
from mcrecon import InputError, PixelStats
from mcrecon.methods import get_method
from mcrecon.methods.base import MethodInputs


def _stats(h=6, w=7, seed=0):
    rng = np.random.default_rng(seed)
    return PixelStats.from_moments(1.0 + rng.normal(0, 0.1, (h, w, 3)), np.full((h, w, 3), 0.04), 8)


def test_method_reconstruct_takes_method_inputs_only():
    st = _stats()
    m = get_method("box")
    for bad in (st, (st, st), st.mean):
        with pytest.raises(InputError, match=r"MethodInputs\(stats\)") as exc:
            m.reconstruct(bad)
        assert "mcrecon.reconstruct(source, method='box')" in str(exc.value)
    np.testing.assert_array_equal(m.reconstruct(MethodInputs(st)), mcrecon.reconstruct(st, method=m))


def test_one_dispatcher_checks_the_statistics_the_caller_gives():
    """mcrecon.reconstruct and mcrecon.restoration refuse the same bad statistics and halves."""
    from mcrecon.core.halves import split_halves
    from mcrecon.core.samples import SampleSet

    rng = np.random.default_rng(1)
    ss = SampleSet(rng.random((400, 2)) * 8, rng.random((400, 3)), width=8, height=8)
    a, b = split_halves(ss).a, split_halves(ss).b
    bad = _stats()
    bad.mean[2, 3, 1] = np.nan  # filled in from outside
    bad_half = split_halves(ss).b
    bad_half.m2[1, 1, 0] = np.inf
    cases = [(bad, "box", "stats.mean"), (PixelStats(4, 4), "gem", "stats"), ((a, bad_half), "auto", "halves[1].m2")]
    for source, name, field in cases:
        for call, where in ((lambda: mcrecon.reconstruct(source, method=name), "reconstruct"),
                            (lambda: getattr(mcrecon.restoration, name)(source), f"mcrecon.restoration.{name}")):
            with pytest.raises(InputError) as exc:
                call()
            assert (exc.value.where, exc.value.field) == (where, field)
    np.testing.assert_array_equal(mcrecon.restoration.auto((a, b)), mcrecon.reconstruct((a, b), method="auto"))


def test_exposure_is_in_stops_everywhere():
    from mcrecon.core.display import tonemap_srgb
    from mcrecon.methods.ci.method import StoppingRule
    from mcrecon.methods.ci.tone import tone_map

    x = np.array([0.05, 0.2, 0.3])
    assert get_method("ci").params["exposure"] == 0.0
    np.testing.assert_allclose(tone_map(x, tone="linear", exposure=2.0), 4.0 * x)
    np.testing.assert_allclose(tone_map(x, tone="linear", exposure=-1.0), 0.5 * x)
    # the same stops as the PNG preview (whose curve differs: compare the scale)
    np.testing.assert_allclose(tonemap_srgb(x, exposure=2.0), tonemap_srgb(4.0 * x))
    rule = StoppingRule(exposure=-2.0)  # negative stops are valid
    assert rule.scale == 0.25
    assert get_method("ci", exposure=-1.0).rule.exposure == -1.0


PUBLIC_MODULES = ["mcrecon", "mcrecon.restoration", "mcrecon.methods", "mcrecon.io", "mcrecon.renderers",
                  "mcrecon.core.metrics", "mcrecon.offline", "mcrecon.core.samples", "mcrecon.core.stats", "mcrecon.adaptive",
                  "mcrecon.distributed", "mcrecon.experiments", "mcrecon.core", "mcrecon.filters"]


@pytest.mark.parametrize("name", PUBLIC_MODULES)
def test_dir_shows_only_the_public_names(name):
    import importlib

    module = importlib.import_module(name)
    assert dir(module) == sorted(module.__all__)
    assert [n for n in module.__all__ if not hasattr(module, n)] == []


def test_restoration_functions_are_written_out_and_take_the_methods_options():
    """What static tools see (the source): each function, its input, its own parameters and ``**options``,
    the method's options, whose signature and docstring entries tests/test_options_written_once.py checks."""
    import ast
    import inspect

    from mcrecon import restoration

    tree = ast.parse(inspect.getsource(restoration))
    defs = {n.name: n for n in tree.body if isinstance(n, ast.FunctionDef)}
    assert restoration.__all__ == ["box", "gem", "awr", "splat", "auto", "nfor"] and not hasattr(restoration, "ci")
    for name in restoration.__all__:
        fn = defs[name]
        assert [a.arg for a in fn.args.posonlyargs] == ["source"] and not fn.args.args
        assert [a.arg for a in fn.args.kwonlyargs][-1] == "nonfinite"
        assert fn.args.vararg is None and fn.args.kwarg.arg == "options"  # unknown names: InputError
        doc = ast.get_docstring(fn)
        for section in ("Parameters", "Notes", "References", "Examples"):
            assert f"\n{section}\n" in doc, (name, section)
        for section in ("Returns", "Raises"):  # shared: the built docstring writes them in
            assert f"\n    {section}\n" in getattr(restoration, name).__doc__, (name, section)
    # options not given take the variant's presets, as get_method gives them; a given value wins,
    # also one equal to the default shown (it is not silently replaced by the paper's)
    st = _stats(16, 16)
    np.testing.assert_array_equal(restoration.gem(st, variant="paper"),
                                  mcrecon.reconstruct(st, method="gem", variant="paper").astype(st.dtype))
    mixed = mcrecon.reconstruct(st, method="gem", variant="paper", final_outliers="adaptive", gamma=0.2)
    np.testing.assert_array_equal(restoration.gem(st, variant="paper", final_outliers="adaptive", gamma=0.2),
                                  mixed.astype(st.dtype))
    assert not np.array_equal(mixed, mcrecon.reconstruct(st, method="gem", variant="paper"))
