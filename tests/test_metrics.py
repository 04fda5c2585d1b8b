"""Metrics against hand-computed values, and the compare command that prints them."""

import json

import numpy as np
import pytest

from mcrecon import InputError
from mcrecon.core.metrics import (compare, flip, flip_available, mse, psnr, relative_mse, relative_mse_map, rmse,
    smape, ssim)
from mcrecon.io import write_exr, write_log

from helpers import run_cli


def test_relative_mse_by_hand():
    ref = np.array([[[1.0, 0.0]]])
    img = np.array([[[2.0, 0.1]]])
    # ((1)^2/(1+0.01) + (0.1)^2/(0+0.01)) / 2
    assert relative_mse(img, ref) == pytest.approx((1 / 1.01 + 1.0) / 2)
    assert relative_mse(img, ref, eps=1.0) == pytest.approx((1 / 2 + 0.01) / 2)
    assert relative_mse_map(img, ref).shape == (1, 1)


def test_mse_rmse_psnr():
    ref = np.zeros((2, 2, 3))
    img = np.full((2, 2, 3), 0.5)
    assert mse(img, ref) == 0.25 and rmse(img, ref) == 0.5
    assert psnr(img, ref, data_range=1.0) == pytest.approx(10 * np.log10(4))
    assert psnr(ref, ref, data_range=1.0) == np.inf
    with pytest.raises(InputError, match="data_range"):
        psnr(img, ref, data_range=0)


def test_ssim_identity_and_degradation(rng):
    ref = rng.random((32, 32, 3))
    assert ssim(ref, ref) == pytest.approx(1.0)
    assert ssim(ref + rng.normal(0, 0.2, ref.shape), ref) < 0.9
    assert np.isfinite(ssim(np.ones((1, 1, 3)), np.ones((1, 1, 3))))


def test_shape_mismatch_and_nonfinite_reference():
    with pytest.raises(InputError, match="differ"):
        relative_mse(np.zeros((2, 2, 3)), np.zeros((2, 3, 3)))
    with pytest.raises(InputError, match="non-finite"):
        relative_mse(np.zeros((1, 1, 1)), np.full((1, 1, 1), np.nan))


def test_compare_is_finite_on_hdr(rng):
    ref = np.where(rng.random((16, 16, 3)) < 0.1, 500.0, 1e-3)
    out = compare(ref * 1.01, ref)
    assert all(np.isfinite(v) for v in out.values() if isinstance(v, float))


def test_smape_by_hand():
    ref = np.array([[[1.0, 0.0]]])
    img = np.array([[[3.0, 0.0]]])
    # channel 0: |3 - 1| / (3 + 1 + 0.01); channel 1: 0 / (0 + 0 + 0.01) = 0
    assert smape(img, ref) == pytest.approx((2 / 4.01 + 0.0) / 2)
    assert smape(img, ref, eps=1.0) == pytest.approx((2 / 5 + 0.0) / 2)
    # sign-symmetric: |-1 - 1| / (1 + 1 + eps)
    assert smape(-np.ones((2, 2, 1)), np.ones((2, 2, 1))) == pytest.approx(2 / 2.01)


def test_smape_of_identical_images_is_zero(rng):
    ref = rng.random((8, 8, 3)) * 100
    assert smape(ref, ref) == 0.0
    with pytest.raises(InputError, match="eps"):
        smape(ref, ref, eps=0.0)


needs_flip = pytest.mark.skipif(not flip_available(), reason="flip-evaluator not installed (pip install flip-evaluator)")


@needs_flip
@pytest.mark.parametrize("hdr", [True, False])
def test_flip_zero_for_identical_and_positive_for_different(rng, hdr):
    ref = rng.random((32, 32, 3)) * 4
    assert flip(ref, ref, hdr=hdr) == 0.0
    assert flip(ref.astype(np.float32), ref, hdr=hdr) == 0.0
    d = flip(ref + rng.normal(0, 0.5, ref.shape), ref, hdr=hdr)
    assert 0 < d <= 1
    grey = ref[..., :1]
    assert flip(grey, grey, hdr=hdr) == 0.0 and flip(grey * 2, grey, hdr=hdr) > 0


