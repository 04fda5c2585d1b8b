"""The ``mcrecon`` command line: it only composes public calls.

Exit status 0 on success; on bad input, 2 with one line on stderr naming
the file, the field and what was expected (no traceback).
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from .errors import InputError, McreconWarning, RendererError

__all__ = ["main", "build_parser"]


class _OneLineParser(argparse.ArgumentParser):
    def error(self, message):  # one line, exit 2
        sys.stderr.write(f"{self.prog}: error: {message}\n")
        raise SystemExit(2)


def _method_option_specs():
    """{cli name: [(method name, Option), ...]} over the available methods."""
    from .methods import available_methods, method_class

    specs = {}
    for name in available_methods():
        for opt in method_class(name).options:
            specs.setdefault(opt.name, []).append((name, opt))
    return specs


def _flag(p, name):
    """The CLI flag of a method option: --NAME, or --method-NAME where the command has its own --NAME."""
    flag = "--" + name.replace("_", "-")
    return flag if flag not in p._option_string_actions else "--method-" + name.replace("_", "-")


def _add_method_args(p):
    p.add_argument("--method", default="box", help="reconstruction method (see `mcrecon methods`)")
    g = p.add_argument_group("method options (each applies to the methods named in its help)")
    for oname, owners in sorted(_method_option_specs().items()):
        opt = owners[0][1]
        choices = f" {{{','.join(map(str, opt.choices))}}}" if opt.choices else ""
        helps = "; ".join(f"{m}: {o.help} (default {o.default})" for m, o in owners)
        g.add_argument(_flag(p, oname), dest="mopt_" + oname, default=None, metavar="V", help=f"{helps}{choices}")


def _convert(opt, text, method):
    if opt.type is bool:
        t = str(text).strip().lower()
        if t in ("1", "true", "yes", "on"):
            return True
        if t in ("0", "false", "no", "off"):
            return False
        raise InputError(f"method {method}", "--" + opt.name.replace("_", "-"), f"{text!r}: expected true or false")
    try:
        return opt.type(text)
    except (TypeError, ValueError):
        raise InputError(f"method {method}", "--" + opt.name.replace("_", "-"),
                         f"{text!r}: expected a value of type {getattr(opt.type, '__name__', opt.type)}") from None


def _make_method(args):
    from .methods import get_method, method_class

    cls = method_class(args.method)
    own = {o.name: o for o in cls.options}
    opts = {}
    for key, value in vars(args).items():
        if not key.startswith("mopt_") or value is None:
            continue
        name = key[5:]
        if name not in own:
            raise InputError(f"method {args.method}", "--" + name.replace("_", "-"),
                             f"does not apply to this method; its options: "
                             f"{', '.join('--' + o.replace('_', '-') for o in own) or '(none)'}")
        opts[name] = _convert(own[name], value, args.method)
    return get_method(args.method, **opts)


def _check_output(out, png=None):
    """Refuse an output the run could not write, before any work is done."""
    if out is None:
        raise InputError("mcrecon", "-o/--output", "missing: give the output EXR path")
    for p, suffix in ((Path(out), ".exr"), (None if png is None else Path(png), ".png")):
        if p is None:
            continue
        if p.suffix.lower() != suffix:
            raise InputError(str(p), "output", f"expected a path ending in {suffix}")
        parent = p.parent
        while not parent.exists() and parent != parent.parent:
            parent = parent.parent
        if not parent.is_dir() or not os.access(parent, os.W_OK):
            raise InputError(str(p), "output", f"cannot be written: {parent} is not a writable directory")


def _write_outputs(image, out, *, channels, png, exposure, diagnostics=None, diag_dir=None, counts=None):
    from .io import write_exr, write_false_colour, write_png_preview

    out = Path(out)
    write_exr(out, image, channels=channels)
    written = [out]
    png = out.with_suffix(".png") if png is None else Path(png)
    write_png_preview(png, image, exposure=exposure)
    written.append(png)
    if diag_dir is not None:
        d = Path(diag_dir)
        maps = dict(diagnostics or {})
        if counts is not None:
            maps.setdefault("sample_density", counts)
        for name, m in maps.items():
            m = np.asarray(m)
            if m.ndim == 3 and m.shape[2] > 1:
                m = m.mean(axis=2)
            written.append(write_false_colour(d / f"{name}.png", m))
    return written


# ----------------------------------------------------------------- commands
def cmd_info(args):
    from .io import read_log
    from .stats import PixelStats

    log = read_log(args.log)
    n_nonfinite = 0
    n_negative = 0
    stats = PixelStats(log.width, log.height, log.channels)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", McreconWarning)  # counted and reported below instead
        for chunk in log.iter_chunks(with_round=False):  # one pass: counts and statistics
            v = np.asarray(chunk.values)
            fin = np.isfinite(v)
            n_nonfinite += int((~fin.all(axis=1)).sum())
            n_negative += int((np.where(fin, v, 0) < 0).any(axis=1).sum())
            stats.add(chunk.positions, v, source=str(log.path))
    cnt = stats.count
    info = {
        "file": str(log.path), "format_version": 1, "width": log.width, "height": log.height,
        "channels": list(log.channels), "samples": log.n_samples, "rounds": log.n_rounds,
        "spp_min": int(cnt.min()), "spp_mean": float(cnt.mean()), "spp_max": int(cnt.max()),
        "empty_pixels": int((cnt == 0).sum()), "pixels_with_one_sample": int((cnt == 1).sum()),
        "nonfinite_samples": n_nonfinite, "negative_samples": n_negative,
        "value_dtype": str(log.value_dtype), "features": list(log.feature_names),
        "reference": log.has_reference, "metadata": log.metadata,
    }
    if args.json:
        print(json.dumps(info, indent=2, sort_keys=True))
    else:
        for k in ("file", "width", "height", "channels", "samples", "rounds", "spp_min", "spp_mean", "spp_max",
                  "empty_pixels", "pixels_with_one_sample", "nonfinite_samples", "negative_samples",
                  "value_dtype", "features", "reference"):
            v = info[k]
            if isinstance(v, list):
                v = ",".join(map(str, v)) or "-"
            if isinstance(v, float):
                v = f"{v:.3f}"
            print(f"{k:24s} {v}")
        if info["metadata"]:
            print(f"{'metadata':24s} {json.dumps(info['metadata'], sort_keys=True)}")
    return 0


def cmd_denoise(args):
    from .io import read_log
    from .metrics import relative_mse
    from .reconstruction import reconstruct
    from .stats import PixelStats

    _check_output(args.output, args.png)
    method = _make_method(args)
    log = read_log(args.log)
    t0 = time.perf_counter()
    rec = reconstruct(log, method=method, nonfinite=args.nonfinite, full=True)
    image = rec.image
    dt = time.perf_counter() - t0
    counts = None
    if args.diagnostics:
        counts = rec.inputs.stats.count if rec.inputs.stats is not None else \
            PixelStats.from_log(log, nonfinite=args.nonfinite).count
    written = _write_outputs(image, args.output, channels=log.channels, png=args.png, exposure=args.exposure,
                             diagnostics=rec.diagnostics(), diag_dir=args.diagnostics, counts=counts)
    msg = f"{method.name}: {log.width}x{log.height}, {log.n_samples} samples, reconstructed in {dt:.3f} s"
    ref = log.reference()
    if ref is not None:
        msg += f", relative MSE {relative_mse(image, ref):.6g} against the log's reference"
    print(msg)
    for p in written:
        print(f"wrote {p}")
    return 0


def _parse_size(text):
    try:
        w, h = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise InputError("--size", "size", f"{text!r}: expected WIDTHxHEIGHT, e.g. 128x128") from None
    if w < 1 or h < 1:
        raise InputError("--size", "size", f"{text!r}: expected at least 1x1")
    return w, h


def _renderer_from_spec(spec):
    kind = spec.get("kind")
    if kind == "scene":
        from .scenes import SceneRenderer, get_scene, reference_image

        scene = get_scene(spec["scene"])
        r = SceneRenderer(scene, width=spec["width"], height=spec["height"], seed=spec.get("seed", 0))
        return r, reference_image(scene, spec["width"], spec["height"])
    if kind == "command":
        from .external import CommandRenderer

        return CommandRenderer(spec["argv"], width=spec["width"], height=spec["height"],
                               channels=tuple(spec["channels"]), timeout=spec.get("timeout"),
                               workdir=spec.get("workdir")), None
    if kind == "mitsuba":
        from .mitsuba_bridge import MitsubaRenderer

        r = MitsubaRenderer(spec.get("scene"), width=spec["width"], height=spec["height"])
        return r, None
    raise InputError("renderer", "kind", f"unknown renderer kind {kind!r}; valid: scene, command, mitsuba")


def _report_run(res, ref, t_total, args):
    from .metrics import relative_mse

    n = res.stats.n_samples
    w, h = res.stats.width, res.stats.height
    msg = (f"{res.method.name}: {len(res.rounds)} round(s), {n} samples ({n / (w * h):.2f} spp), "
           f"stopped: {res.stopped}; time {t_total:.2f} s (renderer {res.renderer_seconds:.2f} s, "
           f"toolkit {res.toolkit_seconds:.2f} s)")
    if ref is not None:
        msg += f"; relative MSE {relative_mse(res.image, ref):.6g}"
    print(msg)


def cmd_adapt(args):
    from . import driver

    _check_output(args.output, args.png)
    if args.resume:
        from .io import read_log

        ignored = [flag for flag, v in (("--scene", args.scene), ("--renderer-cmd", args.renderer_cmd),
                                        ("--mitsuba", args.mitsuba), ("--spp", args.spp), ("--log", args.log),
                                        ("--reference", args.reference))
                   if v is not None]
        ignored += ["--" + k[5:].replace("_", "-") for k, v in vars(args).items() if k.startswith("mopt_") and v is not None]
        if args.method != "box" or args.seed != 0 or args.nonfinite != "drop" or args.storage_dtype != "float32":
            ignored.append("--method/--seed/--nonfinite/--storage-dtype")
        if ignored:
            raise InputError(str(args.resume), "resume", f"{', '.join(ignored)} cannot change a recorded run; "
                             "a resumed run keeps its settings (only --time-limit, -o, --png, --diagnostics, "
                             "--quiet apply)")
        log = read_log(args.resume)
        spec = (log.run_settings or {}).get("renderer_spec") or {}
        if not spec:
            raise InputError(str(args.resume), "run settings", "no renderer recorded; cannot resume")
        renderer, ref = _renderer_from_spec(spec)
        t0 = time.perf_counter()
        res = driver.resume(args.resume, renderer, progress=None if not args.quiet else False,
                            time_limit=args.time_limit)
        if ref is None:
            ref = log.reference()
    else:
        sources = [x for x in (args.scene, args.renderer_cmd, args.mitsuba) if x is not None]
        if len(sources) != 1:
            raise InputError("adapt", "renderer", "give exactly one of --scene NAME, --renderer-cmd CMD, "
                             "--mitsuba [SCENE.xml|cornell-box], or --resume LOG")
        if args.spp is None:
            raise InputError("adapt", "--spp", "missing: give the sample budget in samples per pixel")
        w, h = _parse_size(args.size)
        if args.scene is not None:
            spec = {"kind": "scene", "scene": args.scene, "width": w, "height": h, "seed": args.seed}
        elif args.renderer_cmd is not None:
            argv = shlex.split(args.renderer_cmd)
            if not argv:
                raise InputError("--renderer-cmd", "command", "empty")
            spec = {"kind": "command", "argv": argv, "width": w, "height": h,
                    "channels": args.channels.split(","), "timeout": args.timeout}
        else:
            spec = {"kind": "mitsuba", "scene": None if args.mitsuba == "cornell-box" else args.mitsuba,
                    "width": w, "height": h}
        renderer, ref = _renderer_from_spec(spec)
        if args.reference is not None:
            from .io import read_exr

            ref = read_exr(args.reference)[0].astype(np.float64)
        method = _make_method(args)
        t0 = time.perf_counter()
        res = driver.adapt(renderer, method, spp=args.spp, seed=args.seed, log=args.log, reference=ref,
                           time_limit=args.time_limit, progress=None if not args.quiet else False,
                           nonfinite=args.nonfinite, renderer_spec=spec,
                           track_error=args.rounds_json is not None and ref is not None,
                           storage_dtype=args.storage_dtype, metadata={"scene": spec.get("scene")})
    t_total = time.perf_counter() - t0
    written = _write_outputs(res.image, args.output, channels=res.stats.channels, png=args.png,
                             exposure=args.exposure, diagnostics=res.diagnostics(),
                             diag_dir=args.diagnostics, counts=res.stats.count)
    _report_run(res, ref, t_total, args)
    if args.rounds_json is not None:
        Path(args.rounds_json).write_text(json.dumps(res.rounds, indent=1))
        written.append(Path(args.rounds_json))
    for p in written:
        print(f"wrote {p}")
    return 0


def cmd_compare(args):
    from .io import read_exr
    from .metrics import compare

    img, _ = read_exr(args.image)
    ref, _ = read_exr(args.reference)
    out = compare(img, ref, eps=args.eps, data_range=args.data_range)
    if args.json:
        print(json.dumps(out, indent=2, sort_keys=True))
    else:
        for k, v in out.items():
            print(f"{k:16s} {v:.6g}")
    return 0


def cmd_scenes(args):
    from .scenes import get_scene, scene_names

    for name in scene_names():
        print(f"{name:16s} {get_scene(name).description}")
    return 0


def cmd_methods(args):
    from .methods import available_methods, method_class

    for name in available_methods():
        cls = method_class(name)
        doc = (cls.__doc__ or "").strip().splitlines()[0] if cls.__doc__ else ""
        opts = " ".join(f"--{o.name.replace('_', '-')}" for o in cls.options)
        print(f"{name:8s} {doc}" + (f"  [{opts}]" if opts else ""))
    return 0


def cmd_render_log(args):
    from .scenes import get_scene, write_scene_log

    w, h = _parse_size(args.size)
    path = write_scene_log(get_scene(args.scene), args.output, width=w, height=h, spp=args.spp, seed=args.seed)
    print(f"wrote {path}")
    return 0


def cmd_demo(args):
    """The README's main job: render a log of a built-in scene, reconstruct, write EXR + PNG, print error."""
    from .io import read_log
    from .methods import available_methods, get_method
    from .metrics import relative_mse
    from .reconstruction import reconstruct
    from .scenes import get_scene, write_scene_log

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    w, h = _parse_size(args.size)
    scene = get_scene(args.scene)
    t0 = time.perf_counter()
    log_path = write_scene_log(scene, out / f"{scene.name}.h5", width=w, height=h, spp=args.spp, seed=args.seed)
    t_render = time.perf_counter() - t0
    log = read_log(log_path)
    ref = log.reference()
    print(f"rendered {scene.name} {w}x{h} at {args.spp} spp: {log.n_samples} samples in {t_render:.2f} s -> {log_path}")
    methods = [m for m in args.methods.split(",") if m] if args.methods else available_methods()
    for name in methods:
        method = get_method(name)
        t1 = time.perf_counter()
        img = reconstruct(log, method=method)
        dt = time.perf_counter() - t1
        paths = _write_outputs(img, out / f"{scene.name}_{name}.exr", channels=log.channels, png=None,
                               exposure=args.exposure)
        print(f"{name:6s} relative MSE {relative_mse(img, ref):.6g}  time {dt:.3f} s  -> "
              + ", ".join(str(p) for p in paths))
    from .io import write_png_preview, write_exr
    write_exr(out / f"{scene.name}_reference.exr", ref, channels=log.channels)
    write_png_preview(out / f"{scene.name}_reference.png", ref, exposure=args.exposure)
    return 0


