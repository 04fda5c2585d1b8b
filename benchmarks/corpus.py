"""The scene corpus behind every tuning decision: 55 scenes, a tuning half and a held-out half.

* 22 built-in scenes (:mod:`mcrecon.renderers.scenes`): every family at its
  default parameters, and one to three variants each with parameters drawn
  once from a fixed seed (light size and power, texture scale and contrast,
  the hdr emitter's power, the lens, the motion, the caustic's power and
  probability, ``exposure``); every second one of the untextured families
  sends per-sample features.  Exact references; any film size (128 and 512).
* 24 more built-in scenes in the tuning half only (:data:`EXTRA_PARAM_SEED`):
  12 hdr and 12 checker_spot variants drawn from the same ranges, the
  families whose held-out members ``auto`` missed, so that a rule for such a
  scene is tuned on scenes of its kind, never on the held-out one.
* 4 Mitsuba 3 scenes and 5 Blender Cycles scenes (:mod:`corpus_external`),
  with per-sample albedo, normal and depth; references are high-spp renders
  with an independent seed (Cycles' own render; Mitsuba through the bridge).

The split of the first 31 into halves is drawn here, once, from :data:`SPLIT_SEED`,
stratified by family (built-in) and by renderer (Mitsuba, Cycles), so each
half holds every built-in family and both external renderers.  It was fixed
before any method was run on the corpus: do not redraw it.  The 24 extra
scenes are drawn after it and join the tuning half (39 scenes; held-out 16).

The built-in scenes are rendered in memory when asked for (their samples are
a function of the scene, size, spp and seed; under a second at 128^2).  The
external ones are rendered once by ``--build`` and cached under
``$MCRECON_CORPUS_DIR`` (default ``~/.cache/mcrecon-corpus``)::

    python benchmarks/corpus.py --list                       # the scenes, their half and parameters
    python benchmarks/corpus.py --build                      # logs (128^2, 32 spp) and references (1024 spp)
    python benchmarks/corpus.py --build --size 512 --only mitsuba-cbox

``--build`` at 128^2, 32 spp and 1024-spp references took 33 minutes of
wall on 2 cores shared with other jobs, about 12 CPU minutes (the Cycles
references 190-560 s of wall each, most of it; Mitsuba's 18-62 s; the logs
8-28 s each); 512^2 costs about 16 times that (the held-out Mitsuba scenes'
512^2 references 271 and 400 CPU s, 10 and 18 minutes of wall on 2 busy
cores; their logs 24 and 42 s).  The Cycles scenes need ``bpy`` importable
beside this numpy; their 512^2 references take hours on 2 cores.  A
1024-spp reference's own noise adds about 32/1024 of the pixel mean's
relMSE to every measured 32-spp relMSE (``--ref-spp`` for more).

Use from Python (``sys.path`` holding ``benchmarks/``)::

    import corpus
    for entry in corpus.scenes("held-out"):
        case = corpus.load(entry, size=128, spp=32)   # case.source: a SampleSet or a log path
        ...                                           # case.reference: (H, W, 3) float64
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

_HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(_HERE))
sys.path.insert(0, str(_HERE.parent))

from corpus_external import CYCLES_SCENES, MITSUBA_SCENES  # noqa: E402

#: Seeds of the parameter draw and of the split (fixed: changing them makes another corpus).
PARAM_SEED = 40_2026
SPLIT_SEED = 40_4040
#: Environment variable naming the cache directory.
ENV_DIR = "MCRECON_CORPUS_DIR"
HALVES = ("tuning", "held-out")

#: Built-in families, with the random variants each gets (besides its default scene).
_BUILTIN_VARIANTS = {"soft_shadow": 2, "depth_of_field": 1, "motion_blur": 1, "caustic": 2, "hdr": 2, "flat": 1,
                     "checker_wall": 1, "checker_spot": 2, "checker_dof": 1}
_TEXTURED = ("checker_wall", "checker_spot", "checker_dof")
#: Extra tuning scenes: more draws of the families whose held-out members auto missed, from their own
#: seed and after the split (every entry above keeps its parameters, samples and half).
EXTRA_PARAM_SEED = 40_2027
#: (family, count) in the order drawn (one stream): each round numbered on from the family's last entry.
_EXTRA_VARIANTS = (("hdr", 6), ("checker_spot", 6), ("hdr", 6), ("checker_spot", 6))
_EXTRA_SEED0 = 200


def _draw_ranges(family):
    """(name, low, high, log-uniform) of the parameters drawn for a family's variants."""
    exp = ("exposure", 0.25, 4.0, True)
    return {
        "soft_shadow": [("light_power", 0.5, 3.0, True), ("light_size", 0.3, 1.6, False),
                        ("ambient", 0.02, 0.2, True), ("texture_scale", 0.5, 3.0, True),
                        ("contrast", 0.3, 1.5, False), ("occluder_shift", -0.1, 0.1, False), exp],
        "depth_of_field": [("aperture", 0.3, 2.5, False), ("focus_band", 0.0, 0.3, False),
                           ("texture_scale", 0.5, 2.5, True), ("contrast", 0.3, 1.05, False), exp],
        "motion_blur": [("speed", 0.3, 1.3, False), ("texture_scale", 0.5, 3.0, True), exp],
        "caustic": [("hit_probability", 0.005, 0.2, True), ("power", 0.3, 5.0, True), ("ring_width", 0.5, 3.0, True),
                    ("ring_radius", 0.15, 0.32, False), exp],
        "hdr": [("power", 50.0, 5000.0, True), ("emitter_radius", 0.05, 0.2, False), ("dim_level", 1e-4, 1e-2, True),
                ("light_size", 0.3, 2.0, False), ("texture_scale", 0.5, 3.0, True)],
        "flat": [("exposure", 0.1, 10.0, True)],
        "checker_wall": [("texture_scale", 0.5, 2.5, True), ("contrast", 0.3, 1.0, False), ("sky", 0.05, 0.5, True),
                         ("light_power", 0.5, 3.0, True), ("light_size", 0.3, 3.0, False), exp],
        "checker_spot": [("texture_scale", 0.5, 2.5, True), ("contrast", 0.3, 1.0, False), ("sky", 0.01, 0.1, True),
                         ("light_power", 0.5, 4.0, True), ("hit_probability", 0.01, 0.2, True),
                         ("spot_size", 0.5, 2.0, False), ("light_size", 0.3, 4.0, False), exp],
        "checker_dof": [("aperture", 0.04, 0.3, False), ("focus", 1.0, 3.5, False), ("texture_scale", 0.5, 2.0, True),
                        exp],
    }[family]


