"""Start-up time of the command line: ``mcrecon --help`` and ``mcrecon info SMALL_LOG`` against ``python -c pass``.

    python benchmarks/bench_startup.py                 # 15 interleaved repetitions of each command
    python benchmarks/bench_startup.py --repeat 31 --json startup.json

Each command runs in a fresh interpreter (``python -m mcrecon ...``, as the
console script does; the package is taken from this checkout), the commands
interleaved round by round so that a machine busy with something else
slows them alike.  Prints, per command, the median and the fastest wall
time, the median's ratio to ``python -c pass`` measured in the same run,
and (from one extra ``-X importtime`` run) the heavy packages it imported.
The log is a 32x32, 4-spp float32 RGB log written once into a temporary
directory (``--size``, ``--spp``).

Byte code: as after an install, the runs use cached byte code (written by
an untimed first run into a temporary ``PYTHONPYCACHEPREFIX``, even where
``PYTHONDONTWRITEBYTECODE`` is set); ``--no-bytecode-cache`` keeps the
environment as it is (every run then compiles mcrecon's sources again
when PYTHONDONTWRITEBYTECODE is set).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: Packages whose import the start-up path should not pay for (numpy and h5py: `info` reads a log).
HEAVY = ("numpy", "h5py", "numba", "llvmlite", "scipy", "skimage", "matplotlib", "pywt", "dask", "distributed",
         "mitsuba", "drjit", "OpenEXR", "PIL", "flip_evaluator", "pyoidn")


def _env(pycache: Path | None) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT)] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
    if pycache is not None:
        env.pop("PYTHONDONTWRITEBYTECODE", None)
        env["PYTHONPYCACHEPREFIX"] = str(pycache)
    return env


def _write_log(path: Path, size: int, spp: int) -> None:
    import numpy as np

    sys.path.insert(0, str(ROOT))
    from mcrecon.io import write_log

    rng = np.random.default_rng(0)
    n = size * size * spp
    pos = (rng.random((n, 2)) * size).astype(np.float32)
    write_log(path, pos, rng.random((n, 3)).astype(np.float32), width=size, height=size)


def _run(argv, env) -> float:
    t0 = time.perf_counter()
    r = subprocess.run(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env, cwd=ROOT)
    dt = time.perf_counter() - t0
    if r.returncode != 0:
        raise SystemExit(f"{' '.join(map(str, argv))}: exit status {r.returncode}: {r.stderr.decode()[-500:]}")
    return dt


def _imported(argv, env) -> list[str]:
    """Top-level packages of HEAVY that one run imports (from ``-X importtime``)."""
    r = subprocess.run([argv[0], "-X", "importtime"] + argv[1:], stdout=subprocess.DEVNULL,
                       stderr=subprocess.PIPE, env=env, cwd=ROOT, text=True)
    seen = set()
    for line in r.stderr.splitlines():
        if line.startswith("import time:") and "|" in line:
            seen.add(line.rsplit("|", 1)[1].strip().split(".")[0])
    return [m for m in HEAVY if m in seen]


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=15, help="repetitions of each command (median reported)")
    ap.add_argument("--size", type=int, default=32, help="film side of the small log")
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--json", default=None, metavar="FILE", help="also write the numbers as JSON")
    ap.add_argument("--no-bytecode-cache", action="store_true",
                    help="run with the environment's byte-code settings (PYTHONDONTWRITEBYTECODE: no cache)")
    args = ap.parse_args()
    py = sys.executable
    with tempfile.TemporaryDirectory() as tmp:
        env = _env(None if args.no_bytecode_cache else Path(tmp) / "pycache")
        log = Path(tmp) / "small.h5"
        _write_log(log, args.size, args.spp)
        commands = {
            "python -c pass": [py, "-c", "pass"],
            "import mcrecon": [py, "-c", "import mcrecon"],
            "mcrecon --help": [py, "-m", "mcrecon", "--help"],
            "mcrecon info small.h5": [py, "-m", "mcrecon", "info", str(log)],
        }
        names = list(commands)
        for name in names:  # warm the OS file cache and the bytecode caches, untimed
            _run(commands[name], env)
        times = {name: [] for name in names}
        for i in range(args.repeat):
            order = names[i % len(names):] + names[:i % len(names)]  # rotate: no command always runs first
            for name in order:
                times[name].append(_run(commands[name], env))
        heavy = {name: _imported(commands[name], env) for name in names}
    base = statistics.median(times["python -c pass"])
    rows = []
    print(f"{'command':24s} {'median s':>9s} {'min s':>7s} {'/ pass':>7s}  heavy imports")
    for name in names:
        med, best = statistics.median(times[name]), min(times[name])
        rows.append({"command": name, "median_seconds": round(med, 4), "min_seconds": round(best, 4),
                     "ratio_to_python": round(med / base, 2), "heavy_imports": heavy[name]})
        print(f"{name:24s} {med:9.3f} {best:7.3f} {med / base:7.2f}  {', '.join(heavy[name]) or '-'}")
    cache = "environment's byte-code settings" if args.no_bytecode_cache else "cached byte code"
    print(f"({args.repeat} interleaved runs each, {py}, log {args.size}x{args.size} at {args.spp} spp, {cache}; "
          f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores)")
    if args.json:
        Path(args.json).write_text(json.dumps({"repeat": args.repeat, "python": py, "bytecode_cache": not
                                               args.no_bytecode_cache, "rows": rows}, indent=1))
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
