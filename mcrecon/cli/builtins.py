"""The commands about what mcrecon ships: scenes, methods, render-log, demo, mitsuba.
"""

from __future__ import annotations

import json
import textwrap
import time
from pathlib import Path

from ..errors import InputError
from ._common import (check_log_output, check_output, film_size_flag, method_kernels, parse_size,
                      write_outputs)

def _cmd_scenes(args):
    from ..renderers.scenes import get_scene, scene_names

    for name in scene_names():
        sc = get_scene(name)
        # which scenes send albedo/normal/depth per sample by default, and which only with --features
        tag = "features: on" if sc.features_default else "features: opt-in" if sc.feature_names else "no features"
        print(f"{name:16s} {tag:17s} {sc.description}")
    return 0


def _json_value(v):
    """An option default as JSON holds it (numbers, strings, booleans, None, lists; else its text)."""
    if v is None or isinstance(v, (bool, int, str)) or (isinstance(v, float) and v == v and abs(v) != float("inf")):
        return v
    if isinstance(v, (tuple, list)):
        return [_json_value(x) for x in v]
    return str(v)


def _method_description(name, flags) -> dict:
    """What `mcrecon methods --json` says of one method: its options (flag, type, default, valid values)
    and its inputs (method.requires with the default options)."""
    from ..methods import get_method, method_class

    cls = method_class(name)
    doc = (cls.__doc__ or "").strip().splitlines()
    req = get_method(name).requires
    return {"name": name, "summary": doc[0].strip() if doc else "", "adaptive": bool(cls.adaptive),
            "options": [{"name": o.name, "flag": flags[o.name], "type": getattr(o.type, "__name__", str(o.type)),
                         "default": _json_value(o.default), "valid": o.expectation(), "help": o.help,
                         "variants": {v: _json_value(pre[o.name]) for v, pre in cls.variants.items() if o.name in pre}}
                        for o in cls.options],
            "inputs": {"statistics": bool(req.statistics), "subpixels": int(req.subpixels),
                       "samples": bool(req.samples), "half_buffers": bool(req.half_buffers),
                       "reference": str(req.reference)}}


def _cmd_methods(args):
    import sys

    from ..methods import available_methods, get_method, method_class

    if args.json:
        names = available_methods() if args.name is None else [args.name]
        out = [_method_description(n, args.method_flags) for n in names]
        print(json.dumps(out if args.name is None else out[0], indent=2))
        return 0
    if args.name is None:
        for name in available_methods():
            cls = method_class(name)
            doc = (cls.__doc__ or "").strip().splitlines()[0] if cls.__doc__ else ""
            opts = " ".join(args.method_flags[o.name] for o in cls.options)
            print(f"{name:8s} {doc}" + (f"  [{opts}]" if opts else ""))
        # stdout is the list a script reads, one method a line; the hint is for the person at the terminal
        sys.stderr.write("mcrecon: `mcrecon methods NAME` describes one method's options and inputs; "
                         "`mcrecon methods --json` lists them all as JSON.\n")
        return 0
    cls = method_class(args.name)
    doc = (cls.__doc__ or "").strip().splitlines()
    print(f"{args.name}: {doc[0].strip() if doc else ''}")
    print(f"adaptive sampling: {'yes, it places samples itself' if cls.adaptive else 'no, uniform rounds'}")
    print(f"\noptions (flags of `mcrecon reconstruct/adapt --method {args.name}`):")
    if not cls.options:
        print("  (none)")
    indent = " " * 27
    for o in cls.options:
        presets = "".join(f", --variant {v}: {pre[o.name]}" for v, pre in cls.variants.items()
                          if o.name in pre and pre[o.name] != o.default)
        print(f"  {args.method_flags[o.name]:24s} {getattr(o.type, '__name__', o.type)}, default {o.default}"
              f"{presets}")
        for text in (f"valid: {o.expectation()}", o.help):
            print(textwrap.fill(text, 100, initial_indent=indent, subsequent_indent=indent + "  "))
    req = get_method(args.name).requires
    grid = f"{req.subpixels}x{req.subpixels} subpixel grid" if req.subpixels else "no subpixel grid"
    print("\ninputs (method.requires, default options):")
    print(f"  {'pixel statistics':24s} {'yes, ' + grid if req.statistics else 'no'}")
    print(f"  {'individual samples':24s} {'yes' if req.samples else 'no'}")
    print(f"  {'half-buffer pair':24s} "
          + ("accepted in place of the samples (--half-buffer)" if req.half_buffers and req.samples else
             "accepted (--half-buffer; merged)" if req.half_buffers else "no"))
    print(f"  {'per-sample features':24s} "
          + {"required": "required (albedo, normal, depth: a log's /features/NAME, a renderer's replies)",
             "optional": "read when the input carries them"}.get(req.features, "not read"))
    print(f"  {'reference image':24s} {req.reference}")
    return 0


