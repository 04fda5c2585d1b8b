"""What the user pays for adaptivity: whole adaptive commands against the uniform log of the same samples.

    python benchmarks/bench_adaptive_wall.py                              # Mitsuba and the throttled scene
    python benchmarks/bench_adaptive_wall.py --renderer mitsuba --repeat 7 --methods box,gem
    python benchmarks/bench_adaptive_wall.py --profile-only --methods gem   # the per-stage CPU table only
    python benchmarks/bench_adaptive_wall.py --renderer mitsuba --stages --profile-only --methods splat,gem

Per renderer, per repetition, per method: the uniform command, then the
adaptive one, each a fresh ``python -m mcrecon`` process (interleaved pairs:
a machine busy with something else slows both of a pair alike):

* Mitsuba: ``mcrecon mitsuba log --size S --spp N`` against
  ``mcrecon adapt --mitsuba --size S --spp N --method M --log L -o X.exr``
  (the same bridge, the same log writer, the same number of samples);
* the built-in scene renderer throttled to ``--rate`` samples/s
  (``MCRECON_SCENE_RATE``, :class:`mcrecon.renderers.scenes.SceneRenderer`):
  ``mcrecon render-log --scene SC`` against ``mcrecon adapt --scene SC``
  (both also compute the scene's exact reference).

Prints, per method, the median and the spread (min - max) over the
repetitions of the pair's wall ratio adaptive / uniform, and of the CPU
ratio (user + sys of each process, from ``resource``: the other agents'
load inflates it far less than the wall), with the medians in seconds.

``--stages``: each command of a pair once more, in a fresh process under
``cProfile`` on ``time.process_time`` (which counts every thread: Dr.Jit's,
the filters' pool), with the driver's helper threads run inline so that
each stage is counted once: the CPU seconds by stage of the uniform command
and of each method's adaptive command side by side (docs/mitsuba.md,
"Where an adaptive command's time goes").

``--profile``: one in-process adaptive run per method (the API, as the
command runs it) and the toolkit's CPU seconds per million samples by
stage from its timeline: reply validation, log append (with checksums),
statistics, planning, the renderer's ``prepare`` (Mitsuba's positions,
computed on the toolkit thread of a pipelined run: the renderer's work,
not the toolkit's), the final reconstruction (wall seconds of
``method.finish`` on the calling thread), the EXR write.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
METHODS = ("box", "gem", "awr", "splat", "ci", "auto")
#: Targets of the wall ratio adaptive / uniform (Mitsuba, 512², 32 spp).
TARGETS = {"box": 1.03, "ci": 1.08, "splat": 1.12, "awr": 1.10, "gem": 1.12}


def _env(rate: float | None) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT)] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
    env.pop("MCRECON_SCENE_RATE", None)
    if rate is not None:
        env["MCRECON_SCENE_RATE"] = repr(float(rate))
    return env


def timed(args: list[str], env: dict) -> tuple[float, float]:
    """Wall and CPU (user + sys) seconds of ``python -m mcrecon ARGS`` in a fresh process."""
    for i, a in enumerate(args):  # every command writes a new log (adapt refuses an existing one)
        if i and args[i - 1] in ("--log", "-o") and a.endswith(".h5"):
            Path(a).unlink(missing_ok=True)
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "mcrecon", *args], env=env, cwd=ROOT, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    if r.returncode != 0:
        sys.stderr.write(r.stdout[-2000:] + r.stderr[-2000:])
        raise SystemExit(f"mcrecon {' '.join(args)} failed ({r.returncode})")
    return wall, (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)


def commands(renderer: str, method: str, size: str, spp: int, scene: str, tmp: Path) -> tuple[list, list]:
    """(uniform command, adaptive command) of one pair."""
    adapt = ["adapt", "--size", size, "--spp", str(spp), "--method", method, "--log", str(tmp / "adapt.h5"),
             "-o", str(tmp / "adapt.exr"), "--no-progress"]
    if renderer == "mitsuba":
        return (["mitsuba", "log", "--size", size, "--spp", str(spp), "-o", str(tmp / "uniform.h5")],
                adapt[:1] + ["--mitsuba"] + adapt[1:])
    return (["render-log", "--scene", scene, "--size", size, "--spp", str(spp), "-o", str(tmp / "uniform.h5")],
            adapt[:1] + ["--scene", scene] + adapt[1:])


def pairs(renderer, methods, size, spp, scene, rate, repeat) -> dict:
    env = _env(rate if renderer == "scene" else None)
    out = {m: [] for m in methods}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        # one untimed pass: numba's cache and the byte code are warm, as for a user's second command
        for m in methods:
            for c in commands(renderer, m, size, spp, scene, tmp):
                timed(c, env)
        for k in range(repeat):
            for m in methods:
                uni, ada = commands(renderer, m, size, spp, scene, tmp)
                wu, cu = timed(uni, env)
                wa, ca = timed(ada, env)
                out[m].append({"uniform_wall": wu, "uniform_cpu": cu, "adapt_wall": wa, "adapt_cpu": ca})
                print(f"  {renderer} {m:6s} rep {k + 1}: uniform {wu:6.2f} s wall {cu:6.2f} s CPU, "
                      f"adapt {wa:6.2f} s wall {ca:6.2f} s CPU, ratio {wa / wu:5.3f}", flush=True)
    return out


def table(renderer: str, res: dict) -> list[str]:
    lines = [f"| {renderer} | pairs | uniform wall s | adaptive wall s | wall ratio median | spread | uniform CPU s | "
             f"adaptive CPU s | CPU ratio median | spread | target (wall) |", "|---" * 11 + "|"]
    for m, runs in res.items():
        rw = [r["adapt_wall"] / r["uniform_wall"] for r in runs]
        rc = [r["adapt_cpu"] / r["uniform_cpu"] for r in runs]
        t = TARGETS.get(m)
        med = {k: statistics.median(r[k] for r in runs) for k in runs[0]}
        lines.append(f"| {m} | {len(runs)} | {med['uniform_wall']:.1f} | {med['adapt_wall']:.1f} | "
                     f"{statistics.median(rw):.3f} | {min(rw):.3f}-{max(rw):.3f} | {med['uniform_cpu']:.2f} | "
                     f"{med['adapt_cpu']:.2f} | {statistics.median(rc):.3f} | {min(rc):.3f}-{max(rc):.3f} | "
                     f"{'-' if t is None else f'<= {t:.2f}'} |")
    return lines


STAGES = (("reply validation", ("validate",)), ("log append + checksums", ("append",)),
          ("statistics", ("ingest", "observe")), ("planning", ("plan",)), ("renderer's prepare", ("prepare",)))


def _profiled_run(renderer, method, w, h, spp, scene, rate, log=None):
    """One in-process adaptive run of ``method`` (with a log unless ``log`` is None)."""
    from mcrecon.adaptive.run import adapt
    from mcrecon.methods import get_method

    if renderer == "mitsuba":
        from mcrecon.renderers.mitsuba import MitsubaRenderer

        r = MitsubaRenderer(None, width=w, height=h)
    else:
        from mcrecon.renderers.scenes import SceneRenderer

        r = SceneRenderer(scene, width=w, height=h, rate=rate)
    return adapt(r, get_method(method), spp=spp, seed=0, log=None if log is None else str(log), progress=False,
                 track_error=False)


def profile(renderer: str, methods, size: str, spp: int, scene: str, rate: float) -> list[str]:
    """The toolkit's CPU seconds per million samples by stage, one in-process run per method."""
    sys.path.insert(0, str(ROOT))
    from mcrecon.cli._common import parse_size
    from mcrecon.io import write_exr

    w, h = parse_size(size)
    # one untimed 16x16 box run first (pipelined: it calls the renderer's prepare): the first run in the
    # process loads the renderer's and the driver's kernels (the Mitsuba bridge's positions: 0.56 CPU s
    # in its first prepare), which the method profiled first would otherwise be charged
    _profiled_run(renderer, "box", 16, 16, spp, scene, rate)
    lines = [f"| {renderer}: CPU s per M samples | " + " | ".join(s for s, _ in STAGES)
             + " | final reconstruction | EXR write | total |", "|---" * (len(STAGES) + 4) + "|"]
    for m in methods:
        with tempfile.TemporaryDirectory() as tmp:
            c0 = time.process_time()
            res = _profiled_run(renderer, m, w, h, spp, scene, rate, Path(tmp) / "p.h5")
            c1 = time.process_time()
            write_exr(Path(tmp) / "p.exr", res.image)
            c_exr = time.process_time() - c1
            n = res.samples / 1e6
            row = [sum(e["cpu"] for e in res.timeline if e["phase"] in ph) / n for _, ph in STAGES]
            # the final reconstruction runs on the calling thread after the loop: its wall seconds are CPU seconds
            row += [res.finish_seconds / n, c_exr / n]
            lines.append(f"| {m} | " + " | ".join(f"{v:.3f}" for v in row) + f" | {sum(row):.3f} |")
            print(f"  profiled {renderer} {m}: process CPU {c1 - c0:.2f} s for {n:.2f} M samples", flush=True)
    return lines


