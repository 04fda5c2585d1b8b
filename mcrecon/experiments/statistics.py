"""Statistical experiments of Tamstorf & Jensen 1997 in report form.

* :func:`run_normality`: the chi-square normality test of the pixel
  estimates for several n (the paper: 10% -> 7% rejections for n = 10 -> 50),
  JSON numbers and a z map per n.
* :func:`run_bias`: bootstrap bias of the adaptive stopping rule over an
  image (from a log or a built-in scene), JSON numbers and maps.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Sequence

import numpy as np

from ..io import write_false_colour

__all__ = ["run_normality", "run_bias"]


def run_normality(renderer, *, n_values: Sequence[int] = (10, 20, 50), m: int = 100, seed: int = 0,
                  classes: int = 8, alpha: float = 0.05, out=None) -> dict:
    """Chi-square normality test for each n; writes normality.json and z-map PNGs into ``out``."""
    from ..methods.tamstorf import normality_experiment

    results = []
    for n in n_values:
        t0 = time.perf_counter()
        res = normality_experiment(renderer, n=int(n), m=int(m), seed=seed, classes=classes, alpha=alpha)
        entry = {"n": int(n), "seconds": time.perf_counter() - t0, **res.summary()}
        results.append(entry)
        if out is not None:
            Path(out).mkdir(parents=True, exist_ok=True)
            write_false_colour(Path(out) / f"normality_z_n{n}.png", res.z_map, vmin=0.0, vmax=3 * res.critical)
    report = {"renderer": str(getattr(renderer, "name", "renderer")), "width": renderer.width,
              "height": renderer.height, "m": m, "classes": classes, "alpha": alpha, "results": results}
    if out is not None:
        (Path(out) / "normality.json").write_text(json.dumps(report, indent=1))
        _plot_rates(results, Path(out) / "normality_rate.png")
    return report


def _plot_rates(results, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.5), dpi=100)
    ax.plot([r["n"] for r in results], [100 * r["rejection_rate"] for r in results], "o-", label="measured")
    ax.axhline(100 * results[0]["alpha"], color="k", ls="--", lw=1, label="nominal alpha")
    ax.set_xlabel("samples per estimate n")
    ax.set_ylabel("pixels rejected [%]")
    ax.legend()
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def run_bias(source, *, B: int = 1000, seed: int = 0, rule=None, level: float = 0.95,
             threshold: float = 1.0 / 256.0, out=None, nonfinite: str = "drop") -> dict:
    """Bootstrap bias of the stopping rule; ``source`` is a log path/SampleLog or a SampleBatch with a size.

    Writes bias.json (summary numbers) and one PNG per map into ``out``.
    """
    from ..methods.tamstorf import bootstrap_bias, bootstrap_bias_log

    t0 = time.perf_counter()
    if isinstance(source, dict):
        res = bootstrap_bias(source["positions"], source["values"], width=source["width"],
                             height=source["height"], B=B, seed=seed, rule=rule, level=level,
                             threshold=threshold, nonfinite=nonfinite)
    else:
        res = bootstrap_bias_log(source, B=B, seed=seed, rule=rule, level=level, threshold=threshold,
                                 nonfinite=nonfinite)
    summary = {"seconds": time.perf_counter() - t0, **res.summary()}
    if out is not None:
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "bias.json").write_text(json.dumps(summary, indent=1, default=float))
        for name, m in res.maps().items():
            write_false_colour(out / f"bias_{name}.png", m)
    return summary
