"""Statistical experiments of Tamstorf & Jensen 1997 in report form.

* :func:`run_normality`: the chi-square normality test of the pixel
  estimates for several n (the paper: 10% rejections at n = 10, 7% at n = 50),
  JSON numbers and a z map per n.
* :func:`run_bias`: bootstrap bias of the adaptive stopping rule over an
  image (from a log or a built-in scene), JSON numbers and maps.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Sequence


from ..io import write_false_colour

__all__ = ["run_normality", "run_bias"]


def run_normality(renderer, *, n_values: Sequence[int] = (10, 20, 50), m: int = 100, seed: int = 0,
                  classes: int = 8, alpha: float = 0.05, out=None) -> dict:
    """Chi-square normality test for each n; writes normality.json and z-map PNGs into ``out``."""
    from ..methods.ci.analysis import normality_experiment

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
        md = ["# Chi-square normality test (Tamstorf & Jensen 1997, Sec. 3 and 5.1)", "",
              f"{report['renderer']}, {renderer.width}x{renderer.height}; m = {m} independent estimates of n "
              f"samples per pixel, {classes} equiprobable classes of N(mu, s^2), rejected when z exceeds the "
              f"chi2({classes - 3}) {100 * (1 - alpha):g}% quantile. Under normality about 5-6% of pixels are "
              "rejected (Chernoff-Lehmann: the estimated parameters make the 5% test reject ~6%); the paper "
              "found 10% at n = 10 falling to 7% at n = 50 on a Cornell box.", "",
              "![rejection rate](normality_rate.png)", "",
              "| n | rejected | tests | untestable | mean z | critical | z map |", "|---:|---:|---:|---:|---:|---:|---|"]
        for r in results:
            md.append(f"| {r['n']} | {100 * r['rejection_rate']:.1f}% | {r['tests']} | {r['untestable']} | "
                      f"{r['mean_z']:.2f} | {r['critical']:.2f} | ![](normality_z_n{r['n']}.png) |")
        (Path(out) / "report.md").write_text("\n".join(md) + "\n")
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
    from ..methods.ci.analysis import bootstrap_bias, bootstrap_bias_log

    t0 = time.perf_counter()
    if isinstance(source, dict):
        res = bootstrap_bias(source["positions"], source["values"], width=source["width"],
                             height=source["height"], B=B, seed=seed, rule=rule, level=level,
                             threshold=threshold, nonfinite=nonfinite)
    else:
        from ..io import read_log
        res = bootstrap_bias_log(read_log(source) if not hasattr(source, "iter_chunks") else source, B=B, seed=seed, rule=rule, level=level, threshold=threshold,
                                 nonfinite=nonfinite)
    summary = {"seconds": time.perf_counter() - t0, **res.summary()}
    if out is not None:
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "bias.json").write_text(json.dumps(summary, indent=1, default=float))
        maps = res.maps()
        for name, m in maps.items():
            write_false_colour(out / f"bias_{name}.png", m)
        md = ["# Bootstrap bias of the adaptive stopping rule (Tamstorf & Jensen 1997, Sec. 4)", "",
              f"B = {B} resamples per pixel from each pixel's empirical distribution; the stopping rule "
              f"({json.dumps(summary.get('rule', {}), default=float)}) is rerun on each; "
              f"{100 * level:g}% intervals; threshold {threshold:.6g}. {summary['seconds']:.1f} s.", "",
              "| quantity | value |", "|---|---|"]
        for k, v in summary.items():
            if isinstance(v, (int, float)) and not isinstance(v, bool):
                md.append(f"| {k} | {v:.6g} |")
            elif isinstance(v, dict) and k != "rule":
                for k2, v2 in v.items():
                    if isinstance(v2, (int, float)):
                        md.append(f"| {k}.{k2} | {v2:.6g} |")
        md += ["", "| map | picture |", "|---|---|"] + [f"| {n} | ![](bias_{n}.png) |" for n in maps]
        (out / "report.md").write_text("\n".join(md) + "\n")
    return summary
