"""Renderer idle share and toolkit CPU share of adaptive runs, per adaptive method (issue 15).

The renderer is a built-in scene throttled to a fixed throughput (default
2 M samples/s, the Mitsuba bridge's rate on the Cornell box here): its
time per round is max(real time, samples / rate), the rest of it asleep
(releasing the GIL, as a renderer waiting on its device does).  With
``--renderer mitsuba`` it is the Mitsuba 3 bridge on its Cornell box
(llvm variant; no throttling, its own render time).

Every method runs sequential and pipelined (``adapt(..., pipeline=...)``)
in one process, after a small warm-up run of each (numba caches loaded,
kernels compiled), and prints per mode:

* idle share: the time the renderer was not rendering (waiting for a plan
  or a commit, and the bridge's own Python around its render call, shown
  apart as "of which in the render call": the Mitsuba bridge's jittered
  positions and array conversions outside its kernel launches) over
  the adaptive loop's wall time (first request to the last commit; the
  final image is not part of it) -- issue 15's measure;
* toolkit CPU share: CPU seconds of the thread(s) doing the toolkit's work
  (validation, commit, statistics, planning; the filtering pool's helper
  threads are not counted) over the same wall time;
* the loop's wall time and the renderer's own seconds.

Issue 15 targets (idle share): box <= 2 %, gem, awr, ci <= 5 %, splat <= 8 %.

``--profile`` adds, per run, where the toolkit's time went (validation,
log append, statistics ingest, observe, planning: wall and CPU seconds)
and which of those phases the renderer was waiting for (the overlap of
each phase with the renderer's idle intervals: the critical path).

``--quality`` measures instead what the lag costs: relative MSE (eps 0.01)
of pipelined over sequential runs at equal spp on every built-in scene,
mean over ``--seeds`` seeds (ratio of the means), default 128^2, 32 spp.
``--method-options gem:selection_every=2`` passes options to a method
(also to compare a variant against the default, with ``--compare``).

usage: python benchmarks/bench_adaptive_share.py [--size 512x512] [--spp 32] [--rate 2e6]
       [--methods box,gem,awr,ci,splat] [--renderer scene|mitsuba] [--log] [--profile]
       python benchmarks/bench_adaptive_share.py --quality [--size 128x128] [--seeds 4]
"""

import argparse
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

from mcrecon.adaptive.run import adapt
from mcrecon.adaptive.schedule import method_pipelines
from mcrecon.methods import get_method
from mcrecon.core.requests import SampleRequest
from mcrecon.renderers.scenes import SceneRenderer

METHODS = ("box", "gem", "awr", "ci", "splat")
#: issue 15's targets, idle share in percent
TARGETS = {"box": 2.0, "gem": 5.0, "awr": 5.0, "ci": 5.0, "splat": 8.0}
PHASES = ("validate", "append", "ingest", "observe", "plan", "prepare")


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


def _one_spp(w, h):
    return SampleRequest(w, h, counts=np.ones((h, w), np.int64), seed=1)


def make_renderer(kind, w, h, scene, rate):
    if kind == "mitsuba":
        from mcrecon.renderers.mitsuba import MitsubaRenderer

        r = MitsubaRenderer(None, width=w, height=h)
    else:
        r = ThrottledRenderer(SceneRenderer(scene, width=w, height=h, seed=0), rate)
    (r.inner if kind == "scene" else r).render(_one_spp(w, h))  # compile the renderer's kernels, unmeasured
    return r


def critical_path(res):
    """Seconds of each toolkit phase that overlap the renderer's idle intervals, and the rest.

    The renderer is idle from the loop's start to its first render call,
    between its calls, after its last one, and inside a call for the
    seconds beyond what it reports as its own (the bridge's Python).
    """
    ev = res.timeline
    renders = sorted((e for e in ev if e["phase"] == "render"), key=lambda e: e["start"])
    end = max(e["end"] for e in ev)
    gaps, t = [], 0.0
    for e in renders:
        if e["start"] > t:
            gaps.append((t, e["start"]))
        t = e["end"]
    if end > t:
        gaps.append((t, end))
    out = {p: 0.0 for p in PHASES}
    out["render call beyond its own time"] = sum(max(e["end"] - e["start"] - e["own"], 0.0) for e in renders)
    idle_gaps = sum(b - a for a, b in gaps)
    covered = 0.0
    for a, b in gaps:
        # each instant of a gap is charged to the first phase running then (phases of one
        # thread do not overlap; toolkit and renderer thread phases in a gap: toolkit ones)
        spans = sorted((max(e["start"], a), min(e["end"], b), e["phase"]) for e in ev
                       if e["phase"] in PHASES and e["end"] > a and e["start"] < b)
        t = a
        for s, f, name in spans:
            s = max(s, t)
            if f > s:
                out[name] += f - s
                covered += f - s
                t = f
    out["other (glue, thread hand-off, GIL)"] = idle_gaps - covered
    return out


