"""What per-sample features are worth on the textured built-in scenes: relMSE of each method over the pixel mean's.

Run (from the checkout, so that its mcrecon is imported):
      PYTHONPATH=. python benchmarks/bench_features.py [--size 128] [--spp 32] [--seeds 3]
                   [--scenes checker_wall,checker_spot,checker_dof] [--methods gem,awr,splat,nfor,auto]

For each textured scene (exact colour reference, per-sample albedo, normal
and depth) and seed, one uniform log of ``spp`` jittered samples per pixel
is reconstructed by

* ``box``: the pixel mean, the baseline every ratio divides by;
* mcrecon's methods with the samples and their features (default gem,
  awr, splat, nfor, auto without its feature candidates
  ``auto:feature_candidates=none``, and auto);
* OIDN colour-only: ``pyoidn.denoise(box, hdr=True, quality="high")``;
* OIDN + features: ``pyoidn.denoise(box, albedo, normal, hdr=True,
  quality="high")`` with the *pixel means* of the per-sample albedo and
  normal (noisy where the scene is defocused, so ``clean_aux`` is off);
  also with the albedo alone;
* an oracle row, OIDN with the scene's exact feature references
  (:func:`mcrecon.renderers.scenes.feature_reference`) and
  ``clean_aux=True``: what noise-free features would give.

It prints, per scene and method, the mean over seeds of relMSE / relMSE(box)
(relMSE as :func:`mcrecon.core.metrics.relative_mse`, eps = 0.01) with its
standard error over seeds, the mean relMSE itself, and the CPU time
(``time.process_time``: the machine is shared) of one reconstruction.
Lower than 1 means better than the pixel mean.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

import mcrecon
from mcrecon.core.metrics import relative_mse
from mcrecon.core.samples import SampleSet
from mcrecon.core.stats import PixelStats
from mcrecon.renderers import scenes as S


def _oidn(color, albedo=None, normal=None, clean_aux=False):
    import pyoidn

    f32 = lambda a: None if a is None else np.ascontiguousarray(a, dtype=np.float32)  # noqa: E731
    # OIDN wants albedo in [0, 1] (the scenes' are) and normals in [-1, 1] (pixel means of unit vectors are)
    out = pyoidn.denoise(f32(color), f32(albedo), f32(normal), hdr=True, quality="high", clean_aux=clean_aux)
    return np.asarray(out, dtype=np.float64)


def _method(spec: str):
    """``name`` or ``name:key=value:key=value`` (e.g. ``auto:feature_candidates=none``)."""
    name, *opts = spec.split(":")
    kw = dict(o.split("=", 1) for o in opts)
    return mcrecon.get_method(name, **kw) if kw else name


def run(scenes, methods, size, spp, seeds):
    rows = {}
    for scene in scenes:
        ref = S.reference_image(scene, size, size)
        fref = S.feature_reference(scene, size, size)
        for seed in range(seeds):
            b = S.render_uniform(scene, width=size, height=size, spp=spp, seed=seed, features=True)
            st = PixelStats.from_samples(b.positions, b.values, width=size, height=size, features=b.features)
            # the methods get the samples (splat and awr filter them), with their features
            src = SampleSet(b.positions, b.values, width=size, height=size, features=b.features)
            box = st.mean
            e_box = relative_mse(box, ref)
            out = {}
            for m in methods:
                method = _method(m)
                mcrecon.reconstruct(src, method=method)   # compile / warm (not timed)
                t = time.process_time()
                img = mcrecon.reconstruct(src, method=method)
                out[m] = (relative_mse(img, ref), time.process_time() - t)
            alb, nrm = st.features["albedo"].mean, st.features["normal"].mean
            for label, args, kw in (("oidn", (box,), {}), ("oidn+alb", (box, alb), {}),
                                    ("oidn+alb+nrm", (box, alb, nrm), {}),
                                    ("oidn+exact aux", (box, fref["albedo"], fref["normal"]), {"clean_aux": True})):
                t = time.process_time()
                img = _oidn(*args, **kw)
                out[label] = (relative_mse(img, ref), time.process_time() - t)
            out["box"] = (e_box, 0.0)
            for label, (e, dt) in out.items():
                rows.setdefault((scene, label), []).append((e / e_box, e, dt))
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--spp", type=int, default=32)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--scenes", default="checker_wall,checker_spot,checker_dof")
    ap.add_argument("--methods", default="gem,awr,splat,nfor,auto:feature_candidates=none,auto",
                    help="comma-separated; name:key=value:... passes options")
    a = ap.parse_args()
    scenes = [s for s in a.scenes.split(",") if s]
    methods = [m for m in a.methods.split(",") if m]
    rows = run(scenes, methods, a.size, a.spp, a.seeds)
    print(f"{a.size}x{a.size}, {a.spp} spp, {a.seeds} seeds; ratio = relMSE / relMSE(box), mean +- s.e. over seeds; "
          "CPU seconds per reconstruction (process_time)")
    w = max(14, *(len(m) for m in methods))
    print(f"{'scene':14s} {'method':{w}s} {'ratio':>16s} {'relMSE':>10s} {'cpu s':>7s}")
    for (scene, label), vals in rows.items():
        v = np.array(vals)
        se = v[:, 0].std(ddof=1) / np.sqrt(len(v)) if len(v) > 1 else float("nan")
        print(f"{scene:14s} {label:{w}s} {v[:, 0].mean():8.3f} +- {se:5.3f} {v[:, 1].mean():10.5f} "
              f"{v[:, 2].mean():7.2f}")


if __name__ == "__main__":
    main()
