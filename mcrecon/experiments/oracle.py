"""A ceiling to measure selection against: what choosing among Gaussian scales could reach.

For a scene with an exact reference, two oracles over the same filter
family GEM selects from (the pixel filter and the final Gaussian scales,
with GEM's pixel kernels and masking):

*per-pixel expected-error choice*
    at each pixel, the scale with the lowest *expected* relative MSE
    ``(bias_k^2 + Var_k) / (ref^2 + eps)``, bias from the reference
    (``K_k * ref - ref``) and variance propagated from a per-pixel
    variance of the mean measured at high spp on independent samples; it
    does not look at the noise of the image it filters.
*best single global scale*
    the one scale whose image has the lowest actual relative MSE.

The *ceiling* is the lower relative MSE of the two.  A method's result
divided by the ceiling says how far it is from what selection among these
filters could reach (below 1 is possible with richer filters).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..core.metrics import relative_mse
from ..methods.gem.kernels import filter_bank
from ..filters.gaussian import final_sigmas
from ..core.stats import PixelStats

__all__ = ["OracleResult", "oracle_ceiling", "run_oracle"]


@dataclasses.dataclass(eq=False)
class OracleResult:
    """Relative MSE of the oracles (eps as given) and their images.

    Attributes
    ----------
    per_pixel, best_global, ceiling : float
    best_global_sigma : float
        Gaussian sigma (pixels) of the best single scale; 0 is the pixel filter.
    per_pixel_image, best_global_image : ndarray (H, W, C)
    choice : ndarray (H, W) int
        Per-pixel chosen scale index (0: the pixel filter).
    """

    per_pixel: float
    best_global: float
    best_global_sigma: float
    per_pixel_image: np.ndarray
    best_global_image: np.ndarray
    choice: np.ndarray

    @property
    def ceiling(self) -> float:
        return min(self.per_pixel, self.best_global)


def oracle_ceiling(stats: PixelStats, reference: np.ndarray, mean_variance: np.ndarray, *,
                   sigmas=None, eps: float = 0.01) -> OracleResult:
    """The two oracles on ``stats`` (see the module docstring).

    Parameters
    ----------
    stats : PixelStats
        The samples to filter (their pixel means).
    reference : ndarray (H, W, C)
    mean_variance : ndarray (H, W, C)
        Variance of each pixel mean (true or measured independently at high spp).
    sigmas : sequence of float, optional
        Gaussian scales (default GEM's final ones, ``final_sigmas(8)``).
    eps : float
        Relative MSE epsilon.
    """
    sig = final_sigmas(8) if sigmas is None else np.asarray(sigmas, dtype=np.float64)
    ref = np.asarray(reference, dtype=np.float64)
    mv = np.asarray(mean_variance, dtype=np.float64)
    count = stats.count
    bank = filter_bank(stats.mean, mv, count, sig)
    # The same filters on the reference (masked like the data): their bias.
    rbank = filter_bank(ref, np.zeros_like(mv), count, sig)
    den = ref * ref + eps
    expected = np.stack([((rbank.values[k] - ref) ** 2 + bank.var[k]) / den for k in range(bank.n_scales)])
    choice = np.argmin(expected.mean(axis=3), axis=0)
    values = np.stack(bank.values)
    per_pixel_img = np.take_along_axis(values, choice[None, ..., None], axis=0)[0]
    errs = [relative_mse(values[k], ref, eps=eps) for k in range(bank.n_scales)]
    k_best = int(np.argmin(errs))
    sigmas_all = np.concatenate([[0.0], sig])
    return OracleResult(per_pixel=relative_mse(per_pixel_img, ref, eps=eps), best_global=float(errs[k_best]),
                        best_global_sigma=float(sigmas_all[k_best]), per_pixel_image=per_pixel_img,
                        best_global_image=values[k_best], choice=choice)


def run_oracle(scene, *, spp: int, size=(128, 128), seed: int = 0, variance_spp: int = 256,
               methods=None, eps: float = 0.01) -> dict:
    """The ceiling on a built-in scene and every method's default beside it.

    The per-pixel variance of the mean comes from an independent render at
    ``variance_spp`` (seed + 1000), scaled to ``spp``.  Returns a JSON-ready
    dict: the oracles, and per method its relative MSE, ratio to the pixel
    mean (box) and ratio to the ceiling.
    """
    import warnings

    from ..errors import McreconWarning
    from ..methods import available_methods, get_method
    from ..offline.reconstruction import reconstruct
    from ..renderers.scenes import get_scene, reference_image, render_uniform

    sc = get_scene(scene)
    w, h = size
    ref = reference_image(sc, w, h)
    b = render_uniform(sc, width=w, height=h, spp=spp, seed=seed)
    stats = PixelStats.from_samples(b.positions, b.values, width=w, height=h, channels=sc.channels)
    hi = render_uniform(sc, width=w, height=h, spp=variance_spp, seed=seed + 1000)
    hstats = PixelStats.from_samples(hi.positions, hi.values, width=w, height=h, channels=sc.channels)
    mean_var = hstats.sample_variance(undefined=0.0) / np.maximum(stats.count, 1)[..., None]
    orc = oracle_ceiling(stats, ref, mean_var, eps=eps)
    out = {"scene": sc.name, "size": [w, h], "spp": spp, "seed": seed, "variance_spp": variance_spp, "eps": eps,
           "oracle_per_pixel": orc.per_pixel, "oracle_best_global": orc.best_global,
           "oracle_best_global_sigma": orc.best_global_sigma, "ceiling": orc.ceiling, "methods": {}}
    names = [m for m in (methods or available_methods())]
    box = None
    for name in ["box"] + [m for m in names if m != "box"]:
        m = get_method(name)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", McreconWarning)
            inputs = stats if not m.requires.samples and not m.requires.subpixels else None
            if inputs is None:
                from ..core.samples import SampleSet
                inputs = SampleSet(b.positions, b.values, width=w, height=h, channels=sc.channels)
            img = reconstruct(inputs, method=m)
        err = relative_mse(img, ref, eps=eps)
        box = err if name == "box" else box
        out["methods"][name] = {"relative_mse": err, "to_box": err / box, "to_ceiling": err / orc.ceiling}
    return out