@dataclass(frozen=True)
class Entry:
    """One corpus scene.

    ``name`` is unique (``builtin-caustic-1``, ``mitsuba-cbox``,
    ``cycles-fence``); ``family`` the built-in scene name or the external
    scene's; ``params`` the built-in scene's parameters (empty: its
    defaults); ``seed`` the seed of its samples; ``features`` whether its
    samples carry albedo, normal and depth; ``half`` tuning or held-out.
    """

    name: str
    renderer: str
    family: str
    params: dict = field(hash=False)
    seed: int
    features: bool
    half: str = ""

    @property
    def description(self) -> str:
        if self.renderer == "cycles":
            return CYCLES_SCENES[self.family]
        if self.renderer == "mitsuba":
            return MITSUBA_SCENES[self.family]
        if not self.params:
            return "defaults"
        return ", ".join(f"{k}={v:.3g}" for k, v in self.params.items())


def _draw_params(family, rng):
    from mcrecon.renderers.scenes.params import check_params

    for _ in range(100):
        out = {}
        for name, lo, hi, log in _draw_ranges(family):
            x = float(np.exp(rng.uniform(np.log(lo), np.log(hi)))) if log else float(rng.uniform(lo, hi))
            out[name] = float(f"{x:.4g}")
        try:
            return check_params(family, out)
        except Exception:  # a draw the closed form refuses (motion_blur's objects overlapping): draw again
            continue
    raise RuntimeError(f"no valid parameter draw for {family}")


