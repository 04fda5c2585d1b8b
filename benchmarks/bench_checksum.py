"""Cost of the Fletcher-32 checksums of sample logs: write and read, with and without, in one run.

    python benchmarks/bench_checksum.py                  # 4 Mi samples (1024 x 1024 x 4 spp)
    python benchmarks/bench_checksum.py --samples 33554432 --repeat 1   # the 33.5 M-sample log (1024^2, 32 spp)

Writes the same float32 RGB log with the checksum filter (mcrecon's default)
and without it, then reads each back as mcrecon does (the streamed pixel
statistics of ``PixelStats.from_log``, and the raw rows through
``SampleLog.iter_into``).  Prints the best of ``--repeat`` times and the
ratios checksummed / plain.  File sizes differ by 4 bytes per chunk.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from mcrecon.io import read_log, reader as samplelog, write_log
from mcrecon.io import logformat as samplelog_logformat
from mcrecon.core.samples import DEFAULT_READ_ROWS
from mcrecon.core.stats import PixelStats


def _best(fn, repeat):
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def _raw_read(path):
    log = read_log(path)
    rows = DEFAULT_READ_ROWS
    bufs = [(np.empty((rows, 2), log.position_dtype), np.empty((rows, 3), log.value_dtype)) for _ in range(2)]
    for _ in log.iter_into(bufs):
        pass


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=1 << 22)
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    n, w = args.samples, args.size
    rng = np.random.default_rng(0)
    pos = (rng.random((n, 2), np.float32) * np.float32(w - 1e-3)).astype(np.float32)
    val = rng.random((n, 3), np.float32)
    saved = dict(samplelog_logformat._CHECKSUM)
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        for label, checksum in (("fletcher32", saved), ("plain", {})):
            path = Path(tmp) / f"{label}.h5"
            samplelog_logformat._CHECKSUM.clear()
            samplelog_logformat._CHECKSUM.update(checksum)
            try:
                t_write = _best(lambda: write_log(path, pos, val, width=w, height=w), args.repeat)
            finally:
                samplelog_logformat._CHECKSUM.clear()
                samplelog_logformat._CHECKSUM.update(saved)
            t_raw = _best(lambda: _raw_read(path), args.repeat)
            t_stats = _best(lambda: PixelStats.from_log(read_log(path)), args.repeat)
            rows[label] = (t_write, t_raw, t_stats, path.stat().st_size)
    print(f"{n} float32 RGB samples, {w}x{w} film, best of {args.repeat}")
    print(f"{'':12s} {'write s':>9s} {'raw read s':>11s} {'from_log s':>11s} {'MB':>8s}")
    for label, (a, b, c, size) in rows.items():
        print(f"{label:12s} {a:9.3f} {b:11.3f} {c:11.3f} {size / 1e6:8.1f}")
    f, p = rows["fletcher32"], rows["plain"]
    print(f"{'ratio':12s} {f[0] / p[0]:9.2f} {f[1] / p[1]:11.2f} {f[2] / p[2]:11.2f} {f[3] / p[3]:8.4f}")


if __name__ == "__main__":
    main()
