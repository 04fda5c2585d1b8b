"""Every method's default against the pixel mean, the paper's variant and the ceiling (issue 12).

For each scene and seed, one uniform render is reconstructed offline by
every method (default and ``variant="paper"``) and by ``box`` (the pixel
mean of the *same* samples); each adaptive method also runs adaptively at
the same spp (default and paper) and is compared with that uniform box.
The ceiling is :func:`mcrecon.experiments.oracle.oracle_ceiling`: the
better of the per-pixel expected-error choice among GEM's Gaussian scales
and the best single Gaussian (variance of the mean from an independent
render at ``--variance-spp``).

Printed: mean relative MSE (eps 0.01) over the seeds as ratios measured
in this run -- to box (``/box``; above 1 the method is worse than doing
nothing) and to the ceiling (``/ceil``).  Scenes: the built-in ones and,
with the Mitsuba extra installed, the Cornell box and a variant whose light
is 10x smaller and 100x brighter (``cornell_small_light``).

Run: ``python benchmarks/bench_defaults.py [--size 128] [--spp 32] [--seeds 0 1 2 3 4]
[--scenes soft_shadow hdr ...] [--methods gem awr splat ci] [--no-adaptive] [--no-mitsuba]
[--markdown]``
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np

from mcrecon.adaptive.run import adapt
from mcrecon.experiments.oracle import oracle_ceiling
from mcrecon.methods import available_methods, get_method
from mcrecon.core.metrics import relative_mse
from mcrecon.offline.reconstruction import reconstruct
from mcrecon.renderers import scenes
from mcrecon.core.samples import SampleSet
from mcrecon.core.stats import PixelStats


def _quiet(fn):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return fn()


class BuiltinScene:
    def __init__(self, name, size):
        self.name, self.size = name, size
        self.scene = scenes.get_scene(name)
        self.channels = self.scene.channels

    def reference(self):
        return scenes.reference_image(self.scene, self.size, self.size)

    def uniform(self, spp, seed):
        b = scenes.render_uniform(self.scene, width=self.size, height=self.size, spp=spp, seed=seed)
        return b.positions, b.values

    def renderer(self, seed):
        return scenes.SceneRenderer(self.scene, width=self.size, height=self.size, seed=seed)


def _cornell_dict(small_light: bool):
    import mitsuba as mi

    from mcrecon.renderers.mitsuba import _import_mitsuba
    _import_mitsuba("llvm_ad_rgb")
    d = mi.cornell_box()
    if small_light:
        # 10x smaller area (each side / sqrt 10), 100x the radiance: 10x the power
        light = d["light"]
        s = 1.0 / np.sqrt(10.0)
        light["to_world"] = light["to_world"] @ mi.ScalarTransform4f().scale([s, s, 1.0])
        light["emitter"]["radiance"]["value"] = [100.0 * v for v in light["emitter"]["radiance"]["value"]]
    return d


class MitsubaScene:
    def __init__(self, name, size, ref_spp, small_light):
        from mcrecon.renderers.mitsuba import MitsubaRenderer
        self.name, self.size, self.ref_spp = name, size, ref_spp
        self.channels = ("R", "G", "B")
        self._r = MitsubaRenderer(_cornell_dict(small_light), width=size, height=size)

    def reference(self):
        from mcrecon.renderers.mitsuba import render_reference
        return render_reference(self._r, spp=self.ref_spp, seed=12345)

    def uniform(self, spp, seed):
        from mcrecon.renderers.mitsuba_logs import _uniform_passes
        parts = list(_uniform_passes(self._r, spp, seed + 1))
        return (np.concatenate([p.positions for p in parts]), np.concatenate([p.values for p in parts]))

    def renderer(self, seed):
        return self._r


def variants_of(name):
    cls = type(get_method(name))
    return ["robust", "paper"] if cls.variants else [None]


def measure(scene, methods, spp, seeds, variance_spp, adaptive=True, oidn=False):
    ref = scene.reference()
    n = scene.size
    rows = {}  # (method, variant, mode) -> list of relMSE
    ceil = []
    t0 = time.perf_counter()
    hp, hv = scene.uniform(variance_spp, 10_000)
    hstats = PixelStats.from_samples(hp, hv, width=n, height=n, channels=scene.channels)
    for seed in seeds:
        pos, val = scene.uniform(spp, seed)
        stats = PixelStats.from_samples(pos, val, width=n, height=n, channels=scene.channels)
        ss = SampleSet(pos, val, width=n, height=n, channels=scene.channels)
        mean_var = hstats.sample_variance(undefined=0.0) / np.maximum(stats.count, 1)[..., None]
        ceil.append(oracle_ceiling(stats, ref, mean_var).ceiling)
        rows.setdefault(("box", None, "offline"), []).append(relative_mse(stats.mean, ref))
        if oidn:  # Intel OIDN on the pixel means (colour only), and auto with OIDN among its candidates
            from mcrecon.experiments.convergence import oidn_denoise
            from mcrecon.methods.auto.method import DEFAULT_CANDIDATES
            rows.setdefault(("oidn", None, "offline"), []).append(relative_mse(oidn_denoise(stats.mean), ref))
            with_oidn = DEFAULT_CANDIDATES if "oidn" in DEFAULT_CANDIDATES.split(",") else DEFAULT_CANDIDATES + ",oidn"
            m = get_method("auto", candidates=with_oidn)
            img = _quiet(lambda: reconstruct(ss, method=m))
            rows.setdefault(("auto+oidn", None, "offline"), []).append(relative_mse(img, ref))
        for name in methods:
            for variant in variants_of(name):
                opts = {} if variant is None else {"variant": variant}
                m = get_method(name, **opts)
                if name != "ci":  # ci's offline image is the pixel mean: box
                    src = ss if (m.requires.samples or m.requires.subpixels) else stats
                    img = _quiet(lambda: reconstruct(src, method=m))
                    rows.setdefault((name, variant, "offline"), []).append(relative_mse(img, ref))
                if adaptive and m.adaptive:
                    res = _quiet(lambda: adapt(scene.renderer(seed), m, spp=spp, seed=seed, progress=False,
                                               track_error=False))
                    rows.setdefault((name, variant, "adaptive"), []).append(relative_mse(res.image, ref))
    return {k: float(np.mean(v)) for k, v in rows.items()}, float(np.mean(ceil)), time.perf_counter() - t0


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--spp", type=int, default=32)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    ap.add_argument("--variance-spp", type=int, default=256)
    ap.add_argument("--ref-spp", type=int, default=1024, help="Mitsuba reference spp")
    ap.add_argument("--scenes", nargs="+", default=None)
    ap.add_argument("--methods", nargs="+", default=None)
    ap.add_argument("--no-adaptive", action="store_true")
    ap.add_argument("--no-mitsuba", action="store_true")
    ap.add_argument("--markdown", action="store_true", help="print a Markdown table (docs/which-method.md)")
    ap.add_argument("--no-oidn", action="store_true", help="leave out the OIDN columns (default: shown when "
                    "pyoidn is installed)")
    a = ap.parse_args(argv)
    methods = a.methods or [m for m in available_methods() if m != "box"]
    names = a.scenes or scenes.scene_names() + ([] if a.no_mitsuba else ["cornell", "cornell_small_light"])
    scene_objs = []
    for name in names:
        if name.startswith("cornell"):
            from mcrecon.renderers.mitsuba import mitsuba_available
            ok, why = mitsuba_available()
            if not ok:
                print(f"# {name}: skipped ({why})")
                continue
            scene_objs.append(MitsubaScene(name, a.size, a.ref_spp, name == "cornell_small_light"))
        else:
            scene_objs.append(BuiltinScene(name, a.size))
    cols = []
    for name in methods:
        for variant in variants_of(name):
            tag = name if variant in (None, "robust") else f"{name} paper"
            if name != "ci":
                cols.append((name, variant, "offline", tag))
            if not a.no_adaptive and get_method(name).adaptive:
                cols.append((name, variant, "adaptive", tag + " adapt"))
    from mcrecon.experiments.convergence import oidn_available
    with_oidn = not a.no_oidn and oidn_available()
    if with_oidn:
        cols += [("oidn", None, "offline", "OIDN"), ("auto+oidn", None, "offline", "auto+OIDN")]
    print(f"# {a.size}x{a.size}, {a.spp} spp, seeds {a.seeds}; mean relative MSE (eps 0.01) over seeds; "
          "ratio to box (pixel mean of the same uniform samples) / ratio to the Gaussian-selection ceiling")
    header = ["scene", "box relMSE", "ceiling/box"] + [c[3] for c in cols]
    if a.markdown:
        print("| " + " | ".join(header) + " |")
        print("|" + "---|" * len(header))
    else:
        print("  ".join(f"{h:>16s}" for h in header))
    worst, below_oidn, auto_oidn_worse = {}, [0, 0], []
    for sc in scene_objs:
        res, ceil, secs = measure(sc, methods, a.spp, a.seeds, a.variance_spp, adaptive=not a.no_adaptive,
                                  oidn=with_oidn)
        box = res[("box", None, "offline")]
        cells = [sc.name, f"{box:.3g}", f"{ceil / box:.2f}"]
        for name, variant, mode, tag in cols:
            e = res.get((name, variant, mode))
            if e is None:
                cells.append("-")
                continue
            cells.append(f"{e / box:.3g} / {e / ceil:.3g}")
            worst[tag] = max(worst.get(tag, 0.0), e / box)
        if with_oidn and ("auto", None, "offline") in res:
            below_oidn[0] += res[("auto", None, "offline")] < res[("oidn", None, "offline")]
            below_oidn[1] += 1
            if res[("auto+oidn", None, "offline")] > min(res[("oidn", None, "offline")], box):
                auto_oidn_worse.append(sc.name)
        if a.markdown:
            print("| " + " | ".join(cells) + " |", flush=True)
        else:
            print("  ".join(f"{c:>16s}" for c in cells) + f"   ({secs:.0f} s)", flush=True)
    print("# worst ratio to box per column: " + ", ".join(f"{k} {v:.3g}" for k, v in worst.items()))
    if with_oidn and "auto" in methods:
        print(f"# auto below OIDN on {below_oidn[0]} of {below_oidn[1]} scenes; auto+OIDN worse than the better of "
              f"OIDN and box on {len(auto_oidn_worse)}" + (f" ({', '.join(auto_oidn_worse)})" if auto_oidn_worse else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