#: (stage, ((file suffix, function), ...)): cumulative CPU of the functions, summed (none calls another).
STAGE_FUNCS = (("Mitsuba: import, scene load", (("renderers/mitsuba.py", "__init__"),)),
               ("Mitsuba: tracing (kernel launches, copies out)", (("renderers/mitsuba.py", "_trace"),)),
               ("the bridge's film positions", (("renderers/mitsuba.py", "_film_positions"),)),
               ("log writes (checksums)", (("io/writer.py", "write_log"), ("io/writer.py", "append_log"))),
               ("reply validation", (("adaptive/rounds.py", "receive"),)),
               ("statistics", (("core/stats.py", "_ingest"),)),
               ("method: observe", (("adaptive/rounds.py", "_observe"),)),
               ("method: plan", (("adaptive/context.py", "plan"),)),
               ("EXR and PNG", (("io/images.py", "write_exr"), ("io/images.py", "write_png_preview"))))

_STAGES_CHILD = """
import cProfile, json, resource, sys, time
from concurrent.futures import Future
import mcrecon.adaptive.rounds as R

class Inline:  # the driver's helper threads, run where they are submitted: each stage counted once
    def __init__(self, *a, **k): pass
    def submit(self, fn, *a, **k):
        f = Future()
        try: f.set_result(fn(*a, **k))
        except BaseException as e: f.set_exception(e)
        return f
    def shutdown(self, wait=True): pass

R.ThreadPoolExecutor = Inline
from mcrecon.cli import main
funcs = json.loads(sys.argv[1])
pr = cProfile.Profile(time.process_time)
c0 = time.process_time()
pr.enable(); rc = main(sys.argv[2:]); pr.disable()
total = time.process_time() - c0
pr.create_stats()
out = {name: 0.0 for name, _ in funcs}
for (fn, _line, fname), (_cc, _nc, _tt, ct, _cal) in pr.stats.items():
    for name, pairs in funcs:
        if any(fn.replace(chr(92), "/").endswith(suf) and fname == f for suf, f in pairs):
            out[name] += ct
ru = resource.getrusage(resource.RUSAGE_CHILDREN)
out["whole process"] = total
out["child processes (the availability probe)"] = ru.ru_utime + ru.ru_stime
print("STAGES " + json.dumps(out))
sys.exit(rc)
"""


