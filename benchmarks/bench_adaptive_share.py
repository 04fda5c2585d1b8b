"""Toolkit share of an adaptive run's wall time, per adaptive method.

The renderer is a built-in scene throttled to a fixed throughput (default
2 M samples/s, the Mitsuba bridge's rate on the Cornell box here): its
time per round is max(real time, samples / rate).  The driver splits each
round into renderer and toolkit time; the share printed is toolkit /
(renderer + toolkit) over the whole run, with the per-round maximum.
Targets: GEM <= 5% (paper 4.36%), AWR <= 15% (paper 34.5 s of 211 s).

With ``--renderer mitsuba`` the renderer is the Mitsuba 3 bridge on its
Cornell box (issue 7's benchmark): no throttling, its own render time.

Each method runs twice in one process, sequential and pipelined
(``adapt(..., pipeline=...)``), and prints per mode:

* idle share: the time the renderer was not rendering (waiting for a plan
  or a commit) over the adaptive loop's wall time (first request to the
  last commit; the final image is not part of it; issue 15's measure);
* toolkit CPU share: CPU seconds of the thread doing the toolkit's work
  (validation, commit, statistics, planning; the filtering pool's helper
  threads are not counted) over the same wall time;
* the loop's wall time, and the pipelined / sequential ratio of it.

Issue 15 targets (idle share): box <= 2 %, gem, awr, ci <= 5 %.

usage: python benchmarks/bench_adaptive_share.py [--size 512x512] [--spp 32] [--rate 2e6]
       [--methods box,gem,awr,ci] [--renderer scene|mitsuba] [--log]
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
        # sleeps out the rest of its time (releasing the GIL, as a renderer waiting on
        # its device does), so pipelined toolkit work can overlap it for real
        t0 = time.perf_counter()
        batch = self.inner.render(request)
        real = time.perf_counter() - t0
        if real < request.total / self.rate:
            time.sleep(request.total / self.rate - real)
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
    p.add_argument("--log", action="store_true", help="commit every round to a sample log (in a temporary dir)")
    a = p.parse_args()
    methods = a.methods.split(",") if a.methods else \
        ["box"] + [m for m in available_methods() if get_method(m).adaptive and m != "auto"]
    import tempfile
    from pathlib import Path

    tmp = tempfile.TemporaryDirectory()
    for size in a.size.split(","):
        w, h = (int(x) for x in size.split("x"))
        for name in methods:
            if a.renderer == "mitsuba":
                from mcrecon.renderers.mitsuba import MitsubaRenderer

                r = MitsubaRenderer(None, width=w, height=h)
                r.render(r_warm(w, h))  # compile the kernels once, outside the measurement
            else:
                r = ThrottledRenderer(SceneRenderer(a.scene, width=w, height=h, seed=0), a.rate)
            out = {}
            for pipe in (False, True):
                log = Path(tmp.name) / f"{name}-{size}-{pipe}.h5" if a.log else None
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    try:
                        res = adapt(r, get_method(name), spp=a.spp, seed=0, progress=False, track_error=False,
                                    pipeline=pipe, log=log)
                    except Exception as exc:  # a method that cannot pipeline
                        print(f"{size:9s} {name:6s} {'pipelined' if pipe else 'sequential':10s} -- {exc}")
                        continue
                out[pipe] = res
                loop = res.loop_seconds
                worst = max(x["toolkit_seconds"] / (x["toolkit_seconds"] + x["renderer_seconds"])
                            for x in res.rounds)
                print(f"{size:9s} {name:6s} {'pipelined' if pipe else 'sequential':10s} rounds {len(res.rounds):3d}  "
                      f"renderer {res.renderer_seconds:7.2f} s  loop {loop:7.2f} s  "
                      f"idle share {100 * res.idle_seconds / loop:5.1f}%  "
                      f"toolkit CPU share {100 * res.toolkit_cpu_seconds / loop:5.1f}%  "
                      f"(sequential-style share {100 * res.toolkit_seconds / (res.toolkit_seconds + res.renderer_seconds):5.1f}%, "
                      f"worst round {100 * worst:5.1f}%; final image {res.finish_seconds:5.2f} s)", flush=True)
            if len(out) == 2:
                print(f"{size:9s} {name:6s} pipelined / sequential: loop wall {out[True].loop_seconds / out[False].loop_seconds:.3f}, "
                      f"idle {out[True].idle_seconds / max(out[False].idle_seconds, 1e-9):.3f}", flush=True)


if __name__ == "__main__":
    main()
