"""Adaptive rounds through Cycles (`mcrecon adapt --blender`) against a uniform log of the same budget.

For the three scenes of bench_blender.py (a textured floor, a glass sphere, depth of field), at 128x128
and 32 spp on the CPU: the wall time of a uniform log through the bridge (`mcrecon blender log --spp 32`:
one subset render per sample index plus its probe render) and of an adaptive run through
`BlenderRenderer` (`mcrecon adapt --blender --spp 32`) with box (the default method: uniform rounds
that continue each pixel's pattern) and ci (samples where the confidence interval is wide), their
ratio, the renders and pixel-samples Cycles rendered against the samples delivered (the rest is waste,
or kept for a later round), and the relative MSE of each image against a Cycles reference.  gem, awr and
auto run through the Python API (``--methods box,ci,gem,awr,auto``): their rounds ask for counts that
differ from pixel to pixel, which Cycles renders one sample index at a time over rectangles; the CLI
refuses them with --blender for what that costs.
Times are the fastest of --repeat runs (the machine is shared); the adaptive runs write their log.

    python benchmarks/bench_blender_adaptive.py [--size 128] [--spp 32] [--ref-spp 1024] [--threads 2]

Needs bpy (pip install 'mcrecon[blender]').
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_blender import build, log_stats, rel_mse, render_args  # noqa: E402

from mcrecon import CallableRenderer, adapt  # noqa: E402
from mcrecon.core.requests import jittered_positions  # noqa: E402
from mcrecon.errors import RendererError  # noqa: E402
from mcrecon.renderers import blender as bl  # noqa: E402


def _flat(request):
    """A warm-up renderer: jittered samples of a noisy flat image."""
    parts = [] if request.counts is None else [jittered_positions(request.counts, np.random.default_rng(request.seed))]
    pos = np.concatenate(parts + ([] if request.positions is None else [request.positions]))
    rng = np.random.default_rng(request.seed + 1)
    return pos, rng.random((len(pos), 3))


def main() -> None:
    ap = render_args(argparse.ArgumentParser(description=__doc__.splitlines()[0]))
    ap.add_argument("--scenes", default="textures,glass,dof")
    ap.add_argument("--methods", default="box,ci,gem")
    ap.add_argument("--repeat", type=int, default=2, help="timed runs of each; the fastest is reported")
    a = ap.parse_args()
    if not bl.bpy_available():
        raise SystemExit(bl.BPY_MISSING)
    print(f"{a.size}x{a.size}, {a.spp} spp, {a.threads} threads, reference {a.ref_spp} spp; relMSE = mean((x - ref)^2 "
          "/ (ref^2 + 0.01))")
    print("| scene | run | wall (s) | / uniform | renders | pixel-samples rendered / delivered | relMSE |")
    print("|---|---|---|---|---|---|---|")
    for method in a.methods.split(","):  # compile the toolkit's kernels before any timing
        try:
            adapt(CallableRenderer(_flat, width=16, height=16), method, spp=8, track_error=False, progress=False)
        except Exception as exc:  # noqa: BLE001 - a method that needs what a flat image lacks is timed cold
            print(f"  (warm-up of {method}: {exc})", file=sys.stderr)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for kind in a.scenes.split(","):
            s0 = tmp / f"{kind}.blend"
            build(kind, s0, size=a.size, seed=0)
            ref, _ = bl.render_reference(s0, spp=a.ref_spp, threads=a.threads)
            bl.render_reference(s0, spp=1, threads=a.threads)  # the same warm-up before each timing
            t_log = np.inf
            for _ in range(a.repeat):
                t = time.perf_counter()
                bl.dump_cycles_log(tmp / f"{kind}.h5", s0, spp=a.spp, threads=a.threads, features="all", overwrite=True)
                t_log = min(t_log, time.perf_counter() - t)
            mean, _ = log_stats(tmp / f"{kind}.h5")
            n = a.spp * a.size * a.size
            print(f"| {kind} | uniform log | {t_log:.1f} | 1.00x | {2 * a.spp} | {n} / {n} | "
                  f"{rel_mse(mean, ref):.2e} |", flush=True)
            for method in a.methods.split(","):
                t_run, refused = np.inf, ""
                for _ in range(a.repeat):
                    t = time.perf_counter()
                    r = bl.BlenderRenderer(s0, threads=a.threads, features="all")
                    try:  # with a log, as a resumable run
                        res = adapt(r, method, spp=a.spp, track_error=False, progress=False, log=tmp / "run.h5",
                                    overwrite=True)
                    except RendererError as exc:
                        refused = str(exc).split(": ", 2)[-1]
                        break
                    t_run = min(t_run, time.perf_counter() - t)
                if not np.isfinite(t_run):
                    print(f"| {kind} | adapt {method} | - | - | - | - | refused: {refused[:70]}... |",
                          flush=True)
                    continue
                print(f"  ({method}: {len(res.rounds)} rounds, renderer {res.renderer_seconds:.1f} s, toolkit "
                      f"{res.toolkit_seconds:.1f} s)", file=sys.stderr)
                print(f"| {kind} | adapt {method} | {t_run:.1f} | {t_run / t_log:.2f}x | {r.renders} | "
                      f"{r.samples_rendered} / {r.samples_delivered} | "
                      f"{rel_mse(res.image.astype(np.float32), ref):.2e} |", flush=True)


if __name__ == "__main__":
    main()
