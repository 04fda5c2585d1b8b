"""Scale-out on Dask: batch and ingestion speed-ups, 1 vs 2 workers, measured in one run.

    python benchmarks/bench_distributed.py                    # 16 frames of 512^2, 32 spp, gem; 1024^2 ingestion
    python benchmarks/bench_distributed.py --size 128 --frames 4 --spp 8 --ingest-size 256   # quick

Prints ratios (same machine, same run), the scheduler overhead per task,
the per-frame cost and I/O, and an extrapolation to many workers.  Each
LocalCluster worker is one process running one task at a time with
MCRECON_THREADS=1, so "1 vs 2 workers" measures process scaling; the
1-worker run with 2 threads (the default on a 2-core machine) is shown
too.
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np


def _noop(x):
    return x


def _warm(log, out_dir, method):
    from mcrecon.distributed import denoise_frame

    denoise_frame(log, f"{out_dir}/warm-{os.getpid()}.exr", method, {})


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--frames", type=int, default=16)
    ap.add_argument("--spp", type=int, default=32)
    ap.add_argument("--method", default="gem")
    ap.add_argument("--ingest-size", type=int, default=1024)
    ap.add_argument("--ingest-spp", type=int, default=32)
    ap.add_argument("--dir", default=None, help="work directory (default: a temporary one, removed)")
    args = ap.parse_args()

    from mcrecon import distributed as D
    from mcrecon.renderers.scenes import get_scene, write_scene_log
    from mcrecon.stats import PixelStats

    work = Path(args.dir or tempfile.mkdtemp(prefix="mcrecon-bench-dist-"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        frames = work / "frames"
        frames.mkdir(exist_ok=True)
        scenes = ("soft_shadow", "caustic")
        t0 = time.perf_counter()
        for i in range(args.frames):
            write_scene_log(get_scene(scenes[i % 2]), frames / f"f{i:03d}.h5", width=args.size, height=args.size,
                            spp=args.spp, seed=i)
        log_bytes = sum(p.stat().st_size for p in frames.glob("*.h5"))
        print(f"{args.frames} frames {args.size}^2, {args.spp} spp: logs {log_bytes / 2**20:.0f} MiB "
              f"(written in {time.perf_counter() - t0:.1f} s)")

        times = {}
        for label, workers, threads in (("1 worker, 1 thread", 1, 1), ("2 workers, 1 thread each", 2, 1),
                                        ("1 worker, 2 threads", 1, 2)):
            with D.local_client(workers, threads=threads) as c:
                first = sorted(frames.glob("*.h5"))[0]
                c.run(_warm, str(first), str(work / "warm"), args.method)   # every worker: imports, numba caches
                t = time.perf_counter()
                res = D.denoise_many(sorted(frames.glob("*.h5")), method=args.method, client=c,
                                     out_dir=work / "out", force=True, progress=False)
                times[label] = time.perf_counter() - t
                assert res.ok, res.failed
                per = [r["seconds"] for r in res.records]
                if label.startswith("1 worker, 1"):
                    per_frame = float(np.median(per))
                    n = 1000
                    t = time.perf_counter()
                    c.gather(c.map(_noop, range(n), pure=False))
                    overhead = (time.perf_counter() - t) / n
            print(f"batch, {label}: {times[label]:.2f} s ({times[label] / args.frames:.3f} s/frame; "
                  f"median {np.median(per):.3f} s per frame on its worker)")
        r = times["1 worker, 1 thread"] / times["2 workers, 1 thread each"]
        r2 = times["1 worker, 2 threads"] / times["2 workers, 1 thread each"]
        print(f"batch speed-up, 2 workers vs 1 (1 thread each): {r:.2f}x; "
              f"vs 1 worker with 2 threads: {r2:.2f}x")
        exr = (work / "out").glob("*.exr")
        out_bytes = sum(p.stat().st_size for p in exr) / args.frames
        print(f"per frame: {per_frame:.3f} s of work (median, on a worker), reads {log_bytes / args.frames / 2**20:.1f} "
              f"MiB, writes {out_bytes / 2**10:.0f} KiB; scheduler overhead {overhead * 1e3:.2f} ms per task")
        for nw in (10, 100):
            # frames in parallel; the scheduler hands out tasks one after another; I/O is the
            # shared file system's: nw * (read + write) / per_frame bytes per second
            t_frame = per_frame + overhead * nw
            bw = nw * (log_bytes / args.frames + out_bytes) / per_frame / 2**20
            print(f"extrapolation to {nw} workers: {nw / t_frame * 60:.0f} frames/min if the file system "
                  f"delivers {bw:.0f} MiB/s (scheduler share {overhead * nw / t_frame:.1%})")

        # ---- ingestion of one big log
        big = work / "big.h5"
        write_scene_log(get_scene("soft_shadow"), big, width=args.ingest_size, height=args.ingest_size,
                        spp=args.ingest_spp, seed=99)
        print(f"\ningestion of {args.ingest_size}^2, {args.ingest_spp} spp ({big.stat().st_size / 2**20:.0f} MiB)")
        t = time.perf_counter()
        one = PixelStats.from_log(big)
        t_one = time.perf_counter() - t
        print(f"one process (PixelStats.from_log): {t_one:.2f} s")
        it = {}
        for workers in (1, 2):
            with D.local_client(workers, threads=1) as c:
                D.ingest(big, client=c, parts=2 * workers)                 # warm: imports, page cache
                t = time.perf_counter()
                st = D.ingest(big, client=c, parts=2 * workers)
                it[workers] = time.perf_counter() - t
            assert np.array_equal(st.count, one.count)
            print(f"distributed, {workers} worker(s): {it[workers]:.2f} s")
        print(f"ingestion speed-up, 2 workers vs 1: {it[1] / it[2]:.2f}x; 2 workers vs one process: "
              f"{t_one / it[2]:.2f}x")
    finally:
        if args.dir is None:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
