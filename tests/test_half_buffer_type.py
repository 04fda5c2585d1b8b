"""One half-buffer type: every method reads ``inputs.halves`` as :class:`mcrecon.core.halves.Halves`.

The offline dispatcher splits a sample source once (or converts a caller's
pair once), an adaptive run's halves come from ``Method.observe`` through
``Method.run_inputs``; the methods themselves never split samples, and the
clamp that keeps pixels without samples lives in ``core/safeguard``.
"""

from __future__ import annotations

import ast
import warnings
from pathlib import Path

import numpy as np
import pytest

import mcrecon
from mcrecon import InputError, PixelStats, SampleSet
from mcrecon.core.halves import Halves, as_halves, split_halves
from mcrecon.core.safeguard import confidence_clamp, empty_pixels_kept
from mcrecon.io import write_log
from mcrecon.methods import get_method
from mcrecon.methods.base import MethodInputs

PACKAGE = Path(mcrecon.__file__).parent
H, W = 10, 12


def sample_set(spp=6, seed=0, features=False):
    rng = np.random.default_rng(seed)
    n = H * W * spp
    pos = rng.random((n, 2)) * [W, H]
    val = 0.5 + 0.3 * np.sin(pos[:, :1] / 2.0) * np.ones((1, 3)) + rng.normal(0, 0.1, (n, 3))
    feats = {"albedo": np.clip(0.5 + 0.1 * np.sin(pos[:, :1]) * np.ones((1, 3)), 0, 1)} if features else None
    return SampleSet(pos, val, width=W, height=H, features=feats)


def quiet(fn, *a, **k):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return fn(*a, **k)


def test_the_one_type_unpacks_as_a_pair_and_knows_its_source():
    ss = sample_set()
    h = split_halves(ss)
    a, b = h
    assert isinstance(h, Halves) and h.source is ss and (a, b) == (h.a, h.b) and (h[0], h[1]) == (h.a, h.b)
    assert len(h) == 2 and h.shape == (H, W, 3) and h.n_samples == ss.n_samples
    # a caller's pair is converted once, at the boundary; Halves pass through as they are
    pair = as_halves((h.a, h.b))
    assert isinstance(pair, Halves) and pair.source is None and as_halves(pair) is pair
    with pytest.raises(InputError, match=r"halves\[1\]"):
        as_halves((h.a, "b.exr"))


@pytest.mark.parametrize("method, extra", [("auto", {}), ("nfor", {})])
def test_every_path_hands_the_method_halves_of_the_one_type(method, extra):
    ss = sample_set(features=method == "nfor")
    full = quiet(mcrecon.reconstruct, ss, method=method, full=True)
    assert isinstance(full.inputs.halves, Halves) and full.inputs.halves.source is ss  # the dispatcher's split
    h = split_halves(ss, features="all" if method == "nfor" else ())
    pair = quiet(mcrecon.reconstruct, (h.a, h.b), method=method, full=True)  # the user's tuple, converted once
    assert isinstance(pair.inputs.halves, Halves) and pair.inputs.halves.source is None
    np.testing.assert_array_equal(pair.image, full.image)
    # MethodInputs built by hand: a tuple is taken too
    np.testing.assert_array_equal(quiet(get_method(method).reconstruct, MethodInputs(None, halves=[h.a, h.b])),
                                  full.image)


def test_the_dispatcher_splits_once_and_the_methods_never(monkeypatch):
    import mcrecon.offline.inputs as inputs

    calls = []
    real = inputs.split_halves
    monkeypatch.setattr(inputs, "split_halves", lambda *a, **k: calls.append(1) or real(*a, **k))
    quiet(mcrecon.reconstruct, sample_set(), method="auto")
    assert calls == [1]
    # no method module splits samples or builds halves itself
    for rel in ("methods/auto/method.py", "methods/nfor/method.py"):
        tree = ast.parse((PACKAGE / rel).read_text())
        names = {a.name for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) for a in n.names}
        attrs = {n.attr for n in ast.walk(tree) if isinstance(n, ast.Attribute)}
        built = [n for n in ast.walk(tree) if isinstance(n, ast.Call) and "Halves" in ast.unparse(n.func)]
        assert not names & {"split_halves", "split_labels", "merge_halves", "check_half_buffers"}, rel
        assert "iter_chunks" not in attrs and not built, rel


