"""Metrics against hand-computed values."""

import numpy as np
import pytest

from mcrecon import InputError
from mcrecon.metrics import compare, mse, psnr, relative_mse, relative_mse_map, rmse, ssim


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
    assert all(np.isfinite(v) for v in out.values())
