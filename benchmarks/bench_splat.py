"""Throughput of the splat scatter loop against a plain ``np.add.at`` splat.

Both splat the same samples (jittered, sorted by pixel as a renderer's
reply is) with the same normalised Epanechnikov footprints into the same
RGB image; the ratio is measured in the same run, so machine load cancels
to first order.  Target (issue 5): >= 5 M samples/s at a mean kernel
radius of about 2 pixels.

Run: ``python benchmarks/bench_splat.py [--size 512] [--spp 8] [--radius 2]``
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from mcrecon.methods.splat import _BOUNDARY_CODE, _splat_loop, splat
from mcrecon.protocol import jittered_positions


def add_at_splat(pos, val, radius, width, height):
    """Baseline: normalised Epanechnikov footprints scattered with np.add.at, one offset at a time
    (interior normalisation, the renormalize remedy at the border)."""
    out = np.zeros((height, width, val.shape[1]))
    rmax = int(np.ceil(radius.max())) + 1
    cx = np.floor(pos[:, 0]).astype(np.int64)
    cy = np.floor(pos[:, 1]).astype(np.int64)
    offs = [(dx, dy) for dy in range(-rmax, rmax + 1) for dx in range(-rmax, rmax + 1)]
    wsum = np.zeros(pos.shape[0])
    ws = []
    for dx, dy in offs:
        ix, iy = cx + dx, cy + dy
        q = ((ix + 0.5 - pos[:, 0]) ** 2 + (iy + 0.5 - pos[:, 1]) ** 2) / radius ** 2
        w = np.where((q < 1) & (ix >= 0) & (ix < width) & (iy >= 0) & (iy < height), 1 - q, 0.0)
        ws.append(w)
        wsum += w
    inv = np.where(wsum > 0, 1.0 / np.where(wsum > 0, wsum, 1.0), 0.0)
    for (dx, dy), w in zip(offs, ws):
        ix, iy = cx + dx, cy + dy
        keep = w > 0
        np.add.at(out, (iy[keep], ix[keep]), val[keep] * (w[keep] * inv[keep])[:, None])
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--spp", type=int, default=8)
    ap.add_argument("--radius", type=float, default=2.0, help="mean kernel radius in pixels")
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args(argv)
    rng = np.random.default_rng(0)
    w = h = a.size
    pos = jittered_positions(np.full((h, w), a.spp), rng)
    n = pos.shape[0]
    val = rng.random((n, 3))
    # radii spread around the mean (0.5x .. 1.5x), as variable widths are
    radius = a.radius * (0.5 + rng.random(n))
    diam = 2.0 * radius

    splat(pos, val, diam, width=w, height=h, boundary="renormalize")  # JIT warm-up (both paths)
    best = best_serial = best_cpu = np.inf
    for _ in range(a.repeat):
        t = time.perf_counter()
        ours = splat(pos, val, diam, width=w, height=h, boundary="renormalize")
        best = min(best, time.perf_counter() - t)
        out = np.zeros_like(ours)
        ones = np.ones(n)
        t = time.perf_counter()
        c = time.process_time()
        _splat_loop(pos, val, ones, radius, _BOUNDARY_CODE["renormalize"], out)
        best_serial = min(best_serial, time.perf_counter() - t)
        best_cpu = min(best_cpu, time.process_time() - c)
    t = time.perf_counter()
    base = add_at_splat(pos, val, radius, w, h)
    t_base = time.perf_counter() - t
    err = np.abs(ours - base).max() / np.abs(base).max()
    print(f"samples: {n} ({w}x{h}, {a.spp} spp), mean radius {radius.mean():.2f} px, RGB float64")
    print(f"splat (numba, 2 blocks): {best:8.3f} s  {n / best / 1e6:8.2f} M samples/s")
    print(f"scatter loop, 1 thread:  {best_serial:8.3f} s  {n / best_serial / 1e6:8.2f} M samples/s "
          f"({n / best_cpu / 1e6:.2f} M per CPU second; load average {os.getloadavg()[0]:.1f} on "
          f"{os.cpu_count()} cores)")
    print(f"np.add.at splat:         {t_base:8.3f} s  {n / t_base / 1e6:8.2f} M samples/s")
    print(f"speed-up over np.add.at: {t_base / best:.1f}x (1 thread: {t_base / best_serial:.1f}x)   "
          f"max relative difference: {err:.2e}")
    print(f"target >= 5 M samples/s (wall, best path): "
          f"{'met' if n / min(best, best_serial) >= 5e6 else 'NOT met'}")


if __name__ == "__main__":
    main()
