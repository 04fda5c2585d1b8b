"""Textured Mitsuba 3 scenes: what per-sample features buy, measured against high-spp references.

Builds three independent scenes programmatically (no files to download):

``floor_spheres``
    a checkerboard floor with a texel-noise bitmap, a glass and a metal
    sphere, lit by one small spherical light (sharp caustics and shadows);
``thin_lens``
    a thin-lens camera focused on a checkerboard plane in front of a plane of
    random nearest-filtered texels (defocus blur: noisy features);
``wall_floor``
    a checkerboard wall and floor with a diffuse sphere casting a soft shadow
    from a rectangular area light.

For each it renders (through the bridge, ``mcrecon.renderers.mitsuba``) a
uniform log of ``--spp`` (32) samples per pixel at ``--size`` (128) with the
per-sample features (albedo, shading normal, camera-space depth), and a
``--ref-spp`` (4096) reference with an independent seed; both are cached
under ``--root`` (delete the files to render again).  It then prints the
relative MSE (eps 0.01, ``mcrecon.core.metrics.relative_mse``) of

* ``box``: the pixel mean (the ratios' denominator);
* ``oidn``: Open Image Denoise 2 on the pixel means, colour only;
* ``oidn+aux``: OIDN with the pixel means of the albedo and normal features
  (noisy under defocus and anti-aliasing, so ``clean_aux=False``: OIDN
  prefilters them);
* every registered mcrecon method that runs on the log (``mcrecon.reconstruct``,
  default options), which uses the features if it declares them;

as ratios to box's (below 1 is better), with each method's reconstruction
time (CPU seconds of this process, ``time.process_time``: the machine may
be loaded).

Cost (2 cores shared with four other jobs, the run reported in
docs/mitsuba.md): 149 s wall, 58 s CPU for the first run (references at
128^2 x 4096 spp, ``max_depth`` 6: 24-71 s wall each; logs 1-4 s), 16 s
wall once cached (only the reconstructions).  ``--ref-spp 1024`` for a
quick look (its own noise then inflates the small relMSEs: by about
box's relMSE / 1024 * 32).

Usage::

    python benchmarks/mitsuba_textured.py --root /tmp/mitsuba_textured
    python benchmarks/mitsuba_textured.py --root DIR --scenes thin_lens --methods box,gem
    python benchmarks/mitsuba_textured.py --root DIR --seeds 3 --methods nfor,auto:feature_candidates=none,auto
    python benchmarks/mitsuba_textured.py --root DIR --seeds 3 --methods auto --adaptive auto
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(1, str(Path(__file__).resolve().parent))

from bench_features import _method  # noqa: E402  (name or name:key=value:... method specs)

SCENES = ("floor_spheres", "thin_lens", "wall_floor")


def _texels(n, seed):
    """An (n, n, 3) float32 texture of random grey-ish texels in [0.1, 0.9]."""
    rng = np.random.default_rng(seed)
    base = rng.uniform(0.1, 0.9, (n, n, 1))
    tint = rng.uniform(0.8, 1.0, (n, n, 3))
    return np.ascontiguousarray(base * tint, dtype=np.float32)


def build_scene(name: str, size: int) -> dict:
    """The Mitsuba scene dict of one benchmark scene at ``size`` x ``size``."""
    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")
    T = mi.ScalarTransform4f
    film = {"type": "hdrfilm", "width": size, "height": size, "rfilter": {"type": "box"}}
    checker = lambda c0, c1, k: {"type": "checkerboard", "color0": {"type": "rgb", "value": c0},  # noqa: E731
                                 "color1": {"type": "rgb", "value": c1}, "to_uv": T().scale([k, k, 1])}
    diffuse = lambda tex: {"type": "diffuse", "reflectance": tex}  # noqa: E731
    scene = {"type": "scene", "integrator": {"type": "path", "max_depth": 6}}
    if name == "floor_spheres":
        scene["sensor"] = {"type": "perspective", "fov": 40, "film": film,
                           "to_world": T().look_at(origin=[0, 2.2, 5.5], target=[0, 0.4, 0], up=[0, 1, 0])}
        scene["floor"] = {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(6),
                          "bsdf": diffuse({"type": "bitmap", "bitmap": mi.Bitmap(_texels(64, 1)),
                                           "filter_type": "nearest"})}
        scene["tiles"] = {"type": "rectangle",
                          "to_world": T().translate([0, 0.001, 1.2]).rotate([1, 0, 0], -90).scale([2.5, 1.0, 1]),
                          "bsdf": diffuse(checker([0.8, 0.75, 0.7], [0.1, 0.12, 0.15], 6))}
        scene["glass"] = {"type": "sphere", "center": [-0.9, 0.6, 0.3], "radius": 0.6,
                          "bsdf": {"type": "dielectric", "int_ior": 1.5}}
        scene["metal"] = {"type": "sphere", "center": [0.9, 0.6, -0.2], "radius": 0.6,
                          "bsdf": {"type": "roughconductor", "material": "Au", "alpha": 0.15}}
        scene["light"] = {"type": "sphere", "center": [1.5, 3.5, 1.5], "radius": 0.15,
                          "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [400, 380, 350]}}}
        scene["sky"] = {"type": "constant", "radiance": {"type": "rgb", "value": [0.03, 0.035, 0.05]}}
    elif name == "thin_lens":
        scene["sensor"] = {"type": "thinlens", "fov": 35, "film": film, "aperture_radius": 0.08,
                           "focus_distance": 4.0,
                           "to_world": T().look_at(origin=[0, 0, 4], target=[0, 0, 0], up=[0, 1, 0])}
        scene["checker"] = {"type": "rectangle", "to_world": T().translate([-0.5, 0, 0]).scale([0.9, 1.2, 1]),
                            "bsdf": diffuse(checker([0.85, 0.85, 0.8], [0.05, 0.05, 0.08], 8))}
        scene["texels"] = {"type": "rectangle", "to_world": T().translate([0.6, 0, -2.5]).scale([2.2, 2.2, 1]),
                           "bsdf": diffuse({"type": "bitmap", "bitmap": mi.Bitmap(_texels(32, 2)),
                                            "filter_type": "nearest"})}
        scene["light"] = {"type": "rectangle", "to_world": T().look_at(origin=[2.5, 2.5, 3], target=[0, 0, 0],
                                                                       up=[0, 1, 0]).scale(0.4),
                          "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [30, 30, 28]}}}
        scene["sky"] = {"type": "constant", "radiance": {"type": "rgb", "value": [0.05, 0.05, 0.06]}}
    elif name == "wall_floor":
        scene["sensor"] = {"type": "perspective", "fov": 45, "film": film,
                           "to_world": T().look_at(origin=[0, 1.2, 4.5], target=[0, 0.8, 0], up=[0, 1, 0])}
        scene["floor"] = {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(4),
                          "bsdf": diffuse(checker([0.7, 0.7, 0.7], [0.2, 0.2, 0.25], 10))}
        scene["wall"] = {"type": "rectangle", "to_world": T().translate([0, 2, -1.5]).scale([4, 2, 1]),
                         "bsdf": diffuse(checker([0.75, 0.6, 0.5], [0.15, 0.1, 0.1], 8))}
        scene["ball"] = {"type": "sphere", "center": [0.2, 0.5, 0.2], "radius": 0.5,
                         "bsdf": diffuse({"type": "rgb", "value": [0.3, 0.5, 0.7]})}
        scene["light"] = {"type": "rectangle", "to_world": T().translate([-1.0, 3.0, 1.0]).rotate([1, 0, 0], 90)
                          .scale([0.6, 0.6, 1]),
                          "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [12, 12, 11]}}}
    else:
        raise SystemExit(f"unknown scene {name!r}; valid: {', '.join(SCENES)}")
    return scene


def cached(root: Path, name: str, size: int, spp: int, ref_spp: int, seed: int = 1):
    """(log path, reference (H, W, 3) float64) of one scene, rendered once and cached under ``root``.

    ``seed`` is the log's (1: the first log, whose file name has no seed); the reference has its own."""
    from mcrecon.renderers.mitsuba import MitsubaRenderer, dump_uniform_log, render_reference

    root.mkdir(parents=True, exist_ok=True)
    log = root / (f"{name}_{size}_{spp}spp.h5" if seed == 1 else f"{name}_{size}_{spp}spp_seed{seed}.h5")
    ref_path = root / f"{name}_{size}_{ref_spp}spp_ref.npy"
    renderer = None
    if not log.exists() or not ref_path.exists():
        renderer = MitsubaRenderer(build_scene(name, size), spp_per_pass=16)
    if not log.exists():
        t0 = time.perf_counter()
        dump_uniform_log(log, renderer, spp=spp, seed=seed)
        print(f"  {name}: log {size}^2 x {spp} spp with features in {time.perf_counter() - t0:.1f} s wall")
    if not ref_path.exists():
        t0 = time.perf_counter()
        ref = render_reference(renderer, spp=ref_spp, seed=987654)
        np.save(ref_path, ref)
        print(f"  {name}: reference {ref_spp} spp in {time.perf_counter() - t0:.1f} s wall")
    return log, np.load(ref_path)


