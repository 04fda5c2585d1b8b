"""OIDN 2.5 on the cleaned pixel means (mcrecon.core.cleaning.clean_samples) against OIDN on the raw ones.

On every built-in scene (exact references), 128^2 and 32 spp by default,
with features: relMSE (mcrecon.core.metrics, eps 0.01) of OIDN
(``pyoidn.denoise(rgb, hdr=True)``, colour only, and with the pixel means
of albedo (clipped to [0, 1]) and normal) given the raw pixel means and
given the cleaned ones, averaged over seeds.  Printed per scene: the
pixel mean's relMSE, OIDN's ratio to it, and the ratios cleaned / raw
(below 1: cleaning helps OIDN), the share of the luminance that moved and
the cleaning's time.

    python benchmarks/bench_cleaning.py [--size 128] [--spp 32] [--seeds 1,2,3] [--scenes a,b] [--k-min 4]
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT)]

import mcrecon  # noqa: E402
from mcrecon.core.cleaning import clean_samples  # noqa: E402
from mcrecon.core.metrics import relative_mse  # noqa: E402
from mcrecon.renderers.scenes import reference_image, render_uniform, scene_names  # noqa: E402


def _f32(a):
    return np.ascontiguousarray(a, dtype=np.float32)


def _means(pix, values, n, shape):
    h, w = shape
    s = np.stack([np.bincount(pix, weights=values[:, c], minlength=h * w) for c in range(values.shape[1])], 1)
    return (s / np.maximum(n, 1)[:, None]).reshape(h, w, -1)


def run_scene(scene, size, spp, seed, k_min):
    import pyoidn
    b = render_uniform(scene, width=size, height=size, spp=spp, seed=seed, features=True)
    pos, val = np.asarray(b.positions), np.asarray(b.values)
    pix = np.floor(pos[:, 1]).astype(np.int64) * size + np.floor(pos[:, 0]).astype(np.int64)
    n = np.bincount(pix, minlength=size * size)
    ref = reference_image(scene, size, size)
    albedo = np.clip(_means(pix, np.asarray(b.features["albedo"]), n, (size, size)), 0.0, 1.0)
    normal = _means(pix, np.asarray(b.features["normal"]), n, (size, size))
    t0 = time.perf_counter()
    c = clean_samples(mcrecon.SampleSet(pos, val, width=size, height=size), k_min=k_min)
    t_clean = time.perf_counter() - t0

    def err(img):
        return relative_mse(np.asarray(img, np.float64), ref)

    out = {"box": err(c.raw_mean), "moved": c.moved_fraction, "time": t_clean}
    for tag, img in (("raw", c.raw_mean), ("clean", c.mean)):
        out[f"oidn_{tag}"] = err(pyoidn.denoise(_f32(img), hdr=True, quality="high"))
        out[f"aux_{tag}"] = err(pyoidn.denoise(_f32(img), _f32(albedo), _f32(normal), hdr=True, quality="high"))
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--spp", type=int, default=32)
    ap.add_argument("--seeds", default="1,2,3")
    ap.add_argument("--scenes", default=",".join(scene_names()))
    ap.add_argument("--k-min", type=int, default=4)
    a = ap.parse_args(argv)
    try:
        import pyoidn  # noqa: F401
    except ImportError:
        print("bench_cleaning: needs pyoidn (pip install pyoidn)")
        return 1
    warnings.simplefilter("ignore", mcrecon.errors.McreconWarning)
    seeds = [int(s) for s in a.seeds.split(",")]
    print(f"# {a.size}^2, {a.spp} spp, seeds {seeds}, k_min {a.k_min}; relMSE averaged over seeds")
    print("| scene | box relMSE | oidn/box | oidn+aux/box | oidn clean/raw | oidn+aux clean/raw | moved | clean s |")
    print("|---|---|---|---|---|---|---|---|")
    worst = []
    for scene in a.scenes.split(","):
        rs = [run_scene(scene, a.size, a.spp, s, a.k_min) for s in seeds]
        m = {k: float(np.mean([r[k] for r in rs])) for k in rs[0]}
        r_o, r_a = m["oidn_clean"] / m["oidn_raw"], m["aux_clean"] / m["aux_raw"]
        worst.append(max(r_o, r_a))
        print(f"| {scene} | {m['box']:.4g} | {m['oidn_raw'] / m['box']:.3f} | {m['aux_raw'] / m['box']:.3f} | "
              f"{r_o:.3f} | {r_a:.3f} | {m['moved']:.2g} | {m['time']:.2f} |", flush=True)
    print(f"# worst clean/raw ratio over scenes: {max(worst):.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
