"""Sample-space firefly handling (``fireflies="cascade"``) against the same method without it (issue 12, item 2).

For each scene, film size and spp, each seed's uniform samples are
reconstructed by every listed method twice -- on all the samples, and on
the base of :func:`mcrecon.filters.fireflies.split_fireflies` with the spread
excess added back -- and the mean relative MSE (eps 0.01) over the seeds is
printed as ratios measured in this run: ``m+c / m`` (below 1: the split
helps that method) and each to box.  Also printed: the share of the
luminance moved and the split's time as a ratio to box's reconstruction.

Run: ``python benchmarks/bench_fireflies.py [--configs 64x16 64x64 128x32 256x8] [--seeds 0 1 2]
[--scenes caustic hdr ...] [--methods box gem awr auto] [--k-min 4] [--mitsuba]``
(``--mitsuba`` adds the Cornell boxes of bench_defaults.py at 128 x 128, 32 spp.)
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np

import mcrecon
from mcrecon.filters.fireflies import split_fireflies
from mcrecon.core.metrics import relative_mse
from mcrecon.renderers import scenes


def run(scene_obj, size, spp, seeds, methods, k_min):
    ref = scene_obj.reference()
    rows, moved, t_split, t_box = {}, [], 0.0, 0.0
    for seed in seeds:
        pos, val = scene_obj.uniform(spp, seed)
        samples = mcrecon.SampleSet(pos, val, width=size, height=size)
        t0 = time.perf_counter()
        split = split_fireflies(pos, val, width=size, height=size, k_min=k_min)
        t_split += time.perf_counter() - t0
        base = mcrecon.SampleSet(pos, split.base_values, width=size, height=size)
        moved.append(split.moved_fraction)
        for m in methods:
            t0 = time.perf_counter()
            plain = mcrecon.reconstruct(samples, method=m)
            if m == "box":
                t_box += time.perf_counter() - t0
            rows.setdefault(m, []).append(relative_mse(plain, ref))
            rows.setdefault(m + "+c", []).append(relative_mse(mcrecon.reconstruct(base, method=m) + split.excess,
                                                              ref))
    return {k: float(np.mean(v)) for k, v in rows.items()}, float(np.mean(moved)), t_split / max(t_box, 1e-9)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--configs", nargs="+", default=["64x16", "64x64", "128x32", "256x8"], metavar="SIZExSPP")
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--scenes", nargs="+", default=scenes.scene_names())
    ap.add_argument("--methods", nargs="+", default=["box", "gem", "awr", "auto"])
    ap.add_argument("--k-min", type=int, default=4)
    ap.add_argument("--mitsuba", action="store_true")
    args = ap.parse_args(argv)
    from bench_defaults import BuiltinScene, MitsubaScene

    jobs = [(BuiltinScene(name, int(c.split("x")[0])), int(c.split("x")[0]), int(c.split("x")[1]))
            for name in args.scenes for c in args.configs]
    if args.mitsuba:
        jobs += [(MitsubaScene(n, 128, 1024, n == "cornell_small_light"), 128, 32)
                 for n in ("cornell", "cornell_small_light")]
    cols = [f"{m}+c/{m}" for m in args.methods]
    print("| scene | size | spp | box relMSE | " + " | ".join(cols) + " | best+c/box | moved | split time / box |")
    print("|---" * (len(cols) + 7) + "|")
    for sc, size, spp in jobs:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            r, moved, t_ratio = run(sc, size, spp, args.seeds, args.methods, args.k_min)
        best = min(r[m + "+c"] for m in args.methods) / r["box"]
        print(f"| {sc.name} | {size} | {spp} | {r['box']:.4g} | "
              + " | ".join(f"{r[m + '+c'] / r[m]:.3g}" for m in args.methods)
              + f" | {best:.3g} | {moved:.3g} | {t_ratio:.2g} |", flush=True)


if __name__ == "__main__":
    main()