def stages(renderer, methods, size, spp, scene, rate) -> list[str]:
    """CPU seconds by stage of the uniform command and of each method's adaptive one (one process each)."""
    env = _env(rate if renderer == "scene" else None)
    cols = {}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for m in methods:
            uni, ada = commands(renderer, m, size, spp, scene, tmp)
            for name, args in ((("uniform", uni),) if not cols else ()) + ((m, ada),):
                timed(args, env)  # the command's caches warm (its Dr.Jit kernel, numba)
                for i, a in enumerate(args):
                    if i and args[i - 1] in ("--log", "-o") and a.endswith(".h5"):
                        Path(a).unlink(missing_ok=True)
                r = subprocess.run([sys.executable, "-c", _STAGES_CHILD,
                                    json.dumps([[n, list(map(list, f))] for n, f in STAGE_FUNCS]), *args],
                                   env=env, cwd=ROOT, capture_output=True, text=True)
                got = [ln for ln in r.stdout.splitlines() if ln.startswith("STAGES ")]
                if r.returncode != 0 or not got:
                    sys.stderr.write(r.stdout[-2000:] + r.stderr[-2000:])
                    raise SystemExit(f"profiling {name} failed ({r.returncode})")
                cols[name] = json.loads(got[-1][len("STAGES "):])
                print(f"  stages of {renderer} {name}: {cols[name]['whole process']:.2f} CPU s", flush=True)
    names = [n for n, _ in STAGE_FUNCS] + ["whole process", "child processes (the availability probe)"]
    lines = [f"| {renderer}: CPU s by stage | " + " | ".join(cols) + " |", "|---" * (len(cols) + 1) + "|"]
    for n in names:
        lines.append(f"| {n} | " + " | ".join(f"{c[n]:.2f}" if c[n] else "-" for c in cols.values()) + " |")
    return lines


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--renderer", choices=("mitsuba", "scene", "both"), default="both")
    p.add_argument("--methods", default=",".join(METHODS))
    p.add_argument("--size", default="512x512")
    p.add_argument("--spp", type=int, default=32)
    p.add_argument("--scene", default="soft_shadow")
    p.add_argument("--rate", type=float, default=2e6, help="the scene renderer's samples per second")
    p.add_argument("--repeat", type=int, default=5)
    p.add_argument("--profile", action="store_true", help="also the per-stage CPU table")
    p.add_argument("--profile-only", action="store_true",
                   help="no pairs: the per-stage tables asked for (--stages, --profile), else --profile's")
    p.add_argument("--stages", action="store_true", help="also CPU seconds by stage of whole commands (cProfile)")
    p.add_argument("--json", default=None)
    a = p.parse_args(argv)
    methods = [m for m in a.methods.split(",") if m]
    renderers = ("mitsuba", "scene") if a.renderer == "both" else (a.renderer,)
    if "mitsuba" in renderers:
        sys.path.insert(0, str(ROOT))
        from mcrecon.renderers.mitsuba import mitsuba_available

        ok, why = mitsuba_available()
        if not ok:
            print(f"Mitsuba unavailable ({why}): the scene renderer only")
            renderers = tuple(r for r in renderers if r != "mitsuba")
    out, text = {}, []
    for r in renderers:
        if a.stages:
            text += [""] + stages(r, methods, a.size, a.spp, a.scene, a.rate)
        if not a.profile_only:
            res = pairs(r, methods, a.size, a.spp, a.scene, a.rate, a.repeat)
            out[r] = res
            text += [""] + table(r if r == "mitsuba" else f"scene at {a.rate / 1e6:g} M samples/s", res)
        if a.profile or (a.profile_only and not a.stages):
            text += [""] + profile(r, methods, a.size, a.spp, a.scene, a.rate)
    print(f"\n{a.size}, {a.spp} spp, {a.repeat} interleaved pairs per method, load average "
          f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores at the end")
    print("\n".join(text))
    if a.json:
        Path(a.json).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
