"""Scale-out on Dask: batch and ingestion speed-ups, 1 vs 2 workers, against this machine's ceiling, in one run.

    python benchmarks/bench_distributed.py                    # 16 frames of 512^2, 32 spp, gem; 1024^2 ingestion
    python benchmarks/bench_distributed.py --size 128 --frames 4 --spp 8 --ingest-size 256   # quick

Prints, all measured in this run:

* the machine ceiling: two copies of a pure-CPU single-thread loop at once
  against one, and two copies of a memory-streaming numpy loop at once
  against one (throughput ratios: 2.0 is perfect scaling);
* the same frames in plain processes without Dask (1 vs 2 processes, one
  thread each): the workload's own ceiling on this machine;
* the batch on a LocalCluster, 1 vs 2 workers with one thread each (and 1
  worker with 2 threads, the default on 2 cores; and 2 workers with Dask's
  default housekeeping, profiler on and 20 ms tick, which mcrecon's
  local_client turns down); Dask's own CPU during each batch (client
  process with the scheduler and the nannies, workers' event loops); the
  scheduler overhead per task, the per-frame cost and I/O, and an
  extrapolation to many workers;
* ingestion of one big log: one process, and 1 vs 2 workers.

Times are steady state: each worker has imported mcrecon and loaded its
compiled kernels (one frame each) before the clock starts; the cluster
start and that warm-up are printed separately.  Every configuration runs
``--repeat`` times, alternating (1, 2, 1, 2, ...), and the fastest run of
each counts: on a shared virtual machine a single run can be 30 % slow.
Logs are written to ``--dir`` and reused when they are there already.
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np


# ---------------------------------------------------------------- machine ceiling
def _cpu_loop(n: int) -> int:
    """Pure CPU on one thread: a Python loop whose state stays in registers and L1."""
    s = 0
    for i in range(n):
        s += i * i
    return s


def _memory_loop(reps: int) -> float:
    """Memory streaming on one thread: copy 256 MiB (far beyond the caches) ``reps`` times."""
    a = np.ones(1 << 25)
    b = np.empty_like(a)
    for _ in range(reps):
        np.copyto(b, a)
    return float(b[-1])


def _frames_loop(paths: list, method: str) -> float:
    os.environ["MCRECON_THREADS"] = "1"
    from mcrecon.distributed.batch import reconstruct_frame

    out = Path(tempfile.gettempdir()) / f"mcrecon-bench-plain-{os.getpid()}.exr"
    for p in paths:
        reconstruct_frame(p, out, method, {})
    out.unlink(missing_ok=True)
    return 0.0


def _timed_copy(fn, args, warm_args, ready, start, results):
    if warm_args is not None:
        fn(*warm_args)                      # imports, kernel caches: outside the clock
    ready.put(os.getpid())
    start.wait()
    t = time.perf_counter()
    fn(*args)
    results.put(time.perf_counter() - t)


def _copies_at_once(fn, per_copy_args: list, warm_args=None) -> float:
    """Wall time of one process per element of ``per_copy_args``, all released together once ready."""
    ctx = multiprocessing.get_context("spawn")
    ready, start, results = ctx.Queue(), ctx.Event(), ctx.Queue()
    procs = [ctx.Process(target=_timed_copy, args=(fn, a, warm_args, ready, start, results))
             for a in per_copy_args]
    for p in procs:
        p.start()
    for _ in procs:
        ready.get()
    start.set()
    t = time.perf_counter()
    for _ in procs:
        results.get()
    wall = time.perf_counter() - t
    for p in procs:
        p.join()
    return wall


def _scaling(fn, args_one: tuple, args_two: list, repeat: int, warm_args=None) -> tuple[float, float]:
    """Best wall time of 1 copy and of 2 copies at once (alternating, ``repeat`` times each)."""
    one, two = [], []
    for _ in range(repeat):
        one.append(_copies_at_once(fn, [args_one], warm_args))
        two.append(_copies_at_once(fn, args_two, warm_args))
    return min(one), min(two)


# ---------------------------------------------------------------- Dask
def _noop(x):
    return x


def _loop_thread() -> int:
    """The native id of the calling thread (``Client.run`` calls it on the worker's event loop)."""
    import threading

    return threading.get_native_id()


def _housekeeping_cpu(client):
    """A function giving the CPU seconds so far of this process (client, scheduler, nannies) and of
    the workers' event-loop threads: Dask's own work, as opposed to the frames' (None without psutil)."""
    try:
        import psutil
    except ImportError:
        return None
    me = psutil.Process()
    loops = [(psutil.Process(pid), client.run(_loop_thread, workers=[addr])[addr])
             for addr, pid in client.run(os.getpid).items()]

    def now():
        t = me.cpu_times()
        own = t.user + t.system
        ev = 0.0
        for proc, tid in loops:
            ev += sum(th.user_time + th.system_time for th in proc.threads() if th.id == tid)
        return own, ev
    return now


def _warm(log, out_dir, method):
    from mcrecon.distributed.batch import reconstruct_frame

    reconstruct_frame(log, f"{out_dir}/warm-{os.getpid()}.exr", method, {})


def _write_logs(args, work: Path):
    from mcrecon.renderers.scenes import get_scene, write_scene_log

    frames = work / "frames"
    frames.mkdir(exist_ok=True)
    scenes = ("soft_shadow", "caustic")
    t0 = time.perf_counter()
    wrote = 0
    paths = []
    for i in range(args.frames):
        p = frames / f"f{i:03d}-{args.size}-{args.spp}.h5"
        if not p.exists():
            write_scene_log(get_scene(scenes[i % 2]), p, width=args.size, height=args.size, spp=args.spp, seed=i)
            wrote += 1
        paths.append(p)
    big = work / f"big-{args.ingest_size}-{args.ingest_spp}.h5"
    if not big.exists():
        write_scene_log(get_scene("soft_shadow"), big, width=args.ingest_size, height=args.ingest_size,
                        spp=args.ingest_spp, seed=99)
        wrote += 1
    return paths, big, wrote, time.perf_counter() - t0


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--frames", type=int, default=16)
    ap.add_argument("--spp", type=int, default=32)
    ap.add_argument("--method", default="gem")
    ap.add_argument("--ingest-size", type=int, default=1024)
    ap.add_argument("--ingest-spp", type=int, default=32)
    ap.add_argument("--repeat", type=int, default=2, help="runs of each configuration; the fastest counts")
    ap.add_argument("--dir", default=None, help="work directory, logs reused (default: a temporary one, removed)")
    ap.add_argument("--skip", default="", help="comma-separated sections to skip: ceiling, plain, batch, ingest")
    args = ap.parse_args()
    skip = set(filter(None, args.skip.split(",")))
    rep = max(1, args.repeat)

    from mcrecon import distributed as D
    from mcrecon.distributed import batch as D_batch
    from mcrecon.distributed import cluster as D_cluster
    from mcrecon.distributed import ingestion as D_ingestion
    from mcrecon.core.stats import PixelStats

    work = Path(args.dir or tempfile.mkdtemp(prefix="mcrecon-bench-dist-"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        paths, big, wrote, t_write = _write_logs(args, work)
        log_bytes = sum(p.stat().st_size for p in paths)
        print(f"{args.frames} frames {args.size}^2, {args.spp} spp: logs {log_bytes / 2**20:.0f} MiB "
              f"({wrote} log(s) written in {t_write:.1f} s); best of {rep} run(s) per configuration")

        # ---- 1. the machine's parallel ceiling
        if "ceiling" not in skip:
            n_loop = 20_000_000
            c1, c2 = _scaling(_cpu_loop, (n_loop,), [(n_loop,)] * 2, rep)
            m1, m2 = _scaling(_memory_loop, (12,), [(12,)] * 2, rep)
            print(f"machine ceiling, pure-CPU loop (1 thread per process): 1 copy {c1:.2f} s, 2 at once "
                  f"{c2:.2f} s: {2 * c1 / c2:.2f}x throughput")
            print(f"machine ceiling, memory streaming (numpy copy of 256 MiB, 1 thread per process): 1 copy "
                  f"{m1:.2f} s, 2 at once {m2:.2f} s: {2 * m1 / m2:.2f}x throughput")
        if "plain" not in skip:
            p1, p2 = _scaling(_frames_loop, ([str(p) for p in paths], args.method),
                              [([str(p) for p in paths[k::2]], args.method) for k in range(2)], rep,
                              warm_args=([str(paths[0])], args.method))
            print(f"frames in plain processes (no Dask, 1 thread each): 1 process {p1:.2f} s, 2 processes "
                  f"{p2:.2f} s: {p1 / p2:.2f}x")

        # ---- 2. the batch on Dask
        if "batch" not in skip:
            # the last: local_client with Dask's default housekeeping (profiler on, 20 ms tick), to
            # show in the same run what mcrecon's quieter configuration (D_cluster._QUIET) changes
            default_label = "2 workers, Dask's default housekeeping"
            configs = (("1 worker, 1 thread", 1, 1), ("2 workers, 1 thread each", 2, 1),
                       ("1 worker, 2 threads", 1, 2), (default_label, 2, 1))
            times = {label: [] for label, _, _ in configs}
            per_frame = {label: [] for label, _, _ in configs}
            busy = {label: [] for label, _, _ in configs}
            house = {label: [] for label, _, _ in configs}
            overhead = []
            quiet = dict(D_cluster._QUIET)
            for r in range(rep):
                for label, workers, threads in configs:
                    t0 = time.perf_counter()
                    D_cluster._QUIET = {} if label == default_label else quiet
                    try:
                        cm = D_cluster.local_client(workers, threads=threads)
                        c = cm.__enter__()
                    finally:
                        D_cluster._QUIET = quiet
                    try:
                        t_up = time.perf_counter() - t0
                        t = time.perf_counter()
                        c.run(_warm, str(paths[0]), str(work), args.method)   # every worker: imports, kernels
                        t_warm = time.perf_counter() - t
                        cpu = _housekeeping_cpu(c)
                        cpu0 = cpu and cpu()
                        t = time.perf_counter()
                        res = D_batch.reconstruct_many(paths, method=args.method, client=c, out_dir=work / "out",
                                             force=True, progress=False, summary=False)
                        times[label].append(time.perf_counter() - t)
                        if cpu:
                            house[label].append(tuple(b - a for a, b in zip(cpu0, cpu())))
                        assert res.ok, res.failed
                        per_frame[label].append(float(np.median([x["seconds"] for x in res.records])))
                        busy[label].append(sum(x["seconds"] for x in res.records) / workers / times[label][-1])
                        if workers == 1 and threads == 1:
                            n = 1000
                            t = time.perf_counter()
                            c.gather(c.map(_noop, range(n), pure=False))
                            overhead.append((time.perf_counter() - t) / n)
                    finally:
                        cm.__exit__(None, None, None)
                    if r == 0:
                        print(f"  {label}: cluster start {t_up:.1f} s, warm-up (imports, kernels, one frame) "
                              f"{t_warm:.1f} s (not timed below)")
            best = {k: min(v) for k, v in times.items()}
            for label, _, _ in configs:
                i = int(np.argmin(times[label]))
                print(f"batch, {label}: {best[label]:.2f} s ({best[label] / args.frames:.3f} s/frame; median "
                      f"{per_frame[label][i]:.3f} s per frame on its worker, workers busy {busy[label][i]:.0%} "
                      "of the time); runs: "
                      + ", ".join(f"{x:.2f}" for x in times[label]))
                if house[label]:
                    print("  Dask's own CPU during the batch (client process with the scheduler and the nannies "
                          "+ the workers' event loops), per run: "
                          + ", ".join(f"{a:.2f} + {b:.2f} CPU-s" for a, b in house[label]))
            r1 = best["1 worker, 1 thread"] / best["2 workers, 1 thread each"]
            r2 = best["1 worker, 2 threads"] / best["2 workers, 1 thread each"]
            r3 = best["1 worker, 1 thread"] / best[default_label]
            print(f"batch speed-up, 2 workers vs 1 (1 thread each): {r1:.2f}x; vs 1 worker with 2 threads: {r2:.2f}x; "
                  f"with Dask's default housekeeping: {r3:.2f}x")
            if "ceiling" not in skip:
                print(f"  as a fraction of the machine's pure-CPU ceiling ({2 * c1 / c2:.2f}x): {r1 / (2 * c1 / c2):.0%}")
            if "plain" not in skip:
                print(f"  as a fraction of the same frames in plain processes ({p1 / p2:.2f}x): {r1 / (p1 / p2):.0%}; "
                      f"Dask's 1-worker time / plain 1-process time: {best['1 worker, 1 thread'] / p1:.2f}")
            pf = per_frame["1 worker, 1 thread"][int(np.argmin(times["1 worker, 1 thread"]))]
            ov = min(overhead)
            out_bytes = sum(p.stat().st_size for p in (work / "out").glob("*.exr")) / args.frames
            print(f"per frame: {pf:.3f} s of work (median, on a worker), reads {log_bytes / args.frames / 2**20:.1f} "
                  f"MiB, writes {out_bytes / 2**10:.0f} KiB; scheduler overhead {ov * 1e3:.2f} ms per task "
                  f"(1000 no-op tasks)")
            for nw in (10, 100):
                # frames in parallel; the scheduler hands out tasks one after another; I/O is the
                # shared file system's: nw * (read + write) / per_frame bytes per second
                t_frame = pf + ov * nw
                bw = nw * (log_bytes / args.frames + out_bytes) / pf / 2**20
                print(f"extrapolation to {nw} workers: {nw / t_frame * 60:.0f} frames/min if the file system "
                      f"delivers {bw:.0f} MiB/s (scheduler share {ov * nw / t_frame:.1%})")

        # ---- 3. ingestion of one big log
        if "ingest" not in skip:
            print(f"\ningestion of {args.ingest_size}^2, {args.ingest_spp} spp ({big.stat().st_size / 2**20:.0f} MiB)")
            one_runs, it = [], {1: [], 2: []}
            one = None
            for _ in range(rep):
                t = time.perf_counter()
                from mcrecon.io import read_log

                one = PixelStats.from_log(read_log(big))
                one_runs.append(time.perf_counter() - t)
            for _ in range(rep):
                for workers in (1, 2):
                    with D_cluster.local_client(workers, threads=1) as c:
                        D_ingestion.ingest(big, client=c)                       # warm: imports, kernels
                        t = time.perf_counter()
                        st = D_ingestion.ingest(big, client=c)                  # one part per worker
                        it[workers].append(time.perf_counter() - t)
                    assert np.array_equal(st.count, one.count)
            t_one = min(one_runs)
            print(f"one process (PixelStats.from_log, reads and accumulates on 2 threads): {t_one:.2f} s")
            for workers in (1, 2):
                print(f"distributed, {workers} worker(s), one part each: {min(it[workers]):.2f} s; runs: "
                      + ", ".join(f"{x:.2f}" for x in it[workers]))
            ri = min(it[1]) / min(it[2])
            print(f"ingestion speed-up, 2 workers vs 1: {ri:.2f}x; 2 workers vs one process: {t_one / min(it[2]):.2f}x")
            if "ceiling" not in skip:
                print(f"  as a fraction of the machine's memory-streaming ceiling ({2 * m1 / m2:.2f}x): "
                      f"{ri / (2 * m1 / m2):.0%}; of the pure-CPU ceiling ({2 * c1 / c2:.2f}x): {ri / (2 * c1 / c2):.0%}")
    finally:
        if args.dir is None:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
