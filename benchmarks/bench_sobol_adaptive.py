"""Adaptive against uniform sampling at equal samples, per built-in scene, with a method's options.

Per scene, method spec and run seed: the relMSE (eps 0.01) of ``adapt``
with the method on the scene renderer's sampler (``--sampler sobol``: each
pixel's Owen-scrambled Sobol sequence continued round after round;
``independent``) at ``--spp``, over the same method reconstructing a
uniform render of the same budget and sampler.  The scene renderer declares
its sampler (``SceneRenderer.sampler``, docs/renderer-protocol.md), so a
method whose ``net_counts`` follows the renderer (awr's and auto's default -1) hands
out whole nets with ``--sampler sobol`` and free counts with
``independent``; ``name:net_counts=0`` or ``=1`` decides it instead.
``--sampler both`` runs the two in turn.  Printed: the ratio's mean
over the seeds, its seed-to-seed standard deviation, and adapt's relMSE;
``--extend N`` then runs N seeds for every cell whose mean is within two
standard deviations of 1 or above (marked ``*``).
> 1: adaptive loses to uniform.

A method spec is ``name`` or ``name:key=val[:key=val]`` (e.g.
``gem:stratified_gain=0``, the allocation by ``s^2 / n``); the same
options reconstruct the uniform render.  The uniform render's samples
declare their sampler, as the renderer does to the adaptive run: a Sobol
source's halves are prefix blocks on both sides (an adaptive run's final
image reads its log's, docs/adaptive.md), so the ratio is what a user of
the same renderer gets from adapting instead of rendering uniformly.

``--corpus tuning|held-out|all`` runs the scene corpus's built-in entries
(benchmarks/corpus.py: every family at its defaults and with randomised
parameters) instead of the default scenes, each with its own parameters,
features flag and seed (run seed ``s`` renders with the entry's seed + s),
against its exact reference (``corpus`` reads it from its cache where it
holds one); ``--scenes`` then picks entry names or families.  One process
for everything: the references and compiled kernels are shared.

usage: python benchmarks/bench_sobol_adaptive.py [--size 128x128] [--spp 32] [--seeds 2]
           [--sampler sobol|independent|both] [--scenes a,b] [--methods gem,awr]
           [--corpus tuning|held-out|all] [--extend 4] [--no-structure-test] [--no-net-gate]
           [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from mcrecon import adapt, reconstruct
from mcrecon.core.metrics import relative_mse
from mcrecon.core.requests import SampleRequest
from mcrecon.core.samples import SampleSet
from mcrecon.methods import get_method
from mcrecon.renderers.scenes import SceneRenderer, get_scene, reference_image, scene_names


def _spec(text):
    name, *kv = text.split(":")
    opts = {}
    for item in kv:
        k, v = item.split("=", 1)
        try:
            opts[k] = int(v)
        except ValueError:
            try:
                opts[k] = float(v)
            except ValueError:
                opts[k] = v
    return name, opts


def ratio(name, spec, w, h, spp, seed, sampler, *, ref=None, features=None):
    """(adapt relMSE / uniform relMSE, adapt relMSE) of one scene (a name or a Scene), method spec and seed."""
    m, opts = _spec(spec)
    ref = reference_image(name, w, h) if ref is None else ref

    def renderer():
        return SceneRenderer(name, width=w, height=h, seed=seed, sampler=sampler, features=features)

    b = renderer().render(SampleRequest(w, h, counts=np.full((h, w), spp)))
    # declared as the renderer declares it to the adaptive run: prefix-block halves of a Sobol source on both sides
    uni = reconstruct(SampleSet(b.positions, b.values, width=w, height=h, features=b.features or None,
                                sampler=sampler),
                      method=m, reference=ref, **opts)
    res = adapt(renderer(), get_method(m, **opts),
                spp=spp, seed=seed, reference=ref, track_error=False, progress=False)
    e = relative_mse(res.image, ref)
    return e / relative_mse(uni, ref), e


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="128x128")
    ap.add_argument("--spp", type=int, default=32)
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--sampler", default="sobol", choices=("sobol", "independent", "both"))
    ap.add_argument("--scenes", default=None)
    ap.add_argument("--methods", default="gem,awr")
    ap.add_argument("--corpus", default=None, choices=("tuning", "held-out", "all"),
                    help="the scene corpus's built-in entries of this half instead of the default scenes")
    ap.add_argument("--extend", type=int, default=0,
                    help="then this many seeds for every cell whose mean is within 2 seed-to-seed sd of 1 or above")
    ap.add_argument("--no-structure-test", action="store_true",
                    help="plan from the estimates even where the samples show no structure (Method.structure_test)")
    ap.add_argument("--no-net-gate", action="store_true",
                    help="spend whole-net rounds as planned even where the even round is predicted to err less "
                         "(Method.net_gate)")
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    from mcrecon.methods.base import Method

    if args.no_structure_test:
        Method.structure_test = False
    if args.no_net_gate:
        Method.net_gate = False
    if args.sampler == "both":
        for sampler in ("sobol", "independent"):
            rest = ["--sampler", sampler, "--size", args.size, "--spp", str(args.spp), "--seeds", str(args.seeds),
                    "--methods", args.methods, "--extend", str(args.extend)] + \
                (["--scenes", args.scenes] if args.scenes else []) + \
                (["--corpus", args.corpus] if args.corpus else []) + \
                (["--no-structure-test"] if args.no_structure_test else []) + \
                (["--no-net-gate"] if args.no_net_gate else []) + \
                (["--json", args.json.replace(".json", f"_{sampler}.json")] if args.json else [])
            main(rest)
        return
    w, h = (int(v) for v in args.size.lower().split("x"))
    if args.corpus:
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        import corpus

        entries = [e for e in corpus.scenes(args.corpus, args.scenes.split(",") if args.scenes else None)
                   if e.renderer == "builtin"]
        cases = [(e.name, get_scene(e.family, e.params), e.seed, e.features,
                  corpus._builtin_ref(e, w, None) if w == h else None, e.description) for e in entries]
    else:
        cases = [(n, n, 0, None, None, "defaults")
                 for n in (args.scenes.split(",") if args.scenes else scene_names())]
    specs = args.methods.split(",")
    t0 = time.perf_counter()
    print(f"adapt / uniform relMSE, {args.sampler}, {w}x{h}, {args.spp} spp, {args.seeds} seed(s): "
          "mean ± seed-to-seed sd (adapt's relMSE)")
    print(f"{'scene':<26} " + " ".join(f"{s:>26}" for s in specs))
    out = {}
    for name, scene, seed0, features, ref, params in cases:
        cells = []
        ref = reference_image(scene, w, h) if ref is None else ref
        for spec in specs:
            rs = [ratio(scene, spec, w, h, args.spp, seed0 + seed, args.sampler, ref=ref, features=features)
                  for seed in range(args.seeds)]
            r = np.array([x[0] for x in rs])
            if args.extend > len(rs) and r.mean() + 2 * (r.std(ddof=1) if len(r) > 1 else 0) >= 1:
                rs += [ratio(scene, spec, w, h, args.spp, seed0 + seed, args.sampler, ref=ref, features=features)
                       for seed in range(len(rs), args.extend)]
                r = np.array([x[0] for x in rs])
            e = np.array([x[1] for x in rs])
            out.setdefault(name, {"params": params})[spec] = {"ratios": r.tolist(), "relmse": e.tolist()}
            cells.append(f"{r.mean():.3g}" + (f" ± {r.std(ddof=1):.2g}" if len(r) > 1 else "")
                         + ("*" if len(r) > args.seeds else "") + f" ({e.mean():.2g})")
        print(f"{name:<26} " + " ".join(f"{c:>26}" for c in cells), flush=True)
    print(f"({time.perf_counter() - t0:.0f} s)")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"sampler": args.sampler, "size": [w, h], "spp": args.spp, "seeds": args.seeds,
                       "corpus": args.corpus, "structure_test": not args.no_structure_test,
                       "net_gate": not args.no_net_gate, "scenes": out}, f, indent=1)


if __name__ == "__main__":
    main()
