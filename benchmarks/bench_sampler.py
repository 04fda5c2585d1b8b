"""The built-in scenes' Owen-scrambled Sobol sampler against independent samples, and rounds against one render.

Per built-in scene and run seed, the relative MSE (eps 0.01) of the pixel
mean at ``--spp`` samples per pixel against the exact reference:

* ``independent``: one request of spp samples per pixel, independent samples;
* ``sobol``: the same with each pixel's Owen-scrambled Sobol sequence;
* ``sobol 4 x spp/4``: four requests of spp/4 per pixel, each continuing
  every pixel's sequence from the request's ``first_index`` (the adaptive
  driver's counts): the same points as one render, so the same error;
* ``sobol restarted``: the four requests without ``first_index`` (every
  round starts each pixel's sequence again: the error of spp/4 samples),
  what a renderer that ignores the index would give.

With ``--adaptive``, a second table: per scene and adaptive method (ci,
gem, awr, auto; box, splat and nfor sample uniformly), the relMSE of
``adapt`` with the method's defaults on the sobol sampler at ``--spp``
against the same method reconstructing a uniform sobol render of the same
budget (one request of spp per pixel): the ratio says what adaptive
placement gains (< 1) or loses (> 1) at equal samples with the same sampler.

Printed per scene: the sobol / independent ratio of the relMSE, mean and
standard deviation over the seeds (the seed-to-seed spread), and the two
round ratios against the one sobol render (means over the seeds).  The run
seed is the renderer's seed (another scramble of every pixel for sobol,
other random numbers for independent).

usage: python benchmarks/bench_sampler.py [--size 128x128] [--spp 32] [--seeds 4] [--scenes a,b]
                                          [--adaptive [--methods ci,gem,awr,auto]]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from mcrecon.core.metrics import relative_mse
from mcrecon.core.requests import SampleRequest
from mcrecon.renderers.scenes import SceneRenderer, reference_image, scene_names


def _pixel_mean(batches, w, h):
    """Pixel means of counted replies (each pixel's rows: ``pos`` floors to it)."""
    s = np.zeros((h * w, 3))
    n = np.zeros(h * w)
    for b in batches:
        p = np.floor(b.positions[:, 1]).astype(np.int64) * w + np.floor(b.positions[:, 0]).astype(np.int64)
        for c in range(3):
            s[:, c] += np.bincount(p, weights=b.values[:, c], minlength=h * w)
        n += np.bincount(p, minlength=h * w)
    return (s / n[:, None]).reshape(h, w, 3)


def _rounds(r, w, h, spp, k, *, continued):
    out, first = [], np.zeros((h, w), np.int64)
    per = spp // k
    for j in range(k):
        out.append(r.render(SampleRequest(w, h, counts=np.full((h, w), per), round_index=j, seed=j,
                                          first_index=first.copy() if continued else None)))
        first += per
    return out


def _adaptive_table(scenes, w, h, spp, seeds, methods) -> None:
    """relMSE of adapt (each method's defaults, sobol) over the method on uniform sobol samples."""
    from mcrecon import adapt, reconstruct
    from mcrecon.core.samples import SampleSet

    print(f"\nadaptive vs uniform, both sobol, {spp} spp, {seeds} seed(s): relMSE ratio adapt / uniform "
          "(the method reconstructing either), > 1: adaptive loses; in brackets adapt's relMSE")
    print(f"{'scene':<15} " + " ".join(f"{m:>22}" for m in methods))
    for name in scenes:
        ref = reference_image(name, w, h)
        cells = []
        for m in methods:
            ratios, errs = [], []
            for seed in range(seeds):
                r = SceneRenderer(name, width=w, height=h, seed=seed, sampler="sobol")
                b = r.render(SampleRequest(w, h, counts=np.full((h, w), spp)))
                uni = reconstruct(SampleSet(b.positions, b.values, width=w, height=h, features=b.features or None),
                                  method=m, reference=ref)
                res = adapt(SceneRenderer(name, width=w, height=h, seed=seed, sampler="sobol"), m, spp=spp,
                            seed=seed, reference=ref, track_error=False, progress=False)
                errs.append(relative_mse(res.image, ref))
                ratios.append(errs[-1] / relative_mse(uni, ref))
            cells.append(f"{np.mean(ratios):.3g}" + (f" ± {np.std(ratios, ddof=1):.2g}" if seeds > 1 else "")
                         + f" ({np.mean(errs):.2g})")
        print(f"{name:<15} " + " ".join(f"{c:>22}" for c in cells), flush=True)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="128x128")
    ap.add_argument("--spp", type=int, default=32)
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--scenes", default=None)
    ap.add_argument("--adaptive", action="store_true", help="also the adaptive-vs-uniform table")
    ap.add_argument("--adaptive-only", action="store_true", help="only the adaptive-vs-uniform table")
    ap.add_argument("--methods", default="ci,gem,awr,auto")
    args = ap.parse_args(argv)
    w, h = (int(v) for v in args.size.lower().split("x"))
    scenes = args.scenes.split(",") if args.scenes else scene_names()
    t0 = time.perf_counter()
    if args.adaptive_only:
        _adaptive_table(scenes, w, h, args.spp, args.seeds, args.methods.split(","))
        print(f"({time.perf_counter() - t0:.0f} s)")
        return
    print(f"{w}x{h}, {args.spp} spp, {args.seeds} seeds: relMSE (eps 0.01) of the pixel mean")
    print(f"{'scene':<15} {'indep relMSE':>12} {'sobol relMSE':>12} {'sobol/indep':>16} "
          f"{'4x' + str(args.spp // 4) + '/one':>9} {'restarted/one':>13}")
    for name in scenes:
        ref = reference_image(name, w, h)
        ind, sob, cont, rest = [], [], [], []
        for seed in range(args.seeds):
            counts = np.full((h, w), args.spp)
            ri = SceneRenderer(name, width=w, height=h, seed=seed)
            rs = SceneRenderer(name, width=w, height=h, seed=seed, sampler="sobol")
            ind.append(relative_mse(_pixel_mean([ri.render(SampleRequest(w, h, counts=counts))], w, h), ref))
            sob.append(relative_mse(_pixel_mean([rs.render(SampleRequest(w, h, counts=counts))], w, h), ref))
            cont.append(relative_mse(_pixel_mean(_rounds(rs, w, h, args.spp, 4, continued=True), w, h), ref))
            rest.append(relative_mse(_pixel_mean(_rounds(rs, w, h, args.spp, 4, continued=False), w, h), ref))
        ind, sob, cont, rest = map(np.array, (ind, sob, cont, rest))
        ratio = sob / ind
        spread = ratio.std(ddof=1) if len(ratio) > 1 else 0.0
        print(f"{name:<15} {ind.mean():12.3g} {sob.mean():12.3g} {ratio.mean():9.3g} ± {spread:<5.2g}"
              f" {np.mean(cont / sob):9.3f} {np.mean(rest / sob):13.3g}")
    if args.adaptive:
        _adaptive_table(scenes, w, h, args.spp, args.seeds, args.methods.split(","))
    print(f"({time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
