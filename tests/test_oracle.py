"""The selection ceiling (issue: trustworthy quality, item 1): analytic cases of the two oracles."""

import numpy as np

from mcrecon import PixelStats
from mcrecon.experiments.oracle import oracle_ceiling, run_oracle
from mcrecon.core.metrics import relative_mse


def test_noise_free_input_reaches_zero_with_the_pixel_filter():
    rng = np.random.default_rng(0)
    ref = rng.random((12, 14, 3)) * 5
    st = PixelStats.from_moments(ref, np.zeros_like(ref), 1)
    o = oracle_ceiling(st, ref, np.zeros_like(ref))
    assert o.per_pixel == 0.0 and o.ceiling == 0.0 and (o.choice == 0).all()
    assert o.best_global == 0.0 and o.best_global_sigma == 0.0


def test_flat_noise_goes_to_the_widest_scale():
    rng = np.random.default_rng(1)
    ref = np.full((40, 40, 3), 0.5)
    var = np.full_like(ref, 0.04)          # variance of each pixel mean
    mean = ref + rng.normal(0, 0.2, ref.shape)
    st = PixelStats.from_moments(mean, var * 4, 4)  # sample variance 0.16, 4 spp -> 0.04 per mean
    o = oracle_ceiling(st, ref, var)
    assert o.best_global_sigma == np.sqrt(2) ** 8          # no bias anywhere: the widest scale
    assert np.median(o.choice) == 8
    box = relative_mse(mean, ref)
    assert o.ceiling < 0.001 * box  # a 16 px Gaussian averages hundreds of pixels: measured 0.00086; 15 % margin


def test_ceiling_is_never_above_the_pixel_mean_and_run_oracle_reports_ratios():
    res = run_oracle("soft_shadow", spp=8, size=(24, 20), variance_spp=64, methods=["box", "gem"])
    box = res["methods"]["box"]
    assert box["to_box"] == 1.0 and res["ceiling"] <= box["relative_mse"]
    assert res["ceiling"] == min(res["oracle_per_pixel"], res["oracle_best_global"])
    gem = res["methods"]["gem"]
    assert gem["to_ceiling"] == gem["relative_mse"] / res["ceiling"]
