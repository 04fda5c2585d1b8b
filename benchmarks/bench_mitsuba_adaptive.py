"""Adaptive methods against uniform box on Mitsuba 3's Cornell box, at equal spp.

Prints, per adaptive method, its relative MSE and the ratio to uniform box
measured in the same run (a ratio above 1 is a measured loss: the paper's
AWR is one, see docs/methods/awr.md).  Needs the optional Mitsuba extra
(``bash data_tools/install_mitsuba.sh``).

Run: ``python benchmarks/bench_mitsuba_adaptive.py [--size 64] [--spp 32] [--ref-spp 1024] [--seeds 1 2 3]``
"""

from __future__ import annotations

import argparse
import warnings

import numpy as np

from mcrecon.adaptive.run import adapt
from mcrecon.methods import available_methods, get_method
from mcrecon.core.metrics import relative_mse
from mcrecon.renderers.mitsuba import MitsubaRenderer, mitsuba_available, render_reference


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--spp", type=float, default=32)
    ap.add_argument("--ref-spp", type=int, default=1024)
    ap.add_argument("--seeds", type=int, nargs="+", default=[1])
    args = ap.parse_args(argv)
    ok, reason = mitsuba_available()
    if not ok:
        print(f"Mitsuba bridge unavailable: {reason}")
        return 0
    ref = render_reference(None, width=args.size, height=args.size, spp=args.ref_spp, seed=12345)
    renderer = MitsubaRenderer(None, width=args.size, height=args.size)
    methods = [m for m in available_methods() if get_method(m).adaptive]
    print(f"Cornell box {args.size}x{args.size}, {args.spp:g} spp, reference {args.ref_spp} spp, "
          f"seeds {args.seeds}")
    print(f"{'method':8s} {'relMSE':>10s} {'box relMSE':>11s} {'ratio':>7s}")
    def run(m, seed):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            res = adapt(renderer, m, spp=args.spp, seed=seed, progress=False, track_error=False)
        return relative_mse(res.image, ref)

    box = float(np.mean([run("box", seed) for seed in args.seeds]))
    print(f"{'box':8s} {box:10.4g} {box:11.4g} {1.0:7.2f}")
    for m in methods:
        e = float(np.mean([run(m, seed) for seed in args.seeds]))
        print(f"{m:8s} {e:10.4g} {box:11.4g} {e / box:7.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