def _cmd_render_log(args):
    from ..renderers.scenes import get_scene, write_scene_log

    w, h = parse_size(args.size)
    check_log_output(args.output, overwrite=args.overwrite)
    if args.reference_exr is not None:
        if Path(args.reference_exr).resolve() == Path(args.output).resolve():
            raise InputError(str(args.reference_exr), "--reference-exr", "is the -o sample log: give another path")
        check_output(args.reference_exr)
    path = write_scene_log(get_scene(args.scene), args.output, width=w, height=h, spp=args.spp, seed=args.seed,
                           features=getattr(args, "features", None), sampler=args.sampler)
    print(f"wrote {path}")
    if args.reference_exr is not None:
        from ..io import read_log

        log = read_log(path)   # the reference exactly as stored in the log
        # with its sRGB preview beside it (REF.png), as every other EXR the command line writes
        for written in write_outputs(log.reference(), args.reference_exr, channels=log.channels, png=None,
                                     exposure=0.0):
            print(f"wrote {written}")
    return 0


#: CPU seconds numba took to compile each part's kernels on a first demo in one process (measured with
#: benchmarks/bench_first_run.py --one-process on 2 loaded cores; kernels that several methods share are
#: counted with the first method that runs them).
_DEMO_COMPILE_SECONDS = {"renderers/scenes": 6, "core": 5, "filters": 4, "methods/box.py": 0.5, "methods/gem": 1,
                         "methods/awr": 0.5, "methods/splat": 6, "methods/ci": 0.5, "methods/auto": 12,
                         "methods/nfor": 25}
#: A warm-up of every method on a tiny log takes well under a second once the kernels are cached (0.2 s
#: measured): still running after this many seconds, it is compiling.
_COMPILING_AFTER = 2.0
#: A cold warm-up expected to take at least this long compiles on two processes (a second interpreter
#: costs ~1 s to start, and compiles again the kernels both halves of the methods use).
_TWO_PROCESSES_AFTER = 8.0


#: The second compiler gives up when the tiny log has not appeared after this many seconds.
_CHILD_WAIT = 600.0


def _warm_up_child_main(log_path: str, ready: str, names) -> int:
    """The second compiler of a cold demo: reconstruct the tiny log at ``log_path`` (once the file ``ready``
    exists) with the methods ``names``, which compiles their kernels into numba's cache."""
    import os

    from ..io import read_log
    from ..methods import get_method
    from ..offline.reconstruction import reconstruct

    methods = [get_method(n) for n in names]   # imports their modules while the parent renders the log
    parent = os.getppid()
    t0 = time.monotonic()
    while not os.path.exists(ready):
        if os.getppid() != parent or time.monotonic() - t0 > _CHILD_WAIT:
            return 1
        time.sleep(0.05)
    log = read_log(log_path)
    for m in methods:
        reconstruct(log, method=m)
    return 0


