"""What a first ``mcrecon demo`` pays for numba: compilations and compile seconds per module and kernel.

    python benchmarks/bench_first_run.py                  # a cold run, then a warm one, same cache
    python benchmarks/bench_first_run.py --json first.json --top 30
    python benchmarks/bench_first_run.py --args demo --methods gem --size 64x64

Runs ``python -m mcrecon ARGS`` (default ``demo`` into a temporary
directory) in a fresh interpreter whose ``NUMBA_CACHE_DIR`` is an empty
temporary directory (a fresh install: nothing compiled), then the same
command again with the cache the first run left (the second run of an
install).  Inside each run numba's event API (``numba:compile``, which
fires only for a real compilation, never for a load from the cache)
records every compilation: the kernel, its argument types and its CPU
seconds (``time.thread_time``, which the machine's other load does not
inflate much) *exclusive* of the nested compilations it triggered (a
kernel calling another compiles the callee inside its own compilation).
A cold demo compiles in two processes (:func:`mcrecon.cli.builtins._demo_warm_up`):
the records are the main process's; ``--one-process`` keeps every
compilation in it (to count them all).

Prints per run the wall seconds and the CPU seconds (user + sys of the
command and the processes it started), the number of compilations and
their CPU seconds, per module, per outermost kernel (with what it
compiled inside) and (``--top``) per kernel with how many signatures
each was compiled for: a kernel compiled for
several signatures (float32 and float64, C and A layouts, int32 and
int64) is a candidate for a cast at its boundary.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# The child: a numba:compile listener, then the command.  Nested compilations (callees) are subtracted from
# their caller so that the seconds add up to the compile time.
_CHILD = r"""
import json, sys, time, atexit
from numba.core import event as ev

records, stack = [], []

class _L(ev.Listener):
    def on_start(self, event):
        py = event.data["dispatcher"].py_func
        stack.append([time.thread_time(), 0.0, py.__module__ + "." + py.__qualname__])
    def on_end(self, event):
        t0, nested, _ = stack.pop()
        dt = time.thread_time() - t0
        if stack:
            stack[-1][1] += dt
        d = event.data["dispatcher"]
        py = d.py_func
        records.append({"module": py.__module__, "name": py.__qualname__, "args": [str(a) for a in event.data["args"]],
                        "seconds": dt - nested, "nested": len(stack),
                        "top": stack[0][2] if stack else py.__module__ + "." + py.__qualname__,
                        "inclusive": dt})

ev.register("numba:compile", _L())
OUT = sys.argv[1]
t_cpu0 = time.process_time()
t0 = time.perf_counter()

def _dump():
    json.dump({"records": records, "wall": time.perf_counter() - t0, "cpu": time.process_time() - t_cpu0},
              open(OUT, "w"))
atexit.register(_dump)
ONE = sys.argv[2] == "1"
sys.argv = ["mcrecon"] + sys.argv[3:]
from mcrecon.cli import main
if ONE:
    import mcrecon.cli.builtins as b
    b._TWO_PROCESSES_AFTER = float("inf")
rc = main(sys.argv[1:])
sys.exit(rc)
"""


def run(args: list[str], cache: Path, out_json: Path, one_process: bool = False) -> dict:
    """One child run of ``mcrecon ARGS`` with numba's cache at ``cache``: its compile records and times."""
    env = dict(os.environ)
    env["NUMBA_CACHE_DIR"] = str(cache)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT)] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
    t0 = time.perf_counter()
    ru0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    r = subprocess.run([sys.executable, "-c", _CHILD, str(out_json), str(int(one_process)), *args], env=env, cwd=ROOT,
                       capture_output=True, text=True)
    wall = time.perf_counter() - t0
    ru1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    if r.returncode != 0:
        sys.stderr.write(r.stdout[-3000:] + r.stderr[-3000:])
        raise SystemExit(f"mcrecon {' '.join(args)} failed ({r.returncode})")
    data = json.loads(out_json.read_text())
    data["process_wall"] = wall
    # user + sys of the command and every process it started (the demo's second compiler)
    data["process_cpu"] = (ru1.ru_utime - ru0.ru_utime) + (ru1.ru_stime - ru0.ru_stime)
    data["stdout"] = r.stdout
    data["stderr"] = r.stderr
    return data


