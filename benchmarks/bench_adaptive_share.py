"""Toolkit share of an adaptive run's wall time, per adaptive method.

The renderer is a built-in scene throttled to a fixed throughput (default
2 M samples/s, the Mitsuba bridge's rate on the Cornell box here): its
time per round is max(real time, samples / rate).  The driver splits each
round into renderer and toolkit time; the share printed is toolkit /
(renderer + toolkit) over the whole run, with the per-round maximum.
Targets: GEM <= 5% (paper 4.36%), AWR <= 15% (paper 34.5 s of 211 s).

With ``--renderer mitsuba`` the renderer is the Mitsuba 3 bridge on its
Cornell box (issue 7's benchmark): no throttling, its own render time.

usage: python benchmarks/bench_adaptive_share.py [--size 512x512] [--spp 32] [--rate 2e6]
       [--methods gem,awr,ci,splat] [--renderer scene|mitsuba]
"""

import argparse
import time
import warnings

from mcrecon.driver import adapt
from mcrecon.methods import available_methods, get_method
from mcrecon.renderers.scenes import SceneRenderer


class ThrottledRenderer:
    """A scene renderer that takes at least n / rate seconds per request."""

    def __init__(self, inner, rate):
        self.inner, self.rate = inner, rate
        self.width, self.height, self.channels = inner.width, inner.height, inner.channels
        self.name = f"{inner.name} at {rate / 1e6:g} M samples/s"
        self.last_render_seconds = None

    def render(self, request):
        t0 = time.perf_counter()
        batch = self.inner.render(request)
        real = time.perf_counter() - t0
        self.last_render_seconds = max(real, request.total / self.rate)
        return batch


def r_warm(w, h):
    import numpy as np

    from mcrecon.renderers.protocol import SampleRequest

    return SampleRequest(w, h, counts=np.ones((h, w), np.int64), seed=1)


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--size", default="128x128,512x512")
    p.add_argument("--spp", type=float, default=32)
    p.add_argument("--rate", type=float, default=2e6)
    p.add_argument("--scene", default="soft_shadow")
    p.add_argument("--methods", default=None)
    p.add_argument("--renderer", default="scene", choices=("scene", "mitsuba"))
    a = p.parse_args()
    methods = a.methods.split(",") if a.methods else [m for m in available_methods() if get_method(m).adaptive]
    for size in a.size.split(","):
        w, h = (int(x) for x in size.split("x"))
        for name in methods:
            if a.renderer == "mitsuba":
                from mcrecon.renderers.mitsuba import MitsubaRenderer

                r = MitsubaRenderer(None, width=w, height=h)
                r.render(r_warm(w, h))  # compile the kernels once, outside the measurement
            else:
                r = ThrottledRenderer(SceneRenderer(a.scene, width=w, height=h, seed=0), a.rate)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                res = adapt(r, get_method(name), spp=a.spp, seed=0, progress=False, track_error=False)
            rend, tool = res.renderer_seconds, res.toolkit_seconds
            worst = max(x["toolkit_seconds"] / (x["toolkit_seconds"] + x["renderer_seconds"]) for x in res.rounds)
            print(f"{size:9s} {name:6s} rounds {len(res.rounds):3d}  renderer {rend:7.2f} s  toolkit {tool:6.2f} s  "
                  f"toolkit share {100 * tool / (rend + tool):5.1f}%  (worst round {100 * worst:5.1f}%)")


if __name__ == "__main__":
    main()
