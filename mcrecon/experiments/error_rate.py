"""GEM's empirical analysis of the scale selector on a constant signal (Rousselle et al. 2011, §4.3).

Writes ``error_rate.json`` and four figures:

* ``fig4_terms.png``: histograms of the bias term, the variance term and
  S (unweighted), as the paper's Fig. 4;
* ``fig5_variance_term.png``: the variance term's histogram over filter
  radii and sample counts |P| (Fig. 5);
* ``error_rate_vs_gamma.png``: measured error rate against the target
  gamma (with z(gamma) on a second axis);
* ``error_rate_vs_noise.png``: error rate against the noise variance for
  each gamma (it should stay flat).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Sequence

import numpy as np

__all__ = ["run_error_rate"]


def run_error_rate(out=None, *, gammas: Sequence[float] = (0.05, 0.1, 0.15, 0.2, 0.25, 0.3, 0.35),
                   noise_vars: Sequence[float] = (0.1, 1.0, 10.0, 100.0, 1000.0),
                   radii: Sequence[float] = (1.0, 2.0, 4.0), spp_list: Sequence[int] = (4, 8, 16, 32, 64),
                   n_pixels: int = 200_000, spp: int = 32, seed: int = 0) -> dict:
    from ..methods.gem.experiment import error_rate_experiment
    from ..methods.gem.selection import z_of_gamma

    vs_gamma = []
    for g in gammas:
        r = error_rate_experiment(g, 10.0, n_pixels=n_pixels, spp=spp, seed=seed)
        vs_gamma.append({"gamma": g, "z": float(z_of_gamma(g)), "error_rate": r["error_rate"]})
    vs_noise = []
    for g in (0.1, 0.2, 0.3):
        for nv in noise_vars:
            r = error_rate_experiment(g, nv, n_pixels=n_pixels, spp=spp, seed=seed + 1)
            vs_noise.append({"gamma": g, "noise_var": nv, "error_rate": r["error_rate"]})
    unweighted = error_rate_experiment(None, 10.0, n_pixels=n_pixels, spp=spp, seed=seed + 2)
    var_terms = {}
    for rad in radii:
        for n in spp_list:
            r = error_rate_experiment(0.2, 10.0, n_pixels=max(n_pixels // 4, 1000), spp=n, radius=rad, seed=seed + 3)
            var_terms[(rad, n)] = r["variance"]
    report = {"n_pixels": n_pixels, "spp": spp, "error_rate_vs_gamma": vs_gamma, "error_rate_vs_noise": vs_noise,
              "unweighted_error_rate": unweighted["error_rate"],
              "variance_term_median": [{"radius": k[0], "spp": k[1], "median": float(np.median(v))}
                                       for k, v in var_terms.items()]}
    if out is not None:
        _write(Path(out), report, unweighted, var_terms)
    return report


def _write(out: Path, report, unweighted, var_terms):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    (out / "error_rate.json").write_text(json.dumps(report, indent=1))
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.5), dpi=90)
    for ax, key, title in zip(axes, ("bias", "variance", "S"), ("bias term", "variance term", "S (unweighted)")):
        x = unweighted[key]
        lo, hi = np.percentile(x, [0.5, 99.5])
        ax.hist(x, bins=200, range=(lo, hi), color="C0")
        ax.axvline(0, color="k", lw=1)
        ax.set_title(title)
    fig.suptitle("Fig. 4: constant signal with noise")
    fig.tight_layout()
    fig.savefig(out / "fig4_terms.png")
    plt.close(fig)
    radii = sorted({k[0] for k in var_terms})
    spps = sorted({k[1] for k in var_terms})
    fig, axes = plt.subplots(1, len(radii), figsize=(4 * len(radii), 3.5), dpi=90, squeeze=False)
    for ax, rad in zip(axes[0], radii):
        for n in spps:
            v = var_terms[(rad, n)]
            ax.hist(v / np.median(v), bins=100, range=(0, 3), histtype="step", label=f"|P| = {n}")
        ax.set_title(f"variance term / median, radius {rad:g}")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "fig5_variance_term.png")
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(5, 4), dpi=90)
    g = [r["gamma"] for r in report["error_rate_vs_gamma"]]
    ax.plot(g, [r["error_rate"] for r in report["error_rate_vs_gamma"]], "o-", label="measured")
    ax.plot(g, g, "k--", lw=1, label="target")
    ax.set_xlabel("gamma")
    ax.set_ylabel("error rate")
    ax2 = ax.twinx()
    ax2.plot(g, [r["z"] for r in report["error_rate_vs_gamma"]], "s:", color="C2")
    ax2.set_ylabel("z(gamma)", color="C2")
    ax.legend(loc="upper left")
    fig.tight_layout()
    fig.savefig(out / "error_rate_vs_gamma.png")
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(5, 4), dpi=90)
    for gam in sorted({r["gamma"] for r in report["error_rate_vs_noise"]}):
        pts = [(r["noise_var"], r["error_rate"]) for r in report["error_rate_vs_noise"] if r["gamma"] == gam]
        ax.semilogx([p[0] for p in pts], [p[1] for p in pts], "o-", label=f"gamma {gam}")
        ax.axhline(gam, color="k", lw=0.5, ls="--")
    ax.set_xlabel("noise variance")
    ax.set_ylabel("error rate")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "error_rate_vs_noise.png")
    plt.close(fig)