def summarise(data: dict, top: int) -> dict:
    recs = data["records"]
    by_mod: dict[str, list] = {}
    by_kernel: dict[tuple, list] = {}
    for r in recs:
        m = by_mod.setdefault(r["module"], [0, 0.0])
        m[0] += 1
        m[1] += r["seconds"]
        k = by_kernel.setdefault((r["module"], r["name"]), [0, 0.0, []])
        k[0] += 1
        k[1] += r["seconds"]
        k[2].append(r["args"])
    total = sum(r["seconds"] for r in recs)
    by_top: dict[str, list] = {}
    for r in recs:
        t = by_top.setdefault(r["top"], [0, 0.0])
        t[0] += 1
        t[1] += r["seconds"]
    print(f"  wall {data['process_wall']:.1f} s, CPU (user+sys, with child processes) {data['process_cpu']:.1f} s,"
          f" of the main process {data['cpu']:.1f} s; in it {len(recs)} compilations, {total:.1f} CPU s of them")
    for mod, (n, s) in sorted(by_mod.items(), key=lambda kv: -kv[1][1]):
        print(f"    {mod:48s} {n:4d} compilations {s:7.2f} s")
    if top:
        print(f"  top {top} outermost compilations (with what they compiled inside: compilations, seconds):")
        for name, (n, s) in sorted(by_top.items(), key=lambda kv: -kv[1][1])[:top]:
            print(f"    {name:70s} {n:4d} {s:7.2f} s")
        print(f"  top {top} kernels (signatures compiled, seconds):")
        for (mod, name), (n, s, sigs) in sorted(by_kernel.items(), key=lambda kv: -kv[1][1])[:top]:
            print(f"    {mod.split('.', 1)[-1] + '.' + name:60s} {n:3d} {s:7.2f} s")
            if n > 1:
                for a in sigs:
                    print(f"        ({', '.join(a)})")
    return {"compilations": len(recs), "compile_seconds": total, "wall": data["process_wall"],
            "cpu": data["process_cpu"], "main_cpu": data["cpu"],
            "modules": {m: {"compilations": n, "seconds": s} for m, (n, s) in by_mod.items()},
            "kernels": [{"kernel": f"{m}.{k}", "n": n, "seconds": s, "signatures": sg}
                        for (m, k), (n, s, sg) in by_kernel.items()],
            "outermost": {k: {"compilations": n, "seconds": s} for k, (n, s) in by_top.items()},
            "records": recs}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--args", nargs=argparse.REMAINDER, default=None,
                   help="the mcrecon command line (default: demo --out TMP)")
    p.add_argument("--top", type=int, default=25, help="kernels to list (0: none)")
    p.add_argument("--no-warm", action="store_true", help="only the cold run")
    p.add_argument("--one-process", action="store_true",
                   help="the demo's warm-up in one process (all compilations counted; no second compiler)")
    p.add_argument("--json", default=None)
    a = p.parse_args(argv)
    result = {}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        args = a.args if a.args else ["demo", "--out", str(tmp / "demo")]
        if a.args and "demo" in a.args and "--out" not in a.args:
            args = args + ["--out", str(tmp / "demo")]
        cache = tmp / "numba-cache"
        cache.mkdir()
        print(f"cold: mcrecon {' '.join(args)}  (NUMBA_CACHE_DIR empty)")
        result["cold"] = summarise(run(args, cache, tmp / "cold.json", a.one_process), a.top)
        if not a.no_warm:
            print(f"warm: the same, with the cache the cold run left")
            result["warm"] = summarise(run(args, cache, tmp / "warm.json", a.one_process), a.top)
    if a.json:
        Path(a.json).write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
