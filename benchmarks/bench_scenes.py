"""Throughput of the built-in scenes (mcrecon.renderers.scenes).

Run:  python benchmarks/bench_scenes.py [--samples N] [--size S]

Per scene it prints
* radiance(): samples per second on N random points (target >= 5 M/s),
* SceneRenderer.render() of a uniform S x S x spp request (jittered
  positions + random numbers + radiance), samples per second,
* reference_image(S, S, quadrature=32) wall time (target ~1 s at 128^2),
and, as the machine-independent figure, each rate's ratio to a baseline
measured in the same run: drawing the same random numbers with numpy
(``rng.random((N, n_dims))``), the least any renderer must do per sample.
Machines are shared and noisy: compare ratios, not seconds.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from mcrecon.renderers import scenes as S
from mcrecon.core.requests import SampleRequest


def best_of(fn, repeat=3):
    best = np.inf
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=2_000_000)
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--spp", type=int, default=64)
    args = ap.parse_args()
    n, size = args.samples, args.size
    rng = np.random.default_rng(0)
    x, y = rng.random(n), rng.random(n)
    # Warm up numba (compiled or loaded from the on-disk cache) outside the timings.
    for name in S.scene_names():
        sc = S.get_scene(name)
        sc.radiance(x[:4], y[:4], rng.random((4, sc.n_dims)))
        S.reference_image(name, 2, 2, quadrature=2)
    print(f"{'scene':15s} {'radiance M/s':>12s} {'/ baseline':>10s} {'render M/s':>10s} "
          f"{'/ baseline':>10s} {'reference s':>11s} {'>= 5 M/s':>9s}")
    for name in S.scene_names():
        sc = S.get_scene(name)
        u = rng.random((n, sc.n_dims))
        t_base = best_of(lambda: np.random.default_rng(1).random((n, sc.n_dims)))
        t_rad = best_of(lambda: sc.radiance(x, y, u))
        r = S.SceneRenderer(name, width=size, height=size)
        req = SampleRequest(size, size, counts=np.full((size, size), args.spp, np.int64))
        m = size * size * args.spp
        t_ren = best_of(lambda: r.render(req))
        t_base_ren = best_of(lambda: np.random.default_rng(1).random((m, 2 + sc.n_dims)))
        S._reference_cached.cache_clear()
        t_ref = best_of(lambda: (S._reference_cached.cache_clear(), S.reference_image(name, size, size)), 1)
        rate = n / t_rad / 1e6
        print(f"{name:15s} {rate:12.1f} {t_base / t_rad:10.2f} {m / t_ren / 1e6:10.1f} "
              f"{t_base_ren / t_ren:10.2f} {t_ref:11.2f} {'yes' if rate >= 5 else 'NO':>9s}")


if __name__ == "__main__":
    main()