def cmd_mitsuba(args):
    from . import mitsuba_bridge as mb
    from .io import write_exr, write_png_preview

    w, h = _parse_size(args.size)
    scene = None if args.scene in (None, "cornell-box") else args.scene
    t0 = time.perf_counter()
    if args.mitsuba_command == "reference":
        ref = mb.render_reference(scene, width=w, height=h, spp=args.spp, seed=args.seed)
        out = Path(args.output)
        write_exr(out, ref)
        write_png_preview(out.with_suffix(".png"), ref)
        print(f"rendered a {w}x{h}, {args.spp}-spp reference in {time.perf_counter() - t0:.1f} s")
        print(f"wrote {out}\nwrote {out.with_suffix('.png')}")
    else:
        path = mb.dump_uniform_log(args.output, scene, width=w, height=h, spp=args.spp, seed=args.seed,
                                   reference_spp=args.reference_spp)
        print(f"rendered a {w}x{h}, {args.spp}-spp uniform log in {time.perf_counter() - t0:.1f} s")
        print(f"wrote {path}")
    return 0


def build_parser():
    p = _OneLineParser(prog="mcrecon", description="Adaptive sampling and reconstruction for Monte Carlo renderers.")
    sub = p.add_subparsers(dest="command", required=True, parser_class=_OneLineParser)

    s = sub.add_parser("info", help="describe a sample log")
    s.add_argument("log")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_info)

    def outputs(sp):
        sp.add_argument("-o", "--output", help="output EXR path")
        sp.add_argument("--png", default=None, help="preview PNG path (default: next to the EXR)")
        sp.add_argument("--exposure", type=float, default=0.0, help="preview exposure in stops")
        sp.add_argument("--diagnostics", default=None, metavar="DIR",
                        help="write the method's diagnostic maps (and sample density) as PNGs into DIR")
        sp.add_argument("--nonfinite", default="drop", choices=("drop", "zero", "raise"),
                        help="policy for NaN/Inf sample values (default drop, with a warning)")

    s = sub.add_parser("denoise", help="reconstruct an image from a sample log")
    s.add_argument("log")
    outputs(s)
    _add_method_args(s)
    s.set_defaults(func=cmd_denoise)

    s = sub.add_parser("adapt", help="run adaptive rounds against a renderer")
    s.add_argument("--scene", default=None, help="built-in scene (see `mcrecon scenes`)")
    s.add_argument("--renderer-cmd", default=None, metavar="CMD",
                   help="external renderer command line with {request} and {reply} placeholders "
                        "(split like a shell would, never run through one)")
    s.add_argument("--mitsuba", default=None, nargs="?", const="cornell-box", metavar="SCENE.xml",
                   help="Mitsuba 3 bridge (optional extra): a scene file, default the Cornell box")
    s.add_argument("--channels", default="R,G,B", help="channel names of an external renderer")
    s.add_argument("--timeout", type=float, default=600.0, help="seconds per round for an external renderer")
    s.add_argument("--size", default="128x128", help="film size WIDTHxHEIGHT (default 128x128)")
    s.add_argument("--spp", type=float, default=None, help="sample budget, average samples per pixel")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--log", default=None, help="sample log to write (commits every round)")
    s.add_argument("--resume", default=None, metavar="LOG", help="continue a killed run from its log")
    s.add_argument("--time-limit", type=float, default=None, help="wall seconds")
    s.add_argument("--reference", default=None, metavar="EXR",
                   help="reference image for the error (built-in scenes have their own)")
    s.add_argument("--storage-dtype", default="float32", choices=("float32", "float64"),
                   help="precision of stored positions/values; the statistics see exactly what is stored "
                        "(float64 for values like 1e6 +- 1e-3 whose spread float32 cannot hold)")
    s.add_argument("--rounds-json", default=None, metavar="FILE",
                   help="write per-round samples, renderer/toolkit seconds and (with a reference) the error")
    s.add_argument("--quiet", action="store_true", help="no progress bar")
    outputs(s)
    _add_method_args(s)
    s.set_defaults(func=cmd_adapt)

    s = sub.add_parser("compare", help="error metrics of an EXR against a reference EXR")
    s.add_argument("image")
    s.add_argument("reference")
    s.add_argument("--eps", type=float, default=0.01, help="relative MSE epsilon (default 0.01)")
    s.add_argument("--data-range", type=float, default=None, help="PSNR data range (default: reference max)")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_compare)

    s = sub.add_parser("scenes", help="list the built-in scenes")
    s.set_defaults(func=cmd_scenes)
    s = sub.add_parser("methods", help="list the reconstruction methods and their options")
    s.set_defaults(func=cmd_methods)

    s = sub.add_parser("render-log", help="dump a uniform sample log of a built-in scene (with its reference)")
    s.add_argument("--scene", required=True)
    s.add_argument("--spp", type=int, required=True)
    s.add_argument("--size", default="128x128")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("-o", "--output", required=True)
    s.set_defaults(func=cmd_render_log)

    s = sub.add_parser("mitsuba", help="Mitsuba 3 bridge (optional extra): reference images and uniform logs")
    ms = s.add_subparsers(dest="mitsuba_command", required=True, parser_class=_OneLineParser)
    for name, hlp in (("reference", "render a high-spp reference EXR (pixel means of jittered samples)"),
                      ("log", "dump a uniform sample log (optionally with a reference) for offline denoising")):
        m = ms.add_parser(name, help=hlp)
        m.add_argument("--scene", default=None, help="scene XML (default: the built-in Cornell box)")
        m.add_argument("--size", default="128x128")
        m.add_argument("--spp", type=int, default=1024 if name == "reference" else 16)
        m.add_argument("--seed", type=int, default=0)
        if name == "log":
            m.add_argument("--reference-spp", type=int, default=None, help="also store a reference of this spp")
        m.add_argument("-o", "--output", required=True)
        m.set_defaults(func=cmd_mitsuba)

    s = sub.add_parser("demo", help="the main job on a built-in scene: log, reconstruct, EXR + PNG, error")
    s.add_argument("--scene", default="soft_shadow")
    s.add_argument("--spp", type=int, default=16)
    s.add_argument("--size", default="128x128")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--methods", default=None, help="comma-separated (default: every available method)")
    s.add_argument("--exposure", type=float, default=0.0)
    s.add_argument("--out", default="mcrecon_demo")
    s.set_defaults(func=cmd_demo)

    from . import experiments_cli  # noqa: F401  (registers `experiment` and `bias` when present)
    experiments_cli.register(sub)
    return p


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    with warnings.catch_warnings():
        warnings.simplefilter("always", McreconWarning)
        showwarning = warnings.showwarning

        def _one_line(message, category, filename, lineno, file=None, line=None):
            if issubclass(category, McreconWarning):
                sys.stderr.write(f"mcrecon: warning: {message}\n")
            else:
                showwarning(message, category, filename, lineno, file, line)

        warnings.showwarning = _one_line
        try:
            return int(args.func(args) or 0)
        except (InputError, RendererError) as exc:
            sys.stderr.write(f"mcrecon: error: {exc}\n")
            return 2
        except OSError as exc:  # an output path that cannot be written, a full disk...
            where = exc.filename or "file system"
            sys.stderr.write(f"mcrecon: error: {where}: {exc.strerror or exc}\n")
            return 2
        except KeyboardInterrupt:
            sys.stderr.write("mcrecon: interrupted\n")
            return 130
        except BrokenPipeError:  # e.g. `mcrecon info LOG | head`
            return 0
        finally:
            warnings.showwarning = showwarning


if __name__ == "__main__":
    raise SystemExit(main())
