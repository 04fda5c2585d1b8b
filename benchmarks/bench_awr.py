"""Benchmark of ``awr`` (Overbeck et al. 2009): ratios against baselines measured in the same run.

1. Reconstruction of a 1024x1024 RGB image (variance image + Eq. 10 + Eq. 11
   + synthesis) against OIDN ``pyoidn.denoise(color, hdr=True,
   quality="high")`` on the same pixel means.  Target: ratio <= 1 (the
   paper: < 1 s).
2. Toolkit share of the adaptive loop (``mcrecon.driver.adapt``) with a
   renderer of ~2 M samples/s (a built-in scene padded with sleep to that
   rate).  Target <= 15 % (the paper: 34.5 s of 211 s = 16 %).  Also
   prints the time of one full priority update and the share of the image
   a local update would have had to recompute (``affected_fraction``): a
   full update per batch is justified when that share is large.
3. ``--limits``: the measured limits, i.e. the cases where the paper's AWR
   loses to the pixel mean (box) of the same samples, each beside that
   baseline as a ratio measured in the same run (relative MSE, eps 0.01;
   defaults 128x128, 32 spp, seed 1).  These were strict xfails in the
   tests; a table cannot fail when the method gets better.

Usage: ``python benchmarks/bench_awr.py [--size 1024] [--spp 32] [--round-spp 2 4 8] [--skip-oidn]``
       ``python benchmarks/bench_awr.py --limits [--size 128] [--spp 32] [--seeds 1 2]``
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from mcrecon.driver import adapt
from mcrecon.methods import get_method
from mcrecon.methods.awr import AWRMethod, plan_awr_positions
from mcrecon.metrics import relative_mse
from mcrecon.renderers.scenes import SceneRenderer, reference_image, render_uniform
from mcrecon.stats import PixelStats


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
        m = AWRMethod(wavelet=wavelet)
        m.reconstruct(stats)                       # warm caches (analysis matrices)
        res[wavelet], _ = best_of(lambda: m.reconstruct(stats))
        print(f"awr {wavelet:9s} {res[wavelet]:7.3f} s")
    m = AWRMethod(propagation="cascade")
    t_cas, _ = best_of(lambda: m.reconstruct(stats))
    print(f"awr cdf97 (paper's cascade propagation) {t_cas:7.3f} s")
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

    method = TimedAWR(round_spp=round_spp)
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


#: The measured limits: (stage, scene, variance estimator) where the paper's AWR
#: loses to or ties with box at 128x128, 32 spp (formerly strict xfails in tests/test_awr.py).
LIMITS = [("offline", "soft_shadow", "range"), ("offline", "caustic", "range"), ("offline", "caustic", "sample"),
          ("offline", "hdr", "range"), ("offline", "hdr", "sample"),
          ("adaptive", "depth_of_field", "range"), ("adaptive", "hdr", "range"),
          ("adaptive", "soft_shadow", "range")]  # a tie (0.90-1.00x), within the sampler's rounding sensitivity


def bench_limits(size, spp, seeds):
    """Relative MSE of each limit case beside box (the pixel mean of uniform samples), same run.

    Offline rows reconstruct the uniform samples themselves; adaptive rows
    run the full method (AWR sampling + reconstruction, paper defaults)
    with the same renderer seed and budget, no log.  The depth_of_field
    row also gives offline AWR, the baseline the adaptive sampler loses to.
    """
    print(f"== measured limits: relative MSE (eps 0.01), {size}x{size}, {spp} spp ==")
    print(f"{'seed':>4}  {'case':<40} {'awr':>9} {'box':>9} {'awr/box':>8}")
    for seed in seeds:
        cache = {}

        def uniform(scene):
            if scene not in cache:
                b = render_uniform(scene, width=size, height=size, spp=spp, seed=seed)
                st = PixelStats.from_samples(b.positions, b.values, width=size, height=size)
                ref = reference_image(scene, size, size)
                cache[scene] = st, ref, relative_mse(get_method("box").reconstruct(st), ref)
            return cache[scene]

        for stage, scene, variance in LIMITS:
            st, ref, box = uniform(scene)
            note = ""
            if stage == "offline":
                err = relative_mse(get_method("awr", variance=variance).reconstruct(st), ref)
                case = f"offline awr ({variance}), {scene}"
            else:
                res = adapt(SceneRenderer(scene, width=size, height=size, seed=seed), get_method("awr"), spp=spp,
                            seed=seed, progress=False, track_error=False)
                err = relative_mse(res.image, ref)
                case = f"adaptive awr, {scene}"
                if scene == "depth_of_field":
                    off = relative_mse(get_method("awr").reconstruct(st), ref)
                    note = f"   offline awr {off:.3g}: adaptive/offline {err / off:.2f}"
            print(f"{seed:>4}  {case:<40} {err:9.3g} {box:9.3g} {err / box:8.3g}{note}")


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
    a = ap.parse_args()
    if a.limits:
        bench_limits(a.size or 128, a.spp, a.seeds)
        return
    a.size = a.size or 1024
    bench_reconstruction(a.size, a.skip_oidn)
    if not a.skip_adaptive:
        for r in a.round_spp:
            bench_adaptive(a.size, a.spp, a.rate, r)


if __name__ == "__main__":
    main()