def profile_lines(res):
    ev = res.timeline
    lines = []
    rows = []
    for p in PHASES:
        sel = [e for e in ev if e["phase"] == p]
        if sel:
            rows.append(f"{p} {sum(e['end'] - e['start'] for e in sel):6.3f}s wall {sum(e['cpu'] for e in sel):6.3f}s cpu "
                        f"(max round {max(e['end'] - e['start'] for e in sel):5.3f}s)")
    lines.append("    toolkit phases: " + "; ".join(rows))
    cp = critical_path(res)
    loop = res.loop_seconds
    lines.append("    renderer waits for: " + "; ".join(f"{k} {v:6.3f}s ({100 * v / loop:4.1f}%)"
                                                    for k, v in cp.items() if v > 0.0005))
    first = [e for e in ev if e["round"] == 0 and e["phase"] in PHASES and e["start"] <= min(
        x["start"] for x in ev if x["phase"] == "render" and x["round"] == 1)] if res.pipelined else []
    if first:
        lines.append(f"    (pipelined: round 0's commit and round 1's plan, before round 1 renders: "
                     f"{sum(e['end'] - e['start'] for e in first):.3f}s)")
    return lines


def parse_options(text):
    """'gem:selection_every=2,gamma=0.2;ci:min_spp=4' -> {"gem": {...}, "ci": {...}} (values as Python literals)."""
    import ast

    out = {}
    for part in filter(None, (text or "").split(";")):
        name, _, opts = part.partition(":")
        d = out.setdefault(name.strip(), {})
        for kv in filter(None, opts.split(",")):
            k, _, v = kv.partition("=")
            try:
                d[k.strip()] = ast.literal_eval(v.strip())
            except (ValueError, SyntaxError):
                d[k.strip()] = v.strip()
    return out


