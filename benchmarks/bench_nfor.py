"""nfor against box, the cross-bilateral filter, colour-only NL-means and OIDN (+albedo +normal).

On the synthetic textured scene of ``tests/nfor_scene.py`` (checkerboard
albedo x smooth shading, exponential per-sample noise, a defocused band
whose features are noisy), relMSE (mcrecon.core.metrics, eps 0.01) of each
method for 3 seeds, and nfor's reconstruction time (CPU time of the
process, and wall time) at 128^2 and 512^2, warm (after a first run).
With ``--scenes``, instead: the built-in textured scenes (checker_wall,
checker_dof, checker_spot: exact reference, per-sample albedo, normal,
depth), relMSE / box of nfor (its default and variant='paper') beside the cross-bilateral filter, colour-only
NL-means and OIDN + albedo + normal (pixel means of the features, as
benchmarks/bench_features.py) for 3 seeds, and nfor's CPU time per
reconstruction; with ``--mitsuba-root`` the same for the three textured
Mitsuba scenes of benchmarks/mitsuba_textured.py.

    python benchmarks/bench_nfor.py [--size 128] [--spp 32] [--big 512] [--big-spp 16]
    python benchmarks/bench_nfor.py --scenes checker_wall,checker_dof,checker_spot [--size 128] [--spp 32]
    python benchmarks/bench_nfor.py --mitsuba-root DIR [--seeds 3]   (needs the Mitsuba extra)
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests"), str(ROOT / "benchmarks")]  # this checkout, the test scene

import mcrecon  # noqa: E402
from mcrecon.core.fill import mean_variance_policy  # noqa: E402
from mcrecon.core.halves import split_halves  # noqa: E402
from mcrecon.core.metrics import relative_mse  # noqa: E402
from mcrecon.filters.cross_bilateral import cross_bilateral  # noqa: E402
from mcrecon.methods.auto.nlmeans import nlmeans_cross  # noqa: E402
from mcrecon.methods.nfor.method import feature_planes  # noqa: E402
from nfor_scene import scene_reference, scene_samples  # noqa: E402


def _oidn(colour, albedo, normal):
    try:
        import pyoidn
    except ImportError:
        return None
    f = lambda a: np.ascontiguousarray(a, dtype=np.float32)  # noqa: E731
    return np.asarray(pyoidn.denoise(f(colour), f(np.clip(albedo, 0, 1)), f(normal), hdr=True, quality="high"),
                      dtype=np.float64)


def candidates(ss):
    h = split_halves(ss, features="all")
    st = h.a.copy().merge(h.b)
    var = mean_variance_policy(st)
    fa, fb, fv = feature_planes(h.a, h.b, st)
    feat = 0.5 * (fa + fb)
    na, _, nb, _ = nlmeans_cross(h.a.mean, mean_variance_policy(h.a), h.a.count, h.b.mean,
                                 mean_variance_policy(h.b), h.b.count, radius=7, patch=3)
    out = {"box": st.mean, "cross_bilateral": cross_bilateral(st.mean, var, feat, fv), "nlm_colour": 0.5 * (na + nb),
           "oidn_albedo_normal": _oidn(st.mean, st.features["albedo"].mean, st.features["normal"].mean)}
    t0, w0 = time.process_time(), time.perf_counter()
    out["nfor"] = mcrecon.reconstruct(ss, method="nfor")
    cpu, wall = time.process_time() - t0, time.perf_counter() - w0
    out["nfor_paper"] = mcrecon.reconstruct(ss, method="nfor", variant="paper")  # the paper's qualitative result
    return out, cpu, wall


def _table(label_sources, header):
    """relMSE / box of nfor, the cross-bilateral filter, colour-only NL-means and OIDN + aux, per scene:
    ``label_sources`` yields (scene, [(source, reference), ...])."""
    mcrecon.reconstruct(scene_samples(32, 32, 4, seed=9, square=4), method="nfor")  # compile / load the cache
    print(header + "; relMSE / relMSE(box), mean over seeds (min-max); nfor CPU s (process_time)")
    cols = ("nfor", "nfor_paper", "cross_bilateral", "nlm_colour", "oidn_albedo_normal")
    for scene, pairs in label_sources:
        rows = []
        for src, ref in pairs:
            out, cpu, _ = candidates(src)
            e_box = relative_mse(out["box"], ref)
            rows.append([e_box] + [relative_mse(out[c], ref) / e_box if out[c] is not None else np.nan
                                   for c in cols] + [cpu])
        r = np.array(rows)
        fmt = lambda c: f"{r[:, c].mean():.3f} ({r[:, c].min():.3f}-{r[:, c].max():.3f})"  # noqa: E731
        print(f"  {scene:14s} box relMSE {r[:, 0].mean():.5f}  " + "  ".join(f"{c} {fmt(i + 1)}"
                                                                            for i, c in enumerate(cols))
              + f"  nfor cpu {r[:, -1].mean():.2f} s", flush=True)


def scenes_table(scenes, size, spp, seeds=(0, 1, 2)):
    from mcrecon.core.samples import SampleSet
    from mcrecon.renderers import scenes as S

    def sources(scene):
        ref = S.reference_image(scene, size, size)
        for seed in seeds:
            b = S.render_uniform(scene, width=size, height=size, spp=spp, seed=seed, features=True)
            yield SampleSet(b.positions, b.values, width=size, height=size, features=b.features), ref

    _table(((sc, sources(sc)) for sc in scenes), f"built-in scenes, {size}^2, {spp} spp, seeds {list(seeds)}")


def mitsuba_table(root, seeds):
    """The textured Mitsuba scenes of benchmarks/mitsuba_textured.py (its cached logs, rendered if absent)."""
    import mitsuba_textured as mt

    def sources(name):
        for seed in range(1, seeds + 1):
            log, ref = mt.cached(Path(root), name, 128, 32, 4096, seed)
            yield mcrecon.read_log(log), ref

    _table(((n, sources(n)) for n in mt.SCENES), f"Mitsuba textured scenes, 128^2, 32 spp, {seeds} logs")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--spp", type=int, default=32)
    ap.add_argument("--big", type=int, default=512)
    ap.add_argument("--big-spp", type=int, default=16)
    ap.add_argument("--scenes", default="", help="comma-separated built-in textured scenes: the scene table only")
    ap.add_argument("--mitsuba-root", default="", help="cache directory of benchmarks/mitsuba_textured.py: the "
                    "table of its three textured Mitsuba scenes only")
    ap.add_argument("--seeds", type=int, default=3, help="with --mitsuba-root: logs per scene")
    a = ap.parse_args(argv)
    if a.mitsuba_root:
        mitsuba_table(a.mitsuba_root, a.seeds)
        return
    if a.scenes:
        scenes_table([s for s in a.scenes.split(",") if s], a.size, a.spp)
        return
    sq = max(a.size // 8, 2)
    ref = scene_reference(a.size, a.size, square=sq)
    mcrecon.reconstruct(scene_samples(32, 32, 4, seed=9, square=4), method="nfor")  # compile / load the cache
    rows = []
    for seed in (0, 1, 2):
        out, cpu, wall = candidates(scene_samples(a.size, a.size, a.spp, seed=seed, square=sq))
        e = {k: (relative_mse(v, ref) if v is not None else np.nan) for k, v in out.items()}
        rows.append(e)
        print(f"seed {seed}: " + "  ".join(f"{k} {v:.5f}" for k, v in e.items())
              + f"   nfor {a.size}^2 x {a.spp} spp: cpu {cpu:.2f} s wall {wall:.2f} s", flush=True)
    names = list(rows[0])
    print(f"\nrelMSE / box, {a.size}^2, {a.spp} spp, mean over 3 seeds (min-max):")
    for k in names:
        r = np.array([row[k] / row["box"] for row in rows])
        print(f"  {k:20s} {r.mean():.4f} ({r.min():.4f}-{r.max():.4f})")
    if a.big:
        ss = scene_samples(a.big, a.big, a.big_spp, seed=0, square=max(a.big // 8, 2))
        t0, w0 = time.process_time(), time.perf_counter()
        mcrecon.reconstruct(ss, method="nfor")
        print(f"\nnfor {a.big}^2 x {a.big_spp} spp: cpu {time.process_time() - t0:.1f} s, "
              f"wall {time.perf_counter() - w0:.1f} s")


if __name__ == "__main__":
    main()
