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

``--renderers`` (with ``--corpus``; default ``builtin``) names the entries'
renderers: ``mitsuba`` and ``cycles`` add the external entries
(benchmarks/corpus_external.py), with their renderer's own sampler whatever
``--sampler`` says (Mitsuba's independent samples; Cycles' own pattern,
continued round after round: ``sobol``; under ``--sampler both`` they run
once), their features, and their cached 1024-spp reference
(``python benchmarks/corpus.py --build --only NAME`` first).  Mitsuba's run
seed ``s`` is the request seed, from the entry's seed; a Cycles run renders
a copy of the entry's scene saved with Cycles seed ``s`` (kept in the corpus
cache), from the entry's seed + 2 (its reference renders with seed + 1).
The uniform side is the same renderer's render of ``--spp`` samples in every
pixel.

usage: python benchmarks/bench_sobol_adaptive.py [--size 128x128] [--spp 32] [--seeds 2]
           [--sampler sobol|independent|both] [--scenes a,b] [--methods gem,awr]
           [--corpus tuning|held-out|all] [--renderers builtin,mitsuba,cycles] [--extend 4] [--no-structure-test] [--no-net-gate]
           [--json out.json]
"""

from __future__ import annotations

import argparse
import functools
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


@functools.lru_cache(maxsize=4)
def _uniform(make, spp, seed):
    """The uniform render of ``spp`` samples a pixel of ``make(seed)``'s renderer, as a SampleSet declared
    with its sampler (kept for the next method spec at the same seed: the loop runs every seed of one spec, then
    the next)."""
    r, request_seed = make(seed)
    w, h = r.width, r.height
    b = r.render(SampleRequest(w, h, counts=np.full((h, w), spp), seed=request_seed))
    # declared as the renderer declares it to the adaptive run: prefix-block halves of a Sobol source on both sides
    return SampleSet(b.positions, b.values, width=w, height=h, features=b.features or None, sampler=r.sampler)


def ratio(make, spec, spp, seed, *, ref):
    """(adapt relMSE / uniform relMSE, adapt relMSE) of one renderer, method spec and run seed.

    ``make(seed)`` gives a fresh renderer and the seed of its uniform request: the uniform side is that
    renderer's render of ``spp`` samples in every pixel (its sampler and features), reconstructed by the
    method with the spec's options; the adaptive side ``adapt(make(seed)[0], method, spp=spp, seed=seed)``.
    """
    m, opts = _spec(spec)
    uni = reconstruct(_uniform(make, spp, seed), method=m, reference=ref, **opts)
    res = adapt(make(seed)[0], get_method(m, **opts),
                spp=spp, seed=seed, reference=ref, track_error=False, progress=False)
    e = relative_mse(res.image, ref)
    return e / relative_mse(uni, ref), e


def scene_maker(scene, w, h, sampler, features=None):
    """``make`` of :func:`ratio` for a built-in scene: its renderer seeded with the run seed, request seed 0."""
    return lambda seed: (SceneRenderer(scene, width=w, height=h, seed=seed, sampler=sampler, features=features), 0)


def external_maker(entry, size, root=None):
    """``make`` of :func:`ratio` for the corpus's Mitsuba or Cycles entry: Mitsuba's renderer (as the corpus
    renders its log; the run seed is the request seed), or Cycles' renderer of the entry's scene saved with the
    run seed as its Cycles seed (the ``.blend`` kept in the corpus cache; uniform request seed 0)."""
    import corpus
    from corpus_external import build_cycles, build_mitsuba

    d = corpus.root_dir(root) / entry.renderer
    if entry.renderer == "mitsuba":
        from mcrecon.renderers.mitsuba import MitsubaRenderer

        scene = build_mitsuba(entry.family, size)
        make = lambda seed: (MitsubaRenderer(scene, spp_per_pass=16), seed)  # noqa: E731
        make.sampler = MitsubaRenderer.sampler
        return make
    from mcrecon.renderers.blender import BlenderRenderer

    def make(seed):
        blend = d / f"{entry.family}_{size}_run{seed}.blend"
        if not blend.exists():
            d.mkdir(parents=True, exist_ok=True)
            build_cycles(entry.family, blend, size=size, seed=seed)
        return BlenderRenderer(blend, threads=2), 0
    make.sampler = BlenderRenderer.sampler
    return make


def run_seed0(entry):
    """The first run seed of a corpus entry: its seed, but for Cycles seed + 2 (its reference renders with + 1)."""
    return entry.seed + 2 * (entry.renderer == "cycles")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="128x128")
    ap.add_argument("--spp", type=int, default=32)
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--sampler", default="sobol", choices=("sobol", "independent", "both"))
    ap.add_argument("--scenes", default=None)
    ap.add_argument("--methods", default="gem,awr")
    ap.add_argument("--corpus", default=None, choices=("tuning", "held-out", "all"),
                    help="the scene corpus's entries of this half instead of the default scenes")
    ap.add_argument("--renderers", default="builtin",
                    help="with --corpus: the entries of these renderers (builtin, mitsuba, cycles; comma-separated)")
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
    renderers = args.renderers.split(",")
    if set(renderers) - {"builtin", "mitsuba", "cycles"} or (renderers != ["builtin"] and not args.corpus):
        raise SystemExit(f"--renderers {args.renderers}: expected builtin, mitsuba, cycles, and --corpus with them")
    if args.sampler == "both":
        for sampler in ("sobol", "independent"):
            # the external entries once, with their renderer's own sampler
            which = renderers if sampler == "sobol" else [x for x in renderers if x == "builtin"]
            if not which:
                continue
            rest = ["--sampler", sampler, "--size", args.size, "--spp", str(args.spp), "--seeds", str(args.seeds),
                    "--methods", args.methods, "--extend", str(args.extend), "--renderers", ",".join(which)] + \
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

        cases = []
        for e in corpus.scenes(args.corpus, args.scenes.split(",") if args.scenes else None):
            if e.renderer not in renderers:
                continue
            if e.renderer == "builtin":
                sc = get_scene(e.family, e.params)
                ref = corpus._builtin_ref(e, w, None) if w == h else reference_image(sc, w, h)
                cases.append((e.name, scene_maker(sc, w, h, args.sampler, e.features), e.seed, ref, e.description,
                              args.sampler))
            else:
                make = external_maker(e, w)
                cases.append((e.name, make, run_seed0(e),
                              corpus.load(e, size=w, spp=args.spp).reference, e.description, make.sampler))
    else:
        cases = [(n, scene_maker(n, w, h, args.sampler), 0, None, "defaults", args.sampler)
                 for n in (args.scenes.split(",") if args.scenes else scene_names())]
    specs = args.methods.split(",")
    t0 = time.perf_counter()
    external = " (external entries: their renderer's)" if renderers != ["builtin"] else ""
    print(f"adapt / uniform relMSE, {args.sampler}{external}, {w}x{h}, {args.spp} spp, {args.seeds} seed(s): "
          "mean ± seed-to-seed sd (adapt's relMSE)")
    print(f"{'scene':<26} " + " ".join(f"{s:>26}" for s in specs))
    out = {}
    for name, make, seed0, ref, params, sampler in cases:
        cells, t1 = [], time.perf_counter()
        ref = reference_image(name, w, h) if ref is None else ref
        for spec in specs:
            rs = [ratio(make, spec, args.spp, seed0 + seed, ref=ref) for seed in range(args.seeds)]
            r = np.array([x[0] for x in rs])
            if args.extend > len(rs) and r.mean() + 2 * (r.std(ddof=1) if len(r) > 1 else 0) >= 1:
                rs += [ratio(make, spec, args.spp, seed0 + seed, ref=ref) for seed in range(len(rs), args.extend)]
                r = np.array([x[0] for x in rs])
            e = np.array([x[1] for x in rs])
            out.setdefault(name, {"params": params, "sampler": sampler, "seed0": seed0})[spec] = {
                "ratios": r.tolist(), "relmse": e.tolist()}
            cells.append(f"{r.mean():.3g}" + (f" ± {r.std(ddof=1):.2g}" if len(r) > 1 else "")
                         + ("*" if len(r) > args.seeds else "") + f" ({e.mean():.2g})")
        _uniform.cache_clear()
        print(f"{name:<26} " + " ".join(f"{c:>26}" for c in cells) + f"  ({time.perf_counter() - t1:.0f} s)",
              flush=True)
    print(f"({time.perf_counter() - t0:.0f} s)")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"sampler": args.sampler, "size": [w, h], "spp": args.spp, "seeds": args.seeds,
                       "corpus": args.corpus, "renderers": renderers, "structure_test": not args.no_structure_test,
                       "net_gate": not args.no_net_gate, "scenes": out}, f, indent=1)


if __name__ == "__main__":
    main()