def test_flip_without_flip_evaluator_says_how_to_install(monkeypatch, rng):
    import sys

    monkeypatch.setitem(sys.modules, "flip_evaluator", None)  # import raises ImportError
    ref = rng.random((8, 8, 3))
    with pytest.raises(InputError, match="pip install flip-evaluator"):
        flip(ref, ref)
    out = compare(ref, ref)
    assert "flip" not in out and "pip install flip-evaluator" in out["notes"][0]


def _compare_json(tmp_path, capsys, *extra):
    rng = np.random.default_rng(3)
    ref = (rng.random((16, 16, 3)) * 2).astype(np.float32)
    write_exr(tmp_path / "ref.exr", ref)
    write_exr(tmp_path / "img.exr", ref * 1.1)
    code, out, err = run_cli(["compare", tmp_path / "img.exr", tmp_path / "ref.exr", *extra], capsys)
    assert code == 0, err
    return out, ref


def test_compare_json_fields(tmp_path, capsys):
    text, ref = _compare_json(tmp_path, capsys, "--json", "--eps", "0.001", "--smape-eps", "0.1")
    m = json.loads(text)
    assert m["relative_mse_eps"] == 0.001 and m["smape_eps"] == 0.1
    assert m["relative_mse"] == pytest.approx(relative_mse(ref * 1.1, ref, eps=0.001), rel=1e-5)
    assert m["smape"] == pytest.approx(smape(ref * 1.1, ref, eps=0.1), rel=1e-5)
    assert m["one_minus_ssim"] == pytest.approx(1 - m["ssim"]) and 0 < m["one_minus_ssim"] < 1
    if flip_available():
        assert m["flip_mode"] == "hdr" and 0 < m["flip"] < 1
    else:
        assert "flip" not in m and "pip install flip-evaluator" in m["notes"][0]


@needs_flip
def test_compare_ldr_flip_and_text_output(tmp_path, capsys):
    m = json.loads(_compare_json(tmp_path, capsys, "--json", "--ldr-flip")[0])
    assert m["flip_mode"] == "ldr" and 0 < m["flip"] < 1
    text = _compare_json(tmp_path, capsys)[0]
    assert "relMSE (eps=0.01)" in text and "SMAPE (eps=0.01)" in text and "1-SSIM" in text and "HDR-FLIP" in text
    m = json.loads(_compare_json(tmp_path, capsys, "--json", "--no-flip")[0])
    assert "flip" not in m and "notes" not in m


def test_compare_takes_the_reference_stored_in_a_sample_log(tmp_path, capsys):
    rng = np.random.default_rng(1)
    ref = rng.random((6, 8, 3)).astype(np.float32).astype(np.float64)
    log = write_log(tmp_path / "l.h5", rng.random((40, 2)) * [8, 6], rng.random((40, 3)), width=8, height=6,
                    reference=ref)
    img = ref + 0.01
    a = write_exr(tmp_path / "a.exr", img)
    r = write_exr(tmp_path / "r.exr", ref)
    code, out, err = run_cli(["compare", a, log, "--json", "--no-flip"], capsys)
    assert code == 0, err
    code2, out2, _ = run_cli(["compare", a, r, "--json", "--no-flip"], capsys)
    assert json.loads(out) == json.loads(out2)
    bare = write_log(tmp_path / "bare.h5", rng.random((40, 2)) * [8, 6], rng.random((40, 3)), width=8, height=6)
    code, out, err = run_cli(["compare", a, bare], capsys)
    assert code == 2 and err.count("\n") == 1, err
    assert str(bare) in err and "no reference" in err and "render-log" in err, err
