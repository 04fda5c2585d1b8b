"""A production frame: ``auto`` and ``nfor`` with features against ``gem`` and OIDN + albedo + normal, one run.

On one log of a built-in textured scene with per-sample features (default
checker_wall, 1920x1080, 32 spp), every number comes from the same run on
the same input:

* ``reconstruct --method gem``, ``auto`` and ``nfor`` as whole commands
  (child processes): wall seconds, CPU seconds (user + system of the
  child), peak RSS (``os.wait4``'s rusage of that child), and the
  reconstruction seconds the command prints;
* OIDN (``pyoidn.denoise(colour, albedo, normal, hdr=True,
  quality="high")``) on the same pixel means: the denoise call only,
  after a warm-up call on a small image;
* the ratios the targets are stated in (issue 42): auto / OIDN and nfor /
  OIDN (reconstruction seconds against the denoise call), auto's whole
  command / gem's whole command, and auto's and nfor's peak RSS, each with
  its target, the absolute seconds it divides and the load average;
* ``render-log`` of that log as a whole command (wall, CPU, peak RSS) when
  the benchmark renders it (no ``--log``, no log left in ``--workdir``): it
  streams blocks of samples, so its peak RSS follows the image, not the log;
* the machine's load average before and after, so a number measured on a
  busy machine says so;
* with ``--tile N`` every command reconstructs in tiles of N x N pixels
  (``reconstruct --tile N``) where the method declares a finite halo
  (auto and nfor, whole-image, run untiled), and CPU seconds per megapixel
  compare a 4K log with a 1080p one at the same tile size;
* with ``--log`` given several times (or ``--logs A,B``), every log runs in turn (its table as above)
  and then one row per resolution: each method's CPU seconds per megapixel and peak RSS, each larger
  film's CPU seconds per megapixel over the smallest's against the +-20 % target (tiled where the
  method tiles with ``--tile``), and the peak-RSS targets (3 GB at 1080p; bounded by tiles above);
* with ``--before ROOT`` (another checkout of mcrecon, e.g. ``git worktree``
  or ``git archive`` of an earlier commit), every command also runs on that
  checkout, interleaved with this one's (before, after, before, after ...
  ``--repeat`` times), and the after / before ratios of reconstruction and
  CPU seconds and of peak RSS are printed: on a shared machine only such
  ratios, measured side by side, compare two versions.

Each method first reconstructs a tiny log of the same scene (not timed),
so kernel compilation of a first run is not counted.

    python benchmarks/bench_frame.py [--size 1920x1080] [--spp 32] [--scene checker_wall]
                                     [--log LOG.h5] [--workdir DIR] [--methods gem,auto,nfor]
                                     [--before ROOT [--repeat N]] [--tile N]
    python benchmarks/bench_frame.py --log LOG1080.h5 --log LOG4K.h5 --tile 1024   (per-pixel cost by resolution)
    python benchmarks/bench_frame.py --log LOG.h5 --stages time|memory|rss   (auto's stages, one process)
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

_RECON = re.compile(r"reconstructed in ([0-9.]+) s")


def _env(root: Path = ROOT) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(root) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return env


def run_command(args: list[str], *, root: Path = ROOT) -> dict:
    """Run ``python -m mcrecon ARGS`` from the checkout ``root``: its wall and CPU seconds, peak RSS (this
    child's own rusage, ``os.wait4``) and the reconstruction seconds it prints."""
    t0 = time.perf_counter()
    errf = tempfile.TemporaryFile("w+")
    p = subprocess.Popen([sys.executable, "-m", "mcrecon", *args], stdout=subprocess.PIPE, stderr=errf,
                         env=_env(root), text=True)
    # stderr goes to a file (no pipe to fill while stdout is read); then wait4 reaps the child with its own rusage
    out = p.stdout.read()
    _, status, ru = os.wait4(p.pid, 0)
    errf.seek(0)
    err = errf.read()
    errf.close()
    p.returncode = os.waitstatus_to_exitcode(status)
    wall = time.perf_counter() - t0
    if p.returncode != 0:
        raise SystemExit(f"mcrecon {' '.join(args)} failed ({p.returncode}):\n{err[-2000:]}")
    m = _RECON.search(out)
    return {"wall": wall, "cpu": ru.ru_utime + ru.ru_stime, "rss_gb": ru.ru_maxrss * 1024 / 1e9,
            "recon": float(m.group(1)) if m else float("nan")}


def oidn_seconds(log: str) -> float:
    """Seconds of one ``pyoidn.denoise`` call (colour, albedo, normal; hdr, quality high) on the log's pixel
    means, after a warm-up call on a small crop."""
    import pyoidn

    from mcrecon.core.stats import PixelStats
    from mcrecon.io.reader import read_log

    st = PixelStats.from_source(read_log(log), features=("albedo", "normal"))
    f32 = lambda a: np.ascontiguousarray(a, dtype=np.float32)  # noqa: E731
    colour = f32(st.mean)
    albedo, normal = f32(np.clip(st.features["albedo"].mean, 0, 1)), f32(st.features["normal"].mean)
    pyoidn.denoise(colour[:64, :64].copy(), albedo[:64, :64].copy(), normal[:64, :64].copy(), hdr=True, quality="high")
    t0 = time.perf_counter()
    pyoidn.denoise(colour, albedo, normal, hdr=True, quality="high")
    return time.perf_counter() - t0


#: auto's stages timed by ``--stages`` (module, function): the candidates, the kernels under them, the selection.
STAGES = (("method", "sure_filter_bank"), ("method", "nlmeans_cross"), ("method", "oidn_candidate"),
          ("method", "feature_candidates"), ("features", "_regressions"), ("features", "feature_guided_half"),
          ("features", "prefiltered_features"), ("features", "dual_candidate"), ("blackbox", "oidn_denoise"),
          ("regression", "collaborative_regression"), ("method", "_relative_choice"), ("method", "_global_prior"),
          ("method", "_region_guard"), ("method", "_picked"), ("method", "confidence_clamp"),
          ("method", "_no_push_in_heavy_tails"))


class _RssProbe:
    """The process's resident set (``/proc/self/statm``) read every few milliseconds on a thread, with the
    innermost stage running at its largest: tracemalloc sees only Python's allocations, not OIDN's
    scratch memory nor the interpreter's libraries, so only the RSS says which stage holds a command's
    peak."""

    def __init__(self, stack: list):
        import threading

        self.stack, self.peak, self.at, self.by_stage = stack, 0, "-", {}
        self._page = os.sysconf("SC_PAGE_SIZE")
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._poll, daemon=True)
        self._thread.start()

    def _poll(self):
        with open("/proc/self/statm") as f:
            while not self._stop.wait(0.005):
                f.seek(0)
                rss = int(f.read().split()[1]) * self._page
                at = self.stack[-1] if self.stack else "-"
                self.by_stage[at] = max(self.by_stage.get(at, 0), rss)
                if rss > self.peak:
                    self.peak, self.at = rss, at

    def stop(self):
        self._stop.set()
        self._thread.join()


