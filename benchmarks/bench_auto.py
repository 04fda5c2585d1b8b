"""Time of ``auto``'s offline reconstruction against ``gem`` and ``box`` (issue 12, item 5).

Synthetic samples (smooth blobs, hard edges and a thin bright line with
brightness-dependent noise, plus rare strong outliers) at ``--size``^2 and
``--spp`` samples per pixel are held in memory as a
:class:`mcrecon.SampleSet`; each repetition times
``mcrecon.reconstruct(samples, method=m)`` (statistics included) for box,
gem and auto, interleaved so that machine load hits every method alike.
Printed: median seconds per method and the ratios auto/gem and auto/box
measured in this run.

Run: ``python benchmarks/bench_auto.py [--size 1024] [--spp 32] [--reps 3] [--profile] [--features]``
(``--profile`` adds a breakdown of auto's stages in one extra run).
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np

import mcrecon
from mcrecon.methods import get_method


def synthetic_samples(size: int, spp: int, seed: int = 0, features: bool = False) -> mcrecon.SampleSet:
    """The samples; with ``features`` each also carries an albedo (a checkerboard of 8 px squares,
    which the colour is multiplied by), a normal and a depth, as a renderer's primary hit gives them."""
    rng = np.random.default_rng(seed)
    w = h = size
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32) + 0.5
    s = size / 128.0
    ref = (0.05 + np.exp(-((xx - 40 * s) ** 2 + (yy - 50 * s) ** 2) / (300.0 * s * s))
           + np.where(xx > 80 * s, 0.6, 0.0) + np.where(np.abs(yy - 100 * s) < 0.6 * s, 3.0, 0.0)).astype(np.float32)
    ref = ref[..., None] * np.array([1.0, 0.7, 0.4], np.float32)
    sigma = (0.3 * np.sqrt(ref) + 0.05).astype(np.float32)
    n = w * h * spp
    pix = np.repeat(np.arange(w * h, dtype=np.int64), spp)
    pos = np.empty((n, 2), np.float32)
    pos[:, 0] = (pix % w) + rng.random(n, dtype=np.float32) * np.float32(0.999)
    pos[:, 1] = (pix // w) + rng.random(n, dtype=np.float32) * np.float32(0.999)
    val = rng.standard_normal((n, 3), dtype=np.float32)
    hit = rng.random(n, dtype=np.float32) < 0.002
    val += hit[:, None] * np.float32(30.0)
    val *= sigma.reshape(-1, 3)[pix]
    val += ref.reshape(-1, 3)[pix]
    del pix
    if not features:
        return mcrecon.SampleSet(pos, val, width=w, height=h)
    sq = np.maximum(1.0, 8.0 * s)
    on = ((np.floor(pos[:, 0] / sq) + np.floor(pos[:, 1] / sq)) % 2).astype(np.float32)
    albedo = (0.2 + 0.6 * on)[:, None] * np.array([0.9, 0.8, 0.7], np.float32)
    val *= albedo
    normal = np.zeros((n, 3), np.float32)
    normal[:, 2] = 1.0
    depth = (1.0 + pos[:, 1:2] / h).astype(np.float32)
    return mcrecon.SampleSet(pos, val, width=w, height=h,
                             features={"albedo": albedo, "normal": normal, "depth": depth})


def _time(ss, m) -> float:
    t = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        mcrecon.reconstruct(ss, method=m)
    return time.perf_counter() - t


def profile(ss, m) -> None:
    """Stage times of one auto reconstruction (statistics, halves, candidates, selection)."""
    from mcrecon.core.halves import split_halves
    from mcrecon.methods.auto.estimates import sure_filter_bank
    from mcrecon.methods.auto.nlmeans import nlmeans_cross
    from mcrecon.methods.gem import final_sigmas
    from mcrecon.core.halves import merge_halves
    from mcrecon.core.fill import mean_variance_policy

    t = time.perf_counter()
    hv = split_halves(ss)  # the reader's one pass for auto: the halves, then their merge
    t1 = time.perf_counter()
    st = merge_halves(hv.a, hv.b)
    t2 = time.perf_counter()
    v = mean_variance_policy(st)
    sure_filter_bank(st.mean, v, st.count, final_sigmas(m.params["scales"]))
    t3 = time.perf_counter()
    va, vb = mean_variance_policy(hv.a), mean_variance_policy(hv.b)
    nlmeans_cross(hv.a.mean, va, hv.a.count, hv.b.mean, vb, hv.b.count, radius=m.params["nlm_radius"],
                  patch=m.params["nlm_patch"], k=m.params["nlm_k"])
    t4 = time.perf_counter()
    print(f"  halves (one pass over the samples) {t1 - t:.2f} s, their merge {t2 - t1:.2f} s, "
          f"SURE bank {t3 - t2:.2f} s, "
          f"NL-means {t4 - t3:.2f} s")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--spp", type=int, default=32)
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--profile", action="store_true")
    ap.add_argument("--features", action="store_true", help="samples with albedo, normal and depth (auto then "
                    "adds its feature-guided candidates; gem and box ignore the features)")
    a = ap.parse_args(argv)
    ss = synthetic_samples(a.size, a.spp, features=a.features)
    methods = {"box": get_method("box"), "gem": get_method("gem"), "auto": get_method("auto")}
    # compile every kernel once on a small image
    small = synthetic_samples(64, 4, seed=1, features=a.features)
    for m in methods.values():
        _time(small, m)
    times = {k: [] for k in methods}
    for r in range(a.reps):
        for k, m in methods.items():
            times[k].append(_time(ss, m))
        print(f"rep {r}: " + ", ".join(f"{k} {times[k][-1]:.2f} s" for k in methods), flush=True)
    med = {k: float(np.median(v)) for k, v in times.items()}
    print(f"{a.size}^2, {a.spp} spp, median of {a.reps}: " + ", ".join(f"{k} {med[k]:.2f} s" for k in med))
    print(f"auto / gem = {med['auto'] / med['gem']:.2f}, auto / box = {med['auto'] / med['box']:.2f}, "
          f"gem / box = {med['gem'] / med['box']:.2f}")
    if a.profile:
        profile(ss, methods["auto"])


if __name__ == "__main__":
    main()
