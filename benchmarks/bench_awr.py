"""Benchmark of ``awr`` (Overbeck et al. 2009): ratios against baselines measured in the same run.

1. Reconstruction of a 1024x1024 RGB image (variance image + Eq. 10 + Eq. 11
   + synthesis) against OIDN ``pyoidn.denoise(color, hdr=True,
   quality="high")`` on the same pixel means.  Target: ratio <= 1 (the
   paper: < 1 s).
2. Toolkit share of the adaptive loop (``mcrecon.adaptive.run.adapt``) with a
   renderer of ~2 M samples/s (a built-in scene padded with sleep to that
   rate).  Target <= 15 % (the paper: 34.5 s of 211 s = 16 %).  Also
   prints the time of one full priority update and the share of the image
   a local update would have had to recompute (``affected_fraction``): a
   full update per batch is justified when that share is large.
3. ``--limits``: the paper's AWR (``variant="paper"``) and the robust
   default side by side, each as a ratio to box measured in the same run
   (relative MSE, eps 0.01; defaults 128x128, 32 spp, seed 1), offline on
   uniform samples and adaptive at equal spp, on every built-in scene and
   Mitsuba's Cornell box (when the bridge is available), with the number
   of negative pixels each produces.  docs/methods/awr.md "Default vs
   paper" quotes it.

Usage: ``python benchmarks/bench_awr.py [--size 1024] [--spp 32] [--round-spp 2 4 8] [--skip-oidn]``
       ``python benchmarks/bench_awr.py --limits [--size 128] [--spp 32] [--seeds 1 2] [--no-cornell]``
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from mcrecon.adaptive.run import adapt
from mcrecon.methods import get_method
from mcrecon.methods.base import MethodInputs
from mcrecon.methods.awr import AWRMethod, plan_awr_positions
from mcrecon.core.metrics import relative_mse
from mcrecon.renderers.scenes import SceneRenderer, reference_image, render_uniform
from mcrecon.core.stats import PixelStats


def best_of(fn, repeat=3):
    times = []
    out = None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return min(times), out


class PacedRenderer:
    """A scene renderer slowed down to ``rate`` samples per second."""

    def __init__(self, scene, size, rate, seed=0):
        self.inner = SceneRenderer(scene, width=size, height=size, seed=seed)
        self.width = self.height = size
        self.channels = self.inner.channels
        self.rate = rate
        self.name = f"paced:{scene}"

    def render(self, request):
        t = time.perf_counter()
        out = self.inner.render(request)
        wait = request.total / self.rate - (time.perf_counter() - t)
        if wait > 0:
            time.sleep(wait)
        return out


def bench_reconstruction(size, skip_oidn):
    batch = render_uniform("depth_of_field", width=size, height=size, spp=8, seed=1)
    stats = PixelStats.from_samples(batch.positions, batch.values, width=size, height=size)
    print(f"== reconstruction {size}x{size} RGB (depth_of_field, 8 spp) ==")
    res = {}
    for wavelet in ("cdf97", "legall53", "haar"):
        m = AWRMethod(variant="paper", wavelet=wavelet)
        m.reconstruct(MethodInputs(stats))                       # warm caches (analysis matrices)
        res[wavelet], _ = best_of(lambda: m.reconstruct(MethodInputs(stats)))
        print(f"awr {wavelet:9s} {res[wavelet]:7.3f} s")
    m = AWRMethod(variant="paper", propagation="cascade")
    t_cas, _ = best_of(lambda: m.reconstruct(MethodInputs(stats)))
    print(f"awr cdf97 (paper's cascade propagation) {t_cas:7.3f} s")
    m = AWRMethod()
    m.reconstruct(MethodInputs(stats))
    t_rob, _ = best_of(lambda: m.reconstruct(MethodInputs(stats)))
    print(f"awr cdf97 robust default (log domain + safeguard) {t_rob:7.3f} s")
    if not skip_oidn:
        import pyoidn
        color = np.ascontiguousarray(stats.mean, dtype=np.float32)
        pyoidn.denoise(color, hdr=True, quality="high")
        t_oidn, _ = best_of(lambda: pyoidn.denoise(color, hdr=True, quality="high"), repeat=2)
        print(f"oidn high      {t_oidn:7.3f} s")
        print(f"ratio awr(cdf97)/oidn = {res['cdf97'] / t_oidn:.3f}   (target <= 1)")


def bench_adaptive(size, spp, rate, round_spp):
    print(f"== adaptive loop {size}x{size}, {spp} spp, round_spp {round_spp}, renderer paced to {rate / 1e6:.1f} M samples/s ==")
    infos, plan_times = [], []

    class TimedAWR(AWRMethod):
        def plan(self, run, state):
            t = time.perf_counter()
            req = super().plan(run, state)
            plan_times.append(time.perf_counter() - t)
            if state.n_samples:
                infos.append(dict(run.last_plan_info))
            return req

    method = TimedAWR(variant="paper", round_spp=round_spp)
    renderer = PacedRenderer("depth_of_field", size, rate, seed=3)
    t = time.perf_counter()
    res = adapt(renderer, method, spp=spp, seed=3, progress=False, track_error=False)
    wall = time.perf_counter() - t
    rs, ts = res.renderer_seconds, res.toolkit_seconds
    print(f"rounds {len(res.rounds)}, wall {wall:.2f} s, renderer {rs:.2f} s, toolkit {ts:.2f} s "
          f"(plan {sum(plan_times):.2f} s)")
    print(f"toolkit share = {ts / (rs + ts):.3f}   (target <= 0.15; paper 34.5/211 = 0.16)")
    frac = [i["affected_fraction"] for i in infos]
    if frac:
        print(f"affected fraction per round (what a local update recomputes): "
              f"median {np.median(frac):.2f}, min {np.min(frac):.2f}")
    # One full priority update (Eq. 5, 6, 8, 9) on the final statistics:
    t_full, _ = best_of(lambda: plan_awr_positions(res.stats, 1, np.random.default_rng(0)))
    print(f"one full priority update + 1 sample: {t_full:.3f} s; "
          f"renderer time per round at this rate: {round_spp * size * size / rate:.3f} s")


SCENES = ["soft_shadow", "depth_of_field", "motion_blur", "caustic", "hdr", "flat"]


def _cornell(size, seed):
    """(renderer factory, reference) of Mitsuba's Cornell box, or None when the bridge is unavailable."""
    try:
        from mcrecon.renderers.mitsuba import MitsubaRenderer, mitsuba_available, render_reference
    except ImportError:
        return None
    ok, _ = mitsuba_available()
    if not ok:
        return None
    ref = render_reference(None, width=size, height=size, spp=1024, seed=12345)
    return (lambda: MitsubaRenderer(None, width=size, height=size)), ref