def auto_stages(log: str, *, memory: bool = False, rss: bool = False) -> None:
    """One in-process ``reconstruct(log, method="auto")`` with its stages wrapped: calls, CPU seconds
    (``time.process_time``, every thread), wall seconds, and with ``memory`` (tracemalloc, which slows
    numpy's allocations) the traced bytes held at a stage's entry and the peak during it.  Nested stages
    are counted in their callers too.  With ``rss`` the largest resident set seen while each stage was
    the innermost one running (:class:`_RssProbe`), and the stage at the process's peak.  Kernels
    compile first on a tiny image (not counted)."""
    import functools
    import tracemalloc
    import warnings

    import mcrecon
    from mcrecon.filters import regression
    from mcrecon.methods.auto import blackbox, features, method

    mods = {"method": method, "features": features, "blackbox": blackbox, "regression": regression}
    rows, peaks, stack = {}, [], []

    def wrap(mod, name):
        f = getattr(mod, name)

        @functools.wraps(f)
        def timed(*a, **k):
            c0, w0, i0 = time.process_time(), time.perf_counter(), len(peaks)
            held = tracemalloc.get_traced_memory()[0] if memory else 0
            if memory:
                tracemalloc.reset_peak()
            stack.append(name)
            try:
                return f(*a, **k)
            finally:
                stack.pop()
                r = rows.setdefault(name, [0, 0.0, 0.0, 0.0, 0.0])
                r[0] += 1
                r[1] += time.process_time() - c0
                r[2] += time.perf_counter() - w0
                if memory:  # an inner stage's reset_peak hid its peak from ours: take the largest seen
                    pk = max([tracemalloc.get_traced_memory()[1]] + peaks[i0:])
                    peaks.append(pk)
                    r[3], r[4] = max(r[3], held / 1e9), max(r[4], pk / 1e9)
        setattr(mod, name, timed)

    for mod, name in STAGES:
        wrap(mods[mod], name)
    warnings.simplefilter("ignore")
    tiny = np.random.default_rng(0)
    ss = mcrecon.SampleSet(tiny.random((16 * 16 * 8, 2)) * 16, tiny.random((16 * 16 * 8, 3)), width=16, height=16,
                           features={"albedo": tiny.random((16 * 16 * 8, 3)), "normal": tiny.random((16 * 16 * 8, 3))})
    mcrecon.reconstruct(ss, method="auto")
    rows.clear()
    if memory:
        tracemalloc.start()
    probe = _RssProbe(stack) if rss else None
    c0, w0 = time.process_time(), time.perf_counter()
    mcrecon.reconstruct(log, method="auto")
    c1, w1 = time.process_time(), time.perf_counter()
    if probe is not None:
        probe.stop()
        print(f"auto on {log}: peak RSS {probe.peak / 1e9:.2f} GB while {probe.at} ran; largest RSS while each "
              "stage was the innermost one running (GB): " + ", ".join(
                  f"{k} {v / 1e9:.2f}" for k, v in sorted(probe.by_stage.items(), key=lambda kv: -kv[1])))
    print(f"auto stages on {log}: reconstruct() CPU {c1 - c0:.1f} s, wall {w1 - w0:.1f} s, load {os.getloadavg()[0]:.1f}"
          + (f", traced peak {max(peaks + [tracemalloc.get_traced_memory()[1]]) / 1e9:.2f} GB" if memory else ""))
    print(f"{'stage':28s} {'calls':>5s} {'CPU s':>7s} {'wall s':>7s}" + (f" {'held GB':>8s} {'peak GB':>8s}" if memory else ""))
    for name, r in sorted(rows.items(), key=lambda kv: -kv[1][1]):
        print(f"{name:28s} {r[0]:5d} {r[1]:7.2f} {r[2]:7.2f}" + (f" {r[3]:8.2f} {r[4]:8.2f}" if memory else ""))