def oidn(color, albedo=None, normal=None):
    import pyoidn

    c = lambda a: np.ascontiguousarray(a, dtype=np.float32)  # noqa: E731
    if albedo is None:
        return np.asarray(pyoidn.denoise(c(color), hdr=True, quality="high"), np.float64)
    return np.asarray(pyoidn.denoise(c(color), c(np.clip(albedo, 0, 1)), c(np.clip(normal, -1, 1)), hdr=True,
                                     quality="high", clean_aux=False), np.float64)


def evaluate(log, ref, methods):
    """{name: (relMSE, CPU seconds or None)} for box, OIDN (+aux) and the mcrecon methods."""
    import mcrecon
    from mcrecon.core.metrics import relative_mse
    from mcrecon.core.stats import PixelStats

    out = {}
    t0 = time.process_time()
    st = PixelStats.from_log(mcrecon.read_log(log), features="all")
    out["box"] = (relative_mse(st.mean, ref, eps=0.01), time.process_time() - t0)
    try:
        import pyoidn  # noqa: F401
    except ImportError:
        print("  pyoidn not installed: OIDN rows skipped (pip install 'mcrecon[oidn]')")
    else:
        t0 = time.process_time()
        out["oidn"] = (relative_mse(oidn(st.mean), ref, eps=0.01), time.process_time() - t0)
        t0 = time.process_time()
        img = oidn(st.mean, st.features["albedo"].mean, st.features["normal"].mean)
        out["oidn+aux"] = (relative_mse(img, ref, eps=0.01), time.process_time() - t0)
    for m in methods:
        if m == "box":
            continue
        t0 = time.process_time()
        try:
            img = mcrecon.reconstruct(str(log), method=_method(m))
        except Exception as exc:  # a method that cannot run on this input: say why, go on
            print(f"  {m}: did not run: {type(exc).__name__}: {str(exc).splitlines()[0][:160]}")
            continue
        out[m] = (relative_mse(np.asarray(img, np.float64), ref, eps=0.01), time.process_time() - t0)
    return out


