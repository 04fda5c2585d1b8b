"""Cost of the Fletcher-32 checksums of sample logs: write and read, with and without, in one run.

    python benchmarks/bench_checksum.py                  # 4 Mi samples (1024 x 1024 x 4 spp)
    python benchmarks/bench_checksum.py --samples 33554432 --repeat 1   # the 33.5 M-sample log (1024^2, 32 spp)

Writes the same float32 RGB log with the checksum filter (mcrecon's default)
and without it, then reads each back as mcrecon does (the streamed pixel
statistics of ``PixelStats.from_log``, and the raw rows through
``SampleLog.iter_into``).  Prints the best of ``--repeat`` times and the
ratios checksummed / plain.  File sizes differ by 4 bytes per chunk.

``--alternatives``: the adaptive driver's case instead -- ``--rounds``
appended rounds (resizable chunked datasets of the log's chunk size,
h5py directly) -- in CPU seconds (``time.process_time``: the machine may
be loaded), for the ways to detect a damaged sample: HDF5's Fletcher-32
filter per chunk (the log format's), no checksum, and a checksum the
application would compute per round over the bytes written (zlib's CRC-32
and Adler-32, each over positions and values), written and verified on a
full read.
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


def _cpu_best(fn, repeat):
    best = float("inf")
    for _ in range(repeat):
        t0 = time.process_time()
        fn()
        best = min(best, time.process_time() - t0)
    return best


def alternatives(n: int, rounds: int, repeat: int) -> None:
    """CPU seconds to append ``n`` samples in ``rounds`` rounds and read them back, per checksum."""
    import zlib

    import h5py

    from mcrecon.io.logformat import APPEND_CHUNK_ROWS

    rng = np.random.default_rng(0)
    pos = (rng.random((n, 2), np.float32) * np.float32(511.9)).astype(np.float32)
    val = rng.random((n, 3), np.float32)
    m = n // rounds
    chunk = APPEND_CHUNK_ROWS
    ways = {"fletcher32 (HDF5 filter, per chunk)": ({"fletcher32": True}, None),
            "none": ({}, None),
            "CRC-32 per round (zlib, application)": ({}, zlib.crc32),
            "Adler-32 per round (zlib, application)": ({}, zlib.adler32)}
    print(f"{n} float32 RGB samples appended in {rounds} rounds of {m} (chunks of {chunk} rows), "
          f"best of {repeat}, CPU seconds")
    print(f"{'':40s} {'write':>8s} {'read+verify':>12s} {'write ratio':>12s} {'read ratio':>11s}")
    res = {}
    with tempfile.TemporaryDirectory() as tmp:
        for label, (flt, fn) in ways.items():
            path = Path(tmp) / "a.h5"

            def write():
                with h5py.File(path, "w") as f:
                    dp = f.create_dataset("positions", (0, 2), np.float32, maxshape=(None, 2), chunks=(chunk, 2),
                                          **flt)
                    dv = f.create_dataset("values", (0, 3), np.float32, maxshape=(None, 3), chunks=(chunk, 3),
                                          **flt)
                    sums = []
                    for k in range(rounds):
                        a, b = pos[k * m:(k + 1) * m], val[k * m:(k + 1) * m]
                        for d, x in ((dp, a), (dv, b)):
                            d.resize(d.shape[0] + m, axis=0)
                            d[-m:] = x
                        if fn is not None:
                            sums.append((fn(a.data), fn(b.data)))
                        f.flush()
                    if fn is not None:
                        f["sums"] = np.asarray(sums, np.uint32)

            def read():
                with h5py.File(path, "r") as f:
                    a = f["positions"][:]
                    b = f["values"][:]
                    if fn is not None:
                        want = f["sums"][:]
                        for k in range(rounds):
                            got = (fn(a[k * m:(k + 1) * m].data), fn(b[k * m:(k + 1) * m].data))
                            if tuple(want[k]) != got:
                                raise RuntimeError("checksum mismatch")

            res[label] = (_cpu_best(write, repeat), _cpu_best(read, repeat))
    pw, pr = res["none"]
    for label, (w, r) in res.items():
        print(f"{label:40s} {w:8.3f} {r:12.3f} {w / pw:12.2f} {r / pr:11.2f}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=1 << 22)
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--alternatives", action="store_true", help="the appended-rounds comparison of checksums")
    ap.add_argument("--rounds", type=int, default=8)
    args = ap.parse_args()
    if args.alternatives:
        alternatives(args.samples, args.rounds, args.repeat)
        return
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