def _all_entries() -> list[Entry]:
    rng = np.random.default_rng(PARAM_SEED)
    out = []
    seed = 100
    for family, n in _BUILTIN_VARIANTS.items():
        for k in range(n + 1):
            params = {} if k == 0 else _draw_params(family, rng)
            features = family in _TEXTURED or k % 2 == 1
            out.append(Entry(f"builtin-{family}-{k}", "builtin", family, params, seed, features))
            seed += 1
    out += [Entry(f"mitsuba-{n}", "mitsuba", n, {}, 1, True) for n in MITSUBA_SCENES]
    out += [Entry(f"cycles-{n}", "cycles", n, {}, 0, True) for n in CYCLES_SCENES]
    return _split(out) + _extra_entries()


def _extra_entries():
    """The extra tuning draws: ``builtin-<family>-<k>`` numbered on from the family's split entries."""
    rng = np.random.default_rng(EXTRA_PARAM_SEED)
    out, seed = [], _EXTRA_SEED0
    last = dict(_BUILTIN_VARIANTS)
    for family, n in _EXTRA_VARIANTS:
        for _ in range(n):
            k = last[family] = last[family] + 1
            features = family in _TEXTURED or k % 2 == 1
            out.append(Entry(f"builtin-{family}-{k}", "builtin", family, _draw_params(family, rng), seed, features,
                             "tuning"))
            seed += 1
    return out


def _split(entries):
    """Each entry's half: within each stratum (a built-in family; Mitsuba; Cycles), a seeded permutation
    dealt alternately, the first card to the half that has fewer scenes so far."""
    rng = np.random.default_rng(SPLIT_SEED)
    strata = {}
    for e in entries:
        strata.setdefault(e.family if e.renderer == "builtin" else e.renderer, []).append(e)
    half = {}
    count = {h: 0 for h in HALVES}
    for key in sorted(strata):
        group = strata[key]
        order = rng.permutation(len(group))
        first = min(HALVES, key=lambda h: (count[h], rng.random()))
        other = HALVES[1 - HALVES.index(first)]
        for i, j in enumerate(order):
            h = first if i % 2 == 0 else other
            half[group[j].name] = h
            count[h] += 1
    return [Entry(e.name, e.renderer, e.family, e.params, e.seed, e.features, half[e.name]) for e in entries]


_ENTRIES = _all_entries()


def add_arguments(ap, *, half: str = "held-out") -> None:
    """A corpus benchmark's scene options: ``--half``, ``--scenes``, ``--size``, ``--spp``, ``--ref-spp``, ``--root``."""
    ap.add_argument("--half", default=half, choices=("tuning", "held-out", "all"))
    ap.add_argument("--scenes", default="", help="comma-separated entry names, families or renderers")
    ap.add_argument("--size", type=int, default=128, choices=(128, 512))
    ap.add_argument("--spp", type=int, default=32)
    ap.add_argument("--ref-spp", type=int, default=1024, help="the external scenes' reference spp (as built)")
    ap.add_argument("--root", default=None, help="the corpus cache (default $MCRECON_CORPUS_DIR or "
                    "~/.cache/mcrecon-corpus)")


def scenes(half: str = "all", names=None) -> list[Entry]:
    """The corpus's entries of one half (``tuning``, ``held-out``) or ``all``; ``names``: only these
    (entry names, families or renderers)."""
    if half not in (*HALVES, "all"):
        raise SystemExit(f"--half {half!r}: expected tuning, held-out or all")
    out = [e for e in _ENTRIES if half == "all" or e.half == half]
    if names:
        want = set(names)
        unknown = want - {x for e in _ENTRIES for x in (e.name, e.family, e.renderer)}
        if unknown:
            raise SystemExit(f"--scenes: unknown {', '.join(sorted(unknown))}; see python benchmarks/corpus.py --list")
        out = [e for e in out if want & {e.name, e.family, e.renderer}]
    return out