def test_an_adaptive_run_supplies_its_halves_through_method_inputs(tmp_path):
    from mcrecon.adaptive.run import adapt
    from mcrecon.renderers.scenes import SceneRenderer

    m = get_method("auto")
    seen = []
    real = type(m).reconstruct_run

    class Spy(type(m)):
        def reconstruct_run(self, run, inputs):
            seen.append(inputs.halves)
            return real(self, run, inputs)

    spy = Spy()
    res = quiet(adapt, SceneRenderer("soft_shadow", width=16, height=12, seed=0), spy, spp=8, seed=1,
                log=tmp_path / "r.h5", progress=False)
    assert seen and isinstance(seen[-1], Halves) and seen[-1].n_samples == res.stats.n_samples
    np.testing.assert_array_equal(res.image, quiet(mcrecon.reconstruct, tmp_path / "r.h5", method="auto"))


def test_empty_pixels_keep_their_filled_value_through_the_clamp():
    img = np.full((2, 2, 1), 5.0)
    mean = np.array([[[1.0], [0.0]], [[1.0], [1.0]]])
    count = np.array([[3, 0], [3, 3]])
    var = np.full((2, 2, 1), 0.01)
    var[0, 1] = 0.0  # an empty pixel: mean 0, variance 0
    clamped = confidence_clamp(img.copy(), mean, var, 4.0)
    assert clamped[0, 1, 0] == 0.0  # without the guard the empty pixel would go to its mean 0
    with empty_pixels_kept(img, count):
        confidence_clamp(img, mean, var, 4.0, out=img)
    assert img[0, 1, 0] == 5.0 and img[0, 0, 0] == pytest.approx(1.4)
    # the clamp is written once: auto and nfor use the guard, neither restores empty pixels itself
    for rel in ("methods/auto/clamp.py", "methods/nfor/method.py"):
        text = (PACKAGE / rel).read_text()
        assert "empty_pixels_kept(" in text and "img[empty] = filled" not in text, rel


def test_nfor_on_one_sampled_pixel_whose_one_half_is_empty_gives_the_sample(tmp_path):
    """One sample in a 12x10 film: one half buffer holds nothing; every pixel is the sample (as box's)."""
    path = write_log(tmp_path / "one.h5", np.array([[3.5, 4.5]]), np.array([[2.0, 4.0, 8.0]]), width=W,
                     height=H, features={"albedo": np.array([[0.5, 0.5, 0.5]])})
    box = quiet(mcrecon.reconstruct, path, method="box")
    nfor = quiet(mcrecon.reconstruct, path, method="nfor")
    # within rounding: the fill's weighted mean of equal values is exact only where its sum's order allows
    # (numpy's vectorised sums differ by CPU: 1.9999999999999998 at 6 of 360 values on an AVX2 machine)
    np.testing.assert_allclose(nfor, box, rtol=4e-16, atol=0)
    np.testing.assert_allclose(nfor, np.broadcast_to([2.0, 4.0, 8.0], nfor.shape), rtol=4e-16, atol=0)


def test_nfor_on_a_log_without_samples_names_the_file(tmp_path):
    path = write_log(tmp_path / "empty.h5", np.zeros((0, 2)), np.zeros((0, 3)), width=W, height=H,
                     features={"albedo": np.zeros((0, 3))})
    with pytest.raises(InputError, match="no sample") as exc:
        mcrecon.reconstruct(path, method="nfor")
    assert str(exc.value).startswith(str(path)) and "\n" not in str(exc.value)
    # the same from the command line: exit 2, one line naming the file
    from mcrecon.cli import main

    assert main(["reconstruct", str(path), "-o", str(tmp_path / "o.exr"), "--method", "nfor"]) == 2
    assert not (tmp_path / "o.exr").exists()


def test_statistics_without_samples_are_not_halves():
    st = PixelStats.from_source(sample_set())
    with pytest.raises(InputError, match="half-buffer pair"):
        mcrecon.reconstruct(st, method="nfor")
