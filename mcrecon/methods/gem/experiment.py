"""The empirical analysis of the scale selector on a constant signal (Rousselle et al. 2011, Sec. 4.3, Figs. 4-5).

:mod:`mcrecon.experiments.error_rate` runs it over gamma, noise variances,
radii and sample counts and draws the figures.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from ...errors import InputError
from ...filters.gaussian import gaussian_kernel
from .selection import check_gamma, scale_selector_terms, z_of_gamma

__all__ = ["error_rate_experiment"]


def error_rate_experiment(gamma: float | None, noise_var: float = 10.0, *, n_pixels: int = 1_000_000,
                          spp: int = 32, radius: float = 1.0, ratio: float = 2.0, seed: int = 0,
                          distribution: str = "normal") -> dict:
    """The paper's empirical analysis of S on a constant signal (Sec. 4.3).

    A 1-D signal of ``n_pixels`` pixels with value 0, ``spp`` samples per
    pixel of i.i.d. noise of variance ``noise_var``; fine and coarse
    Gaussians of sigma ``radius`` and ``ratio * radius`` applied to the
    pixel means (the samples carry no positions here, as in the paper);
    variances from the per-pixel sample variances (Eq. 3) through the
    squared kernels (Eq. 2).  The ideal decision is always "go coarser"
    (all biases are 0), so the error rate is the fraction of pixels with
    S > 0; the paper calibrates z(gamma) so that it is about gamma.

    Parameters
    ----------
    gamma : float or None
        None: unweighted S (Fig. 4).
    noise_var : float
        Variance of one sample.
    distribution : {'normal', 'uniform'}

    Returns
    -------
    dict
        ``bias``, ``variance``, ``S`` (arrays over the pixels, borders of
        4 * ratio * radius pixels dropped), ``error_rate`` (float),
        ``z``, ``rho`` and the parameters.
    """
    if gamma is not None:
        check_gamma(gamma, "error_rate_experiment")
    if not noise_var > 0:
        raise InputError("error_rate_experiment", "noise_var", f"got {noise_var!r}, expected > 0")
    if int(spp) < 2:
        raise InputError("error_rate_experiment", "spp", f"got {spp!r}, expected >= 2 (Eq. 3 needs two samples)")
    rng = np.random.default_rng(seed)
    n = int(n_pixels)
    if distribution == "normal":
        s = rng.normal(0.0, math.sqrt(noise_var), size=(n, int(spp)))
    elif distribution == "uniform":
        a = math.sqrt(3.0 * noise_var)
        s = rng.uniform(-a, a, size=(n, int(spp)))
    else:
        raise InputError("error_rate_experiment", "distribution", f"got {distribution!r}; valid: normal, uniform")
    mean = s.mean(axis=1)
    v = s.var(axis=1, ddof=1) / spp
    r_f, r_c = float(radius), float(ratio) * float(radius)
    kf, kc = gaussian_kernel(r_f), gaussian_kernel(r_c)
    f = ndimage.correlate1d(mean, kf, mode="wrap")
    c = ndimage.correlate1d(mean, kc, mode="wrap")
    vf = ndimage.correlate1d(v, kf * kf, mode="wrap")
    vc = ndimage.correlate1d(v, kc * kc, mode="wrap")
    cut = int(math.ceil(4 * r_c))
    sl = slice(cut, n - cut) if n > 2 * cut else slice(None)
    bias, variance, S = scale_selector_terms(f[sl], c[sl], vf[sl], vc[sl], r_f=r_f, r_c=r_c, n=spp, gamma=gamma)
    return {"bias": bias, "variance": variance, "S": S, "error_rate": float(np.mean(S > 0)),
            "z": None if gamma is None else z_of_gamma(gamma), "rho": 1.0 - 1.0 / spp,
            "gamma": gamma, "noise_var": float(noise_var), "spp": int(spp), "radius": r_f,
            "ratio": float(ratio), "n_pixels": n}