def root_dir(root=None) -> Path:
    return Path(root or os.environ.get(ENV_DIR) or Path.home() / ".cache" / "mcrecon-corpus")


@dataclass
class Case:
    """A scene at a size and spp, ready to reconstruct: ``source`` (a SampleSet or a log path) and the
    ``reference`` (H, W, 3) float64."""

    entry: Entry
    source: object
    reference: np.ndarray
    features: bool


def _paths(entry, size, spp, ref_spp, root):
    d = root_dir(root) / entry.renderer
    return (d / f"{entry.family}_{size}_{spp}spp_seed{entry.seed}.h5",
            d / f"{entry.family}_{size}_ref{ref_spp}.npy")


def _builtin_ref(entry, size, root):
    """The exact reference, cached on disk at 512^2 and above (16 times the 128^2 cost there: 15-40 CPU s each)."""
    from mcrecon.renderers import scenes as S

    sc = S.get_scene(entry.family, entry.params)
    if size < 512:
        return S.reference_image(sc, size, size)
    key = hashlib.sha1(json.dumps([entry.family, sc.param_key]).encode()).hexdigest()[:10]
    p = root_dir(root) / "builtin" / f"{entry.family}_{key}_{size}_ref.npy"
    if p.exists():
        return np.load(p)
    ref = S.reference_image(sc, size, size)
    p.parent.mkdir(parents=True, exist_ok=True)
    np.save(p, ref)
    return ref


def load(entry: Entry, *, size: int = 128, spp: int = 32, ref_spp: int = 1024, root=None) -> Case:
    """One corpus scene's samples and reference (an external scene must have been built: ``--build``)."""
    if entry.renderer == "builtin":
        from mcrecon.core.samples import SampleSet
        from mcrecon.renderers import scenes as S

        sc = S.get_scene(entry.family, entry.params)
        b = S.render_uniform(sc, width=size, height=size, spp=spp, seed=entry.seed, features=entry.features)
        src = SampleSet(b.positions, b.values, width=size, height=size, features=b.features or None)
        return Case(entry, src, _builtin_ref(entry, size, root), entry.features)
    log, ref = _paths(entry, size, spp, ref_spp, root)
    if not log.exists() or not ref.exists():
        raise FileNotFoundError(f"{entry.name} at {size}^2, {spp} spp is not built: python benchmarks/corpus.py "
                                f"--build --size {size} --spp {spp} --ref-spp {ref_spp} --only {entry.name} "
                                f"(cache {root_dir(root)})")
    return Case(entry, str(log), np.load(ref).astype(np.float64), True)


def is_built(entry, *, size=128, spp=32, ref_spp=1024, root=None) -> bool:
    if entry.renderer == "builtin":
        return True
    return all(p.exists() for p in _paths(entry, size, spp, ref_spp, root))