def bench_limits(size, spp, seeds, cornell=True):
    """Paper vs robust AWR beside box of the same samples, as ratios measured in the same run.

    Offline rows reconstruct one set of uniform samples (box = their pixel
    means); adaptive rows run the full method (sampler + reconstruction)
    at the same budget and renderer seed against uniform box (the box
    method's own adaptive run: uniform doubling rounds).  Relative MSE,
    eps 0.01.  ``neg`` counts pixels below 0 from non-negative samples
    (``mcrecon.core.metrics.output_sanity``).  The Cornell box (Mitsuba, 1024 spp
    reference, seed 12345) is included when the bridge is available.
    """
    import warnings

    from mcrecon.core.metrics import output_sanity
    from mcrecon.core.requests import SampleRequest
    warnings.simplefilter("ignore")
    print(f"== paper vs robust awr, ratio of relative MSE (eps 0.01) to box, {size}x{size}, {spp} spp ==")
    print(f"{'seed':>4}  {'scene':<15} {'stage':<9} {'box':>9} {'paper/box':>10} {'robust/box':>11} "
          f"{'neg paper':>9} {'neg robust':>10}")
    cb = _cornell(size, 1) if cornell else None
    for seed in seeds:
        cases = [(sc, (lambda sc=sc: SceneRenderer(sc, width=size, height=size, seed=seed)),
                  reference_image(sc, size, size)) for sc in SCENES]
        if cb is not None:
            cases.append(("cornell", cb[0], cb[1]))
        for scene, make, ref in cases:
            r = make()
            b = r.render(SampleRequest(size, size, counts=np.full((size, size), spp, np.int64), round_index=0,
                                       seed=seed))
            st = PixelStats.from_samples(b.positions, b.values, width=size, height=size)
            box = relative_mse(st.mean, ref)
            out, neg = {}, {}
            for v in ("paper", "robust"):
                img = get_method("awr", variant=v).reconstruct(MethodInputs(st))
                out[v] = relative_mse(img, ref) / box
                neg[v] = output_sanity(img, st)["negative_pixels"]
            print(f"{seed:>4}  {scene:<15} {'offline':<9} {box:9.3g} {out['paper']:10.3g} {out['robust']:11.3g} "
                  f"{neg['paper']:9d} {neg['robust']:10d}", flush=True)
            ubox = relative_mse(adapt(make(), "box", spp=spp, seed=seed, progress=False, track_error=False).image, ref)
            for v in ("paper", "robust"):
                res = adapt(make(), get_method("awr", variant=v), spp=spp, seed=seed, progress=False,
                            track_error=False)
                out[v] = relative_mse(res.image, ref) / ubox
                neg[v] = output_sanity(res.image, res.stats)["negative_pixels"]
            print(f"{seed:>4}  {scene:<15} {'adaptive':<9} {ubox:9.3g} {out['paper']:10.3g} {out['robust']:11.3g} "
                  f"{neg['paper']:9d} {neg['robust']:10d}", flush=True)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=int, default=None, help="film side (default 1024; 128 with --limits)")
    ap.add_argument("--spp", type=int, default=32)
    ap.add_argument("--rate", type=float, default=2e6)
    ap.add_argument("--round-spp", type=float, nargs="+", default=[4.0])
    ap.add_argument("--skip-oidn", action="store_true")
    ap.add_argument("--skip-adaptive", action="store_true")
    ap.add_argument("--limits", action="store_true", help="print the measured-limits table instead")
    ap.add_argument("--seeds", type=int, nargs="+", default=[1], help="renderer seeds of the limits table")
    ap.add_argument("--no-cornell", action="store_true", help="leave Mitsuba's Cornell box out of --limits")
    a = ap.parse_args()
    if a.limits:
        bench_limits(a.size or 128, a.spp, a.seeds, cornell=not a.no_cornell)
        return
    a.size = a.size or 1024
    bench_reconstruction(a.size, a.skip_oidn)
    if not a.skip_adaptive:
        for r in a.round_spp:
            bench_adaptive(a.size, a.spp, a.rate, r)


if __name__ == "__main__":
    main()
