"""Ingest a 1024x1024, 32-spp log (33.5 M samples) into PixelStats.

Prints samples/s and the ratio to a raw h5py read of the same datasets in
the same run (read first once so both come from the page cache), and the
peak memory growth of the ingestion (tracemalloc: numpy allocations).
Targets (issue 2): >= 20 M samples/s, >= 0.5 of the raw read rate, memory
bounded by the image plus one chunk.

usage: python benchmarks/bench_ingest.py [LOG] [--size 1024x1024 --spp 32]
"""

import argparse
import os
import subprocess
import sys
import tempfile
import time
import tracemalloc

import h5py
import numpy as np

from mcrecon.io import read_log
from mcrecon.core.samples import DEFAULT_READ_ROWS
from mcrecon.core.stats import PixelStats


def raw_read(path, n):
    with h5py.File(path, "r") as f:
        for s in range(0, n, DEFAULT_READ_ROWS):
            f["positions"][s:s + DEFAULT_READ_ROWS]
            f["values"][s:s + DEFAULT_READ_ROWS]


def main():
    p = argparse.ArgumentParser()
    p.add_argument("log", nargs="?")
    p.add_argument("--size", default="1024x1024")
    p.add_argument("--spp", type=int, default=32)
    p.add_argument("--repeat", type=int, default=5, help="interleaved raw/ingest pairs")
    a = p.parse_args()
    path = a.log
    if path is None:
        path = os.path.join(tempfile.gettempdir(), f"mcrecon_bench_{a.size}_{a.spp}.h5")
        if not os.path.exists(path):
            subprocess.run([sys.executable, os.path.join(os.path.dirname(__file__), "..", "data_tools",
                                                         "make_benchmark_log.py"), path, "--size", a.size,
                            "--spp", str(a.spp)], check=True)
    log = read_log(path)
    n = log.n_samples
    # JIT warm-up with the log's own dtypes and both subpixel settings, outside the timings.
    head = next(log.iter_chunks(chunk_size=1000, stop=1000))
    for sub in (0, 4):
        PixelStats.from_log(log, subpixels=sub, chunk_size=1000) if n <= 1000 else \
            PixelStats.from_batches([(head.positions, head.values)], width=log.width, height=log.height,
                                    channels=log.channels, subpixels=sub)
    raw_read(path, n)  # page cache
    print(f"log: {path}  {log.width}x{log.height}, {n / 1e6:.1f} M samples")
    for sub in (0, 4):
        ratios, rates = [], []
        for _ in range(a.repeat):  # interleaved pairs: both sides see the same machine load
            t = time.perf_counter(); raw_read(path, n); t_raw = time.perf_counter() - t
            t = time.perf_counter(); st = PixelStats.from_log(log, subpixels=sub); dt = time.perf_counter() - t
            assert st.n_samples == n
            ratios.append(t_raw / dt)
            rates.append(n / dt / 1e6)
        tracemalloc.start()
        st = PixelStats.from_log(log, subpixels=sub)
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        image_bytes = sum(v.nbytes for v in vars(st).values() if isinstance(v, np.ndarray))
        print(f"ingest subpixels={sub}: median {np.median(rates):.1f} M samples/s (range {min(rates):.1f}-"
              f"{max(rates):.1f}); ratio to the raw h5py read in the same pair: median {np.median(ratios):.2f} "
              f"(range {min(ratios):.2f}-{max(ratios):.2f}, {a.repeat} pairs); peak memory {peak / 2**20:.0f} MiB "
              f"(statistics {image_bytes / 2**20:.0f} MiB + two read buffers of "
              f"{DEFAULT_READ_ROWS * 20 / 2**20:.0f} MiB)")


if __name__ == "__main__":
    main()