def _log_size(log: str) -> tuple[int, int]:
    """A log's film, width and height."""
    from mcrecon.io.reader import read_log

    lg = read_log(log)
    return int(lg.width), int(lg.height)


def one_log(args, log: str | None, work: Path, methods: list, before: Path | None) -> dict:
    """Every method's whole command on one log (rendered into ``work`` when None), OIDN on its pixel means,
    and the table and the target ratios of that log printed; returns what the per-resolution rows read."""
    load0 = os.getloadavg()
    rendered = None
    if log is None:
        log = str(work / f"{args.scene}_{args.size}_{args.spp}.h5")
        if not Path(log).exists():
            rendered = run_command(["render-log", "--scene", args.scene, "--spp", str(args.spp), "--size", args.size,
                                    "--features", "-o", log])
    width, height = _log_size(log)
    size = f"{width}x{height}"
    tiny = str(work / f"{args.scene}_tiny.h5")
    if not Path(tiny).exists():
        run_command(["render-log", "--scene", args.scene, "--spp", "4", "--size", "48x40", "--features", "-o", tiny])
    res, old = {}, {}
    from mcrecon.methods import get_method

    for m in methods:
        # a whole-image method refuses tiles: it runs untiled beside the others
        tiled = ["--tile", str(args.tile)] if args.tile and get_method(m).halo(1, 1) is not None else []
        run_command(["reconstruct", tiny, "--method", m, "-o", str(work / f"tiny_{m}.exr")])  # compile, not timed
        out = str(work / f"{m}_{size}.exr")
        if before is not None:
            run_command(["reconstruct", tiny, "--method", m, "-o", str(work / f"tiny_{m}_before.exr")], root=before)
            pairs = []
            for _ in range(args.repeat):
                b = run_command(["reconstruct", log, "--method", m, "-o", str(work / f"{m}_{size}_before.exr")],
                                root=before)
                a = run_command(["reconstruct", log, "--method", m, *tiled, "-o", out])
                pairs.append((b, a))
            # the pair with the median CPU ratio: one pair's two runs saw the same load
            pairs.sort(key=lambda ba: ba[1]["cpu"] / ba[0]["cpu"])
            old[m], res[m] = pairs[len(pairs) // 2]
        else:
            res[m] = run_command(["reconstruct", log, "--method", m, *tiled, "-o", out])
        res[m]["tiled"] = bool(tiled)
    try:
        t_oidn = oidn_seconds(log)
    except ImportError:
        t_oidn = float("nan")
    load1 = os.getloadavg()
    print(f"bench_frame: {Path(log).name}, {size}, features"
          + (f", tiles of {args.tile} px" if args.tile else "") + f"; {os.cpu_count()} CPUs; load average "
          f"{load0[0]:.2f} before, {load1[0]:.2f} after")
    print(f"{'':8s} {'reconstruction s':>17s} {'command wall s':>15s} {'command CPU s':>14s} {'peak RSS GB':>12s}")
    for m in methods:
        r = res[m]
        print(f"{m:8s} {r['recon']:17.2f} {r['wall']:15.2f} {r['cpu']:14.2f} {r['rss_gb']:12.2f}")
    print(f"{'OIDN':8s} {t_oidn:17.2f}   (denoise call only: colour + albedo + normal, hdr, quality high)")
    if rendered is not None:  # the whole command; most of its wall is the exact reference (32x32 points a pixel)
        print(f"{'render-log':10s} {'':15s} {rendered['wall']:15.2f} {rendered['cpu']:14.2f} {rendered['rss_gb']:12.2f}"
              f"   (whole command, log {Path(log).stat().st_size / 1e9:.2f} GB)")
    load = f"load {load0[0]:.1f}-{load1[0]:.1f}"
    # issue 42's targets beside each ratio, with the seconds it divides and the load it was measured under
    target = {"auto": 3.0, "nfor": 2.0}
    for m in ("auto", "nfor"):
        if m in res:
            print(f"{m} / OIDN (reconstruction): {res[m]['recon'] / t_oidn:.1f}   (target <= {target[m]:g}; "
                  f"{res[m]['recon']:.2f} s / {t_oidn:.2f} s, {load})")
    if "auto" in res and "gem" in res:
        a, g = res["auto"], res["gem"]
        print(f"auto / gem (whole command, wall): {a['wall'] / g['wall']:.1f}   (target <= 2; "
              f"{a['wall']:.2f} s / {g['wall']:.2f} s, {load})")
        # on a shared machine wall time follows the other jobs; CPU seconds (both cores counted) less so
        print(f"auto / gem (whole command, CPU): {a['cpu'] / g['cpu']:.1f}   ({a['cpu']:.2f} s / {g['cpu']:.2f} s)")
    for m in ("auto", "nfor"):
        if m in res:
            print(f"{m} peak RSS: {res[m]['rss_gb']:.2f} GB   (target <= 3 GB)")
    mpix = width * height / 1e6
    for m in methods:
        print(f"{m}: {res[m]['cpu'] / mpix:.1f} CPU s per megapixel (whole command)")
    if old:
        print(f"after / before ({before}; median pair of {args.repeat}):")
        print(f"{'':8s} {'reconstruction':>15s} {'command CPU':>12s} {'peak RSS':>9s}   (before: recon s, CPU s, GB)")
        for m in methods:
            a, b = res[m], old[m]
            print(f"{m:8s} {a['recon'] / b['recon']:15.3f} {a['cpu'] / b['cpu']:12.3f} {a['rss_gb'] / b['rss_gb']:9.3f}"
                  f"   ({b['recon']:.2f}, {b['cpu']:.2f}, {b['rss_gb']:.2f})")
    return {"size": size, "mpix": mpix, "res": res, "load": (load0[0], load1[0])}


#: Issue 42's per-pixel target: a larger film's CPU seconds per megapixel within 20 % of the smallest's.
PER_PIXEL_TOLERANCE = 0.20
#: Issue 42's memory target at 1920 x 1080 (decimal GB); larger films reconstruct in tiles.
PEAK_RSS_1080P_GB = 3.0


def per_resolution(runs: list, methods: list) -> None:
    """One row per log (its film, each method's whole-command CPU seconds per megapixel and peak RSS), then
    each larger film's per-megapixel CPU seconds over the smallest film's against the +-20 % target, and
    the peak-RSS targets: every row from this one run, the loads beside them."""
    runs = sorted(runs, key=lambda r: r["mpix"])
    print("per resolution (whole command; CPU s per megapixel, peak RSS GB; t: tiled):")
    print(f"{'film':>10s} {'MP':>6s} " + " ".join(f"{m + ' CPU s/MP':>16s} {m + ' GB':>9s}" for m in methods)
          + "  load")
    for r in runs:
        cells = []
        for m in methods:
            x = r["res"][m]
            cells.append(f"{x['cpu'] / r['mpix']:15.1f}{'t' if x['tiled'] else ' '} {x['rss_gb']:9.2f}")
        print(f"{r['size']:>10s} {r['mpix']:6.2f} " + " ".join(cells) + f"  {r['load'][0]:.1f}-{r['load'][1]:.1f}")
    base = runs[0]
    for r in runs[1:]:
        for m in methods:
            a, b = r["res"][m], base["res"][m]
            ratio = (a["cpu"] / r["mpix"]) / (b["cpu"] / base["mpix"])
            ok = "within" if abs(ratio - 1.0) <= PER_PIXEL_TOLERANCE else "outside"
            print(f"{m}: {r['size']} / {base['size']} CPU s per megapixel {ratio:.2f}   ({ok} the target 1 +- "
                  f"{PER_PIXEL_TOLERANCE:g}; {'tiled' if a['tiled'] else 'untiled'} / "
                  f"{'tiled' if b['tiled'] else 'untiled'})")
    for r in runs:
        for m in methods:
            x = r["res"][m]
            if r["size"] == "1920x1080":
                print(f"{m} peak RSS at {r['size']}: {x['rss_gb']:.2f} GB   (target <= {PEAK_RSS_1080P_GB:g} GB)")
            elif r["mpix"] > 1920 * 1080 / 1e6:
                print(f"{m} peak RSS at {r['size']}: {x['rss_gb']:.2f} GB   ({'tiles' if x['tiled'] else 'untiled'}; "
                      f"target: bounded by tiles, {x['rss_gb'] / base['res'][m]['rss_gb']:.2f} x the "
                      f"{base['size']} run's)")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", default="1920x1080", help="WIDTHxHEIGHT (default 1920x1080)")
    ap.add_argument("--spp", type=int, default=32)
    ap.add_argument("--scene", default="checker_wall")
    ap.add_argument("--log", action="append", help="an existing log with features (else one is rendered into "
                    "--workdir); given several times, every log is run and one row per resolution printed")
    ap.add_argument("--logs", help="comma-separated logs, as --log given for each")
    ap.add_argument("--workdir", help="where the log and the outputs go (default: a temporary folder)")
    ap.add_argument("--methods", default="gem,auto,nfor")
    ap.add_argument("--before", help="another mcrecon checkout: every command also runs there, interleaved, "
                                     "and the after / before ratios are printed")
    ap.add_argument("--repeat", type=int, default=1, help="before/after pairs per method with --before (default 1)")
    ap.add_argument("--tile", type=int, default=None, help="reconstruct in tiles of N x N pixels (reconstruct --tile)")
    ap.add_argument("--stages", choices=("time", "memory", "rss"), help="with --log: only auto's stage breakdown "
                    "of that log, in this process (memory: tracemalloc's held and peak bytes per stage too; rss: "
                    "the process's resident set per stage, OIDN's scratch memory included)")
    args = ap.parse_args(argv)
    logs = list(args.log or []) + [x.strip() for x in (args.logs or "").split(",") if x.strip()]
    if args.stages:
        if len(logs) != 1:
            raise SystemExit("bench_frame: --stages needs one --log LOG.h5")
        auto_stages(logs[0], memory=args.stages == "memory", rss=args.stages == "rss")
        return 0
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    before = Path(args.before).resolve() if args.before else None
    if before is not None and not (before / "mcrecon" / "__init__.py").is_file():
        raise SystemExit(f"bench_frame: --before {args.before}: no mcrecon package there (give a checkout's root)")
    if args.repeat < 1:
        raise SystemExit(f"bench_frame: --repeat {args.repeat}: give 1 or more")
    for lg in logs:
        if not Path(lg).is_file():
            raise SystemExit(f"bench_frame: --log {lg}: no such file (give an existing log, or none to render one)")
    work = Path(args.workdir or tempfile.mkdtemp(prefix="bench_frame_"))
    work.mkdir(parents=True, exist_ok=True)
    runs = [one_log(args, lg, work, methods, before) for lg in (logs or [None])]
    if len(runs) > 1:
        per_resolution(runs, methods)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