def quality(a, methods, options):
    """Relative MSE pipelined / sequential (or variant / default with --compare), per scene and method."""
    from mcrecon.core.metrics import relative_mse
    from mcrecon.renderers.scenes import scene_names

    w, h = (int(x) for x in a.size.split(",")[0].split("x"))
    seeds = range(a.seeds)
    rows = {}
    for scene in scene_names():
        ref = SceneRenderer(scene, width=w, height=h, seed=0).reference()
        for name in methods:
            errs = {}
            for variant in ("base", "test"):
                e = []
                for seed in seeds:
                    opts = options.get(name, {}) if (variant == "test" or not a.compare) else {}
                    pipe = (variant == "test") if not a.compare else None
                    m = get_method(name, **opts)
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore")
                        res = adapt(SceneRenderer(scene, width=w, height=h, seed=seed), m, spp=a.spp, seed=seed,
                                    progress=False, track_error=False,
                                    pipeline=pipe if pipe is not None else None)
                    e.append(relative_mse(res.image, ref))
                errs[variant] = float(np.mean(e))
            rows[(scene, name)] = errs["test"] / errs["base"]
            print(f"{scene:15s} {name:6s} relMSE {errs['base']:.4g} -> {errs['test']:.4g}  ratio "
                  f"{rows[(scene, name)]:.3f}", flush=True)
    what = "variant / default" if a.compare else "pipelined / sequential"
    print(f"\nrelative MSE {what}; {w}x{h}, {a.spp:g} spp, {a.seeds} seeds (ratio of the means)")
    print("| scene | " + " | ".join(methods) + " |")
    print("|---|" + "---|" * len(methods))
    for scene in scene_names():
        print(f"| {scene} | " + " | ".join(f"{rows[(scene, m)]:.3f}" for m in methods) + " |")


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--size", default="512x512", help="WxH, or several separated by commas (default 512x512)")
    p.add_argument("--spp", type=float, default=32)
    p.add_argument("--rate", type=float, default=2e6, help="throttled scene renderer's samples per second")
    p.add_argument("--scene", default="soft_shadow")
    p.add_argument("--methods", default=",".join(METHODS))
    p.add_argument("--modes", default="sequential,pipelined")
    p.add_argument("--renderer", default="scene", choices=("scene", "mitsuba"))
    p.add_argument("--log", action="store_true", help="commit every round to a sample log (in a temporary dir)")
    p.add_argument("--profile", action="store_true", help="where the toolkit's time goes, and what the renderer "
                   "waits for")
    p.add_argument("--quality", action="store_true", help="relative MSE pipelined / sequential on the built-in scenes")
    p.add_argument("--seeds", type=int, default=4)
    p.add_argument("--method-options", default="", help="e.g. 'gem:selection_every=2;ci:min_spp=4'")
    p.add_argument("--compare", action="store_true", help="with --quality: the --method-options variant against "
                   "the default, both in the method's default mode")
    a = p.parse_args()
    methods = a.methods.split(",")
    options = parse_options(a.method_options)
    if a.quality:
        if a.size == "512x512":
            a.size = "128x128"
        quality(a, methods, options)
        return
    modes = [{"sequential": False, "pipelined": True}[m] for m in a.modes.split(",")]
    tmp = tempfile.TemporaryDirectory()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for name in methods:  # load every method's compiled kernels before any measurement
            for pipe in modes:
                adapt(SceneRenderer(a.scene, width=48, height=40, seed=0), name, spp=8, seed=0, progress=False,
                      track_error=False, pipeline=pipe,
                      log=Path(tmp.name) / f"warm-{name}-{pipe}.h5" if a.log else None)
    table = []
    print(f"renderer: {a.renderer}{'' if a.renderer == 'mitsuba' else f' ({a.scene} at {a.rate / 1e6:g} M samples/s)'}"
          f", {a.spp:g} spp, log {'on' if a.log else 'off'}", flush=True)
    for size in a.size.split(","):
        w, h = (int(x) for x in size.split("x"))
        for name in methods:
            r = make_renderer(a.renderer, w, h, a.scene, a.rate)
            out = {}
            for pipe in modes:
                mode = "pipelined" if pipe else "sequential"
                log = Path(tmp.name) / f"{name}-{size}-{pipe}.h5" if a.log else None
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    try:
                        res = adapt(r, get_method(name, **options.get(name, {})), spp=a.spp, seed=0,
                                    progress=False, track_error=False, pipeline=pipe, log=log)
                    except Exception as exc:  # a method that cannot pipeline
                        print(f"{size:9s} {name:6s} {mode:10s} -- {exc}", flush=True)
                        continue
                out[pipe] = res
                loop = res.loop_seconds
                idle = 100 * res.idle_seconds / loop
                cpu = 100 * res.toolkit_cpu_seconds / loop
                bridge = 100 * sum(max(e["end"] - e["start"] - e["own"], 0.0) for e in res.timeline
                                   if e["phase"] == "render") / loop
                table.append((size, name, mode, idle, bridge, cpu, loop, res.renderer_seconds, len(res.rounds)))
                print(f"{size:9s} {name:6s} {mode:10s} rounds {len(res.rounds):3d}  renderer {res.renderer_seconds:7.2f} s"
                      f"  loop {loop:7.2f} s  idle share {idle:5.1f}%  toolkit CPU share {cpu:5.1f}%"
                      f"  (final image {res.finish_seconds:5.2f} s)", flush=True)
                if a.profile:
                    for line in profile_lines(res):
                        print(line, flush=True)
            if len(out) == 2:
                print(f"{size:9s} {name:6s} pipelined / sequential: loop wall "
                      f"{out[True].loop_seconds / out[False].loop_seconds:.3f}", flush=True)
    print()
    print("| size | method | mode | idle share | of which in the render call | toolkit CPU share | loop s | "
          "renderer s | rounds | target (idle) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for size, name, mode, idle, bridge, cpu, loop, rend, n in table:
        tgt = TARGETS.get(name)
        mark = "" if tgt is None else (f"<= {tgt:g} % " + ("met" if idle <= tgt else "missed"))
        print(f"| {size} | {name} | {mode} | {idle:.1f} % | {bridge:.1f} % | {cpu:.1f} % | {loop:.2f} | {rend:.2f} "
              f"| {n} | {mark} |")


if __name__ == "__main__":
    main()