def adaptive(name, size, spp, seed, method, ref):
    """(relMSE, CPU s) of an adaptive run of ``method`` on one scene through the bridge (features on)."""
    import warnings

    import mcrecon
    from mcrecon.core.metrics import relative_mse
    from mcrecon.renderers.mitsuba import MitsubaRenderer

    renderer = MitsubaRenderer(build_scene(name, size), spp_per_pass=16)
    t0 = time.process_time()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = mcrecon.adapt(renderer, _method(method), spp=spp, seed=seed, progress=False)
    return relative_mse(np.asarray(res.image, np.float64), ref, eps=0.01), time.process_time() - t0


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--root", required=True, help="cache directory for the logs and references")
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--spp", type=int, default=32)
    ap.add_argument("--ref-spp", type=int, default=4096)
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--methods", default=None, help="mcrecon methods, each name or name:key=value:... "
                    "(default: every registered one)")
    ap.add_argument("--seeds", type=int, default=1, help="logs per scene (seeds 1..N; one reference): ratios "
                    "are means over them")
    ap.add_argument("--adaptive", default="", help="methods also run adaptively (mcrecon.adapt through the "
                    "bridge, features on, --spp on average, each seed's run seed): rows 'adapt NAME', their ratio "
                    "to the uniform box of the same seed's log")
    args = ap.parse_args(argv)

    import os

    from mcrecon.renderers.mitsuba import drjit_cache_dir, mitsuba_available

    os.environ.setdefault("DRJIT_CACHE_DIR", drjit_cache_dir())
    ok, why = mitsuba_available()
    if not ok:
        raise SystemExit(f"Mitsuba unavailable: {why}")
    import mcrecon

    methods = args.methods.split(",") if args.methods else list(mcrecon.available_methods())
    rows = {}
    for name in args.scenes.split(","):
        per_seed = []
        for seed in range(1, args.seeds + 1):
            log, ref = cached(Path(args.root), name, args.size, args.spp, args.ref_spp, seed)
            per_seed.append(evaluate(log, ref, methods))
            for m in (m for m in args.adaptive.split(",") if m):
                per_seed[-1][f"adapt {m}"] = adaptive(name, args.size, args.spp, seed, m, ref)
        # per method: the mean over the logs of its ratio to box's relMSE (box: its mean relMSE), mean CPU s
        rows[name] = {m: (float(np.mean([r[m][0] / (1.0 if m == "box" else r["box"][0]) for r in per_seed])),
                          float(np.mean([r[m][1] for r in per_seed])))
                      for m in per_seed[0] if all(m in r for r in per_seed)}
    names = ["box"] + [k for k in ("oidn", "oidn+aux") if any(k in r for r in rows.values())] \
        + [m for m in methods if m != "box"] + [f"adapt {m}" for m in args.adaptive.split(",") if m]
    print(f"\nrelMSE / relMSE(box), {args.size}^2, {args.spp} spp uniform, reference {args.ref_spp} spp, "
          f"mean over {args.seeds} log(s) (CPU s of the reconstruction in brackets)")
    print(f"{'method':10s}" + "".join(f"{n:>24s}" for n in rows))
    for m in names:
        cells = []
        for name, r in rows.items():
            if m not in r:
                cells.append(f"{'-':>24s}")
                continue
            e, t = r[m]
            val = f"{e:.4g} (box)" if m == "box" else f"{e:.3f}"
            cells.append(f"{val + f' [{t:.1f}]':>24s}")
        print(f"{m:10s}" + "".join(cells))
    return rows


if __name__ == "__main__":
    main()