def build(entry: Entry, *, size=128, spp=32, ref_spp=1024, root=None, threads=2) -> None:
    """Render an external scene's log and reference into the cache (nothing to do for a built-in one)."""
    if entry.renderer == "builtin":
        return
    log, ref = _paths(entry, size, spp, ref_spp, root)
    log.parent.mkdir(parents=True, exist_ok=True)
    if entry.renderer == "cycles":
        from corpus_external import build_cycles
        from mcrecon.renderers import blender as bl

        for seed, name in ((entry.seed, "log"), (entry.seed + 1, "ref")):
            build_cycles(entry.family, log.parent / f"{entry.family}_{size}_{name}.blend", size=size, seed=seed)
        if not ref.exists():
            t = time.perf_counter()
            img, _ = bl.render_reference(log.parent / f"{entry.family}_{size}_ref.blend", spp=ref_spp,
                                         threads=threads)
            np.save(ref, np.asarray(img, np.float32))
            print(f"  {entry.name}: reference {ref_spp} spp in {time.perf_counter() - t:.0f} s wall", flush=True)
        if not log.exists():
            t = time.perf_counter()
            bl.dump_cycles_log(log, log.parent / f"{entry.family}_{size}_log.blend", spp=spp, threads=threads,
                               features="all", overwrite=True)
            print(f"  {entry.name}: log {spp} spp in {time.perf_counter() - t:.0f} s wall", flush=True)
        return
    from corpus_external import build_mitsuba
    from mcrecon.renderers.mitsuba import MitsubaRenderer, drjit_cache_dir, dump_uniform_log, render_reference

    os.environ.setdefault("DRJIT_CACHE_DIR", drjit_cache_dir())
    renderer = MitsubaRenderer(build_mitsuba(entry.family, size), spp_per_pass=16)
    if not log.exists():
        t = time.perf_counter()
        dump_uniform_log(log, renderer, spp=spp, seed=entry.seed)
        print(f"  {entry.name}: log {spp} spp in {time.perf_counter() - t:.0f} s wall", flush=True)
    if not ref.exists():
        t = time.perf_counter()
        img = render_reference(renderer, spp=ref_spp, seed=987654)
        np.save(ref, np.asarray(img, np.float32))
        print(f"  {entry.name}: reference {ref_spp} spp in {time.perf_counter() - t:.0f} s wall", flush=True)


def _list():
    print(f"{'scene':28s} {'half':9s} {'features':8s} parameters / description")
    for e in _ENTRIES:
        print(f"{e.name:28s} {e.half:9s} {'yes' if e.features else 'no':8s} {e.description}")
    for h in HALVES:
        sel = [e for e in _ENTRIES if e.half == h]
        fam = sorted({e.family for e in sel if e.renderer == "builtin"})
        print(f"{h}: {len(sel)} scenes, {len(fam)} built-in families, "
              f"{sum(e.renderer == 'mitsuba' for e in sel)} Mitsuba, {sum(e.renderer == 'cycles' for e in sel)} Cycles")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--list", action="store_true", help="print the scenes, their half and parameters")
    ap.add_argument("--build", action="store_true", help="render the external scenes' logs and references")
    ap.add_argument("--only", default="", help="comma-separated entry names, families or renderers")
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--spp", type=int, default=32)
    ap.add_argument("--ref-spp", type=int, default=1024)
    ap.add_argument("--threads", type=int, default=2, help="Cycles' render threads")
    ap.add_argument("--root", default=None, help=f"cache directory (default ${ENV_DIR} or ~/.cache/mcrecon-corpus)")
    ap.add_argument("--one", default="", help=argparse.SUPPRESS)  # build one entry (a subprocess of --build)
    a = ap.parse_args(argv)
    if a.one:
        (e,) = scenes("all", [a.one])
        build(e, size=a.size, spp=a.spp, ref_spp=a.ref_spp, root=a.root, threads=a.threads)
        return
    if a.build:
        todo = [e for e in scenes("all", [x for x in a.only.split(",") if x] or None) if e.renderer != "builtin"
                and not is_built(e, size=a.size, spp=a.spp, ref_spp=a.ref_spp, root=a.root)]
        print(f"building {len(todo)} scene(s) into {root_dir(a.root)}", flush=True)
        for e in todo:
            # one process per scene: bpy and Dr.Jit keep global state, and a crash loses one scene only
            cmd = [sys.executable, __file__, "--one", e.name, "--size", str(a.size), "--spp", str(a.spp),
                   "--ref-spp", str(a.ref_spp), "--threads", str(a.threads)]
            if a.root:
                cmd += ["--root", a.root]
            t = time.process_time()
            r = subprocess.run(cmd)
            print(f"{e.name}: {'done' if r.returncode == 0 else f'FAILED ({r.returncode})'}", flush=True)
        return
    _list()


if __name__ == "__main__":
    main()