def _warm_up_child(log_path: Path, ready: Path, names):
    """Start :func:`_warm_up_child_main` in a second interpreter, or None when it cannot start.  Its output is
    discarded: the parent compiles whatever it failed to."""
    import os
    import subprocess
    import sys

    env = dict(os.environ)
    # the same mcrecon as this process, whatever the working directory
    root = str(Path(__file__).resolve().parents[2])
    env["PYTHONPATH"] = os.pathsep.join([root] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
    code = ("import sys\nfrom mcrecon.cli.builtins import _warm_up_child_main\n"
            f"sys.exit(_warm_up_child_main({str(log_path)!r}, {str(ready)!r}, {list(names)!r}))")
    try:
        return subprocess.Popen([sys.executable, "-c", code], env=env, stdin=subprocess.DEVNULL,
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    except OSError:
        return None


def _two_process_split(costs, shared: float) -> int:
    """Where to cut the methods (in their order) so that this process compiles ``costs[:k]`` and a second
    one ``costs[k:]``, both also paying ``shared``: the ``k`` of the least longer side (:func:`_longer_side`);
    ``len(costs)`` (no second process) when that saves less than 2 s."""
    total = shared + sum(costs)
    best_k = min(range(1, len(costs) + 1), key=lambda k: _longer_side(costs, shared, k))
    return best_k if total >= _TWO_PROCESSES_AFTER and total - _longer_side(costs, shared, best_k) >= 2.0 \
        else len(costs)


def _longer_side(costs, shared: float, k: int) -> float:
    """Expected seconds of a warm-up split at ``k``: the longer of this process's and the second one's (which
    starts ~1 s later); ``k == len(costs)``: all in this process."""
    if k >= len(costs):
        return shared + sum(costs)
    return shared + max(sum(costs[:k]), 1.0 + sum(costs[k:]))


def _demo_warm_up(scene, methods, spp, seed) -> None:
    """Render a tiny log and reconstruct it with every method: compiles (or loads from numba's cache) every
    kernel the demo runs, with the one-line notice when that takes long (a cold cache).

    On a cold cache with two or more usable cores the methods at the end of the list compile in a second
    interpreter at the same time (numba compiles one kernel at a time per process; the second one imports
    while this one renders the tiny log, then reads it); this process reconstructs those methods once it
    has finished, loading their kernels from the cache.
    """
    import tempfile
    import threading

    from ..filters.engine import n_threads
    from ..io import read_log
    from ..offline.reconstruction import reconstruct
    from ..renderers.scenes import write_scene_log
    from ._common import compile_notice, numba_cache_cold

    base = ("renderers/scenes", "core", "filters")
    parts = tuple(dict.fromkeys(base + tuple(p for m in methods.values() for p in method_kernels(m))))
    cold = {p for p in parts if numba_cache_cold((p,))}
    # the expected time: of the parts whose numba cache index is missing; of all of them when every index is
    # there and the warm-up is slow all the same (numba keeps its cache somewhere this check does not look)
    guess = (sum(_DEMO_COMPILE_SECONDS.get(p, 1) for p in cold)
             or sum(_DEMO_COMPILE_SECONDS.get(p, 1) for p in parts))
    names = list(methods)
    split = len(names)
    if cold and len(names) > 1 and n_threads() > 1:
        seen: set = set(base)
        costs = []
        for m in methods.values():
            own = [p for p in method_kernels(m) if p not in seen]
            seen.update(own)
            costs.append(sum(_DEMO_COMPILE_SECONDS.get(p, 1) for p in own if p in cold))
        shared = sum(_DEMO_COMPILE_SECONDS.get(p, 1) for p in base if p in cold)
        split = _two_process_split(costs, shared)
        guess = min(guess, _longer_side(costs, shared, split))
    timer = threading.Timer(_COMPILING_AFTER, compile_notice, kwargs={"seconds": guess})
    timer.daemon = True
    timer.start()
    try:
        with tempfile.TemporaryDirectory() as tmp:
            path, ready = Path(tmp) / "warm-up.h5", Path(tmp) / "ready"
            child = _warm_up_child(path, ready, names[split:]) if split < len(names) else None
            try:
                log = read_log(write_scene_log(scene, path, width=16, height=16, spp=spp, seed=seed))
                ready.touch()
                for i, method in enumerate(methods.values()):
                    if i == split and child is not None:
                        child.wait()  # its kernels are in numba's cache now: the reconstructions below load them
                    reconstruct(log, method=method)
            finally:
                if child is not None and child.poll() is None:  # interrupted: the second compiler stops too
                    child.kill()
                    child.wait()
    finally:
        timer.cancel()


def _cmd_demo(args):
    """The README's main job: render a log of a built-in scene, reconstruct, write EXR + PNG, print error."""
    from ..io import read_log, write_exr, write_png_preview
    from ..methods import available_methods, get_method
    from ..core.metrics import relative_mse
    from ..offline.reconstruction import reconstruct
    from ..renderers.scenes import get_scene, write_scene_log

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    w, h = parse_size(args.size)
    scene = get_scene(args.scene)
    methods = {name: get_method(name) for name in
               ([m for m in args.methods.split(",") if m] if args.methods else available_methods())}
    # by default, the methods that need per-sample features (nfor) only on the scenes whose logs hold them
    # (the textured scenes: write_scene_log's features default to the scene's features_default)
    has_features = bool(scene.features_default and scene.feature_names)
    skipped = [] if args.methods or has_features else [n for n, m in methods.items()
                                                       if m.requires.features == "required"]
    methods = {n: m for n, m in methods.items() if n not in skipped}
    _demo_warm_up(scene, methods, args.spp, args.seed)
    t0 = time.perf_counter()
    log_path = write_scene_log(scene, out / f"{scene.name}.h5", width=w, height=h, spp=args.spp, seed=args.seed)
    t_render = time.perf_counter() - t0
    log = read_log(log_path)
    ref = log.reference()
    feats = f" with features {', '.join(log.feature_names)}" if log.feature_names else ""
    print(f"rendered {scene.name} {w}x{h} at {args.spp} spp: {log.n_samples} samples{feats} in {t_render:.2f} s "
          f"-> {log_path}")
    for name, method in methods.items():
        reconstruct(log, method=method)  # whatever the warm-up's tiny log left to compile: not timed
        t1 = time.perf_counter()
        img = reconstruct(log, method=method)
        dt = time.perf_counter() - t1
        paths = write_outputs(img, out / f"{scene.name}_{name}.exr", channels=log.channels, png=None,
                              exposure=args.exposure)
        print(f"{name:6s} relative MSE {relative_mse(img, ref):.7g}  time* {dt:.3f} s  -> "
              + ", ".join(str(p) for p in paths))
    write_exr(out / f"{scene.name}_reference.exr", ref, channels=log.channels)
    write_png_preview(out / f"{scene.name}_reference.png", ref, exposure=args.exposure)
    print("* time: the method's second reconstruction of the log, so without the kernel compilation of a first run")
    if skipped:
        print(f"not run: {', '.join(skipped)} (need per-sample features, which this scene does not render; the "
              "textured scenes do: `mcrecon scenes`)")
    if "ci" in methods and "box" in methods:
        print("ci is box here by design: on uniform samples it reconstructs the pixel mean (its part is where to "
              "sample: `mcrecon adapt --method ci`)")
    return 0


def _cmd_mitsuba(args):
    from ..io import read_log, write_exr, write_png_preview
    from ..renderers import mitsuba as mb

    scene = None if args.scene in (None, "cornell-box") else args.scene
    # a scene file renders at its own film size unless --size is given; the Cornell box at 128x128
    w, h = (None, None) if args.size is None and scene is not None else parse_size(args.size or "128x128")
    if args.mitsuba_command == "reference":
        check_output(args.output)
    else:
        check_log_output(args.output, overwrite=args.overwrite)
    t0 = time.perf_counter()
    if args.mitsuba_command == "reference":
        with film_size_flag(args.size):
            ref = mb.render_reference(scene, width=w, height=h, spp=args.spp, seed=args.seed)
        out = Path(args.output)
        write_exr(out, ref)
        write_png_preview(out.with_suffix(".png"), ref)
        print(f"rendered a {ref.shape[1]}x{ref.shape[0]}, {args.spp}-spp reference in {time.perf_counter() - t0:.1f} s")
        print(f"wrote {out}\nwrote {out.with_suffix('.png')}")
    else:
        with film_size_flag(args.size):
            path = mb.dump_uniform_log(args.output, scene, width=w, height=h, spp=args.spp, seed=args.seed,
                                       reference_spp=args.reference_spp, features=args.features)
        lg = read_log(path)
        print(f"rendered a {lg.width}x{lg.height}, {args.spp}-spp uniform log in {time.perf_counter() - t0:.1f} s")
        print(f"wrote {path}")
    return 0
