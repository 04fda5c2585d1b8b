"""The main commands: info, reconstruct (denoise), adapt, compare; the others are in :mod:`.builtins`.

Each only composes public calls of the package; imports are made where a
command needs them, so ``--help`` stays quick.
"""

from __future__ import annotations

import argparse
import json
import shlex
import time
from pathlib import Path

from ..errors import InputError
from ._common import (HelpFormatter, OneLineParser, add_exr_read_flags, add_method_options, add_sampler_flag,
                      add_scene_flags, check_log_output, check_output, exr_read_flags_given, exr_read_options,
                      film_size_flag, finite_float, given_method_options, jit_notice, make_method, method_flags,
                      method_kernels, parse_size, write_outputs)
from .builtins import _cmd_demo, _cmd_methods, _cmd_mitsuba, _cmd_render_log, _cmd_scenes

__all__ = ['register']

# ----------------------------------------------------------------- info
_INFO_LINES = ("file", "width", "height", "channels", "samples", "finite_samples", "rounds", "spp_min", "spp_mean",
               "spp_max",
               "empty_pixels", "pixels_with_one_sample", "nonfinite_samples", "negative_samples", "value_dtype",
               "features", "reference")


def _log_feature_details(path) -> list[dict]:
    """Name, components (canonical names where they fit) and stored dtype of each feature of a log."""
    from ..core.features import MAX_COMPONENTS, feature_components
    from ..io import read_log

    log = read_log(path)
    out = []
    for name in log.feature_names:
        shape = tuple(log.feature_shapes[name])
        k = shape[0] if len(shape) == 1 and shape[0] <= MAX_COMPONENTS else 1 if not shape else None
        comps = list(feature_components(name, k)) if k is not None else [f"shape {shape}"]
        dtype = log.feature_dtypes[name]  # the stored dtype, from the metadata (no row read)
        out.append({"name": name, "components": comps, "dtype": str(dtype)})
    return out


def _cmd_info(args):
    from ..io import summarize_log
    from ..io.pixel_exr import describe_pixel_exr
    from ..io.pixel_exr import is_pixel_file_source

    info = describe_pixel_exr(args.log) if is_pixel_file_source(args.log) else None
    if info is not None and (info["layout"] is None and not info["features"]):
        info = None  # a plain image: the log reader says what it is and what is accepted
    if info is not None:
        if info["layout"] is None:
            info["layout"] = "not recognised (explicit mapping: --mean ... --variance-channels ...)"
        if args.json:
            print(json.dumps(info, indent=2, sort_keys=True))
            return 0
        for k in ("file", "width", "height", "channels", "layout", "count"):
            v = info[k]
            print(f"{k:24s} {','.join(v) if isinstance(v, list) else v}")
        if not info["features"]:
            print(f"{'features':24s} -")
        for f in info["features"]:
            var = f"variance from {','.join(f['second_moments'])}" if f["second_moments"] else "no variance"
            print(f"{'feature ' + f['name']:24s} {','.join(f['channels'])} ({var})")
        return 0
    info = summarize_log(args.log)
    info["feature_details"] = _log_feature_details(args.log)
    if args.json:
        print(json.dumps(info, indent=2, sort_keys=True))
        return 0
    for k in _INFO_LINES:
        v = info[k]
        if isinstance(v, list):
            v = ",".join(map(str, v)) or "-"
        if isinstance(v, float):
            v = f"{v:.3f}"
        print(f"{k:24s} {v}")
        if k == "features":
            for f in info["feature_details"]:
                print(f"{'  ' + f['name']:24s} {len(f['components'])} component(s) "
                      f"{','.join(f['components'])}, {f['dtype']}")
    if info["metadata"]:
        print(f"{'metadata':24s} {json.dumps(info['metadata'], sort_keys=True)}")
    if info["writer_pid"] is not None:
        print(f"{'writer':24s} process {info['writer_pid']} is appending rounds (counts above: committed rounds)")
    return 0


# ----------------------------------------------------------------- denoise
def _refuse_pixel_stats_flags(args) -> None:
    flags = exr_read_flags_given(args)
    given = [f for f in flags if f != "--variance-of"] + (["--half-buffer"] if args.half_buffer is not None else [])
    if given or flags:
        raise InputError(str(args.log), ", ".join(given) or "--variance-of",
                         "applies to a pixel-statistics EXR input (a path ending in .exr), not to a sample log"
                         + (" (a log holds the samples: methods that use halves split them themselves)"
                            if args.half_buffer is not None else ""))


def _exr_note(rec) -> str:
    """What was read from the pixel-statistics EXR(s) of a reconstruction, for the note line."""
    first = rec.files[0]
    if len(rec.files) == 2:
        other = rec.files[1]
        count_source = (first.count_source if first.count_source == other.count_source
                        else f"{first.count_source} / {other.count_source}")
        name = f"{first.path} + {other.path} (half-buffer pair)"
    else:
        count_source, name = first.count_source, str(first.path)
    what = ", ".join(f"{k} {','.join(v)}" for k, v in first.sources.items() if k != "features")
    if first.sources.get("features"):
        what += ", features " + ", ".join(f"{f} ({','.join(c)})" for f, c in first.sources["features"].items())
    space = f"; reconstructed in {','.join(first.stats.channels)}, written as {','.join(first.output_channels)}" \
        if first.output_matrix is not None else ""
    return f"{name}: layout {first.layout}: {what}; count from {count_source}{space}"


def _cmd_reconstruct(args):
    import sys

    from .. import reconstruct
    from ..core.metrics import relative_mse
    from ..core.stats import PixelStats
    from ..io import read_log
    from ..offline.pixel_files import command_line, is_pixel_file_source

    check_output(args.output, args.png, command=args.command)
    exr = is_pixel_file_source(args.log)  # per-pixel statistics a renderer wrote (pbrt-v4, Mitsuba...)
    if not exr:
        _refuse_pixel_stats_flags(args)
    method = make_method(args.method, args, args.method_flags)  # validates the flags given
    if exr:
        if args.half_buffer is not None and not is_pixel_file_source(args.half_buffer):
            raise InputError(str(args.half_buffer), "--half-buffer", "expected an EXR of the other half of the "
                             "samples (a path ending in .exr)")
        source = (args.log, args.half_buffer) if args.half_buffer is not None else args.log
        log = ref = None
        features = False
    else:
        source = log = read_log(args.log)
        ref = log.reference()  # a bad reference is refused before the work, not after the output is written
        features = bool(log.feature_names)
    jit_notice(method_kernels(method, features=features))
    t0 = time.perf_counter()
    with command_line():  # refusals name this command's flags
        rec = reconstruct(source, method=method, nonfinite=args.nonfinite, full=True, fireflies=args.fireflies,
                          tile=args.tile, diagnostics=args.diagnostics is not None,
                          **({"exr_options": exr_read_options(args)} if exr else {}))
    dt = time.perf_counter() - t0
    if exr:
        sys.stderr.write(f"mcrecon: note: {_exr_note(rec)}\n")
    stats = rec.inputs.stats
    counts = None
    if args.diagnostics:
        counts = stats.count if stats is not None else PixelStats.from_log(log, nonfinite=args.nonfinite).count
    written = write_outputs(rec.image, args.output, channels=rec.channels, png=args.png, exposure=args.exposure,
                            diagnostics=rec.diagnostics() if args.diagnostics else None, diag_dir=args.diagnostics,
                           counts=counts)
    h, w, _ = rec.image.shape
    n_samples = log.n_samples if log is not None else int(stats.count.sum())
    msg = (f"{rec.method.name}: {w}x{h}, {n_samples} samples"
           + (" (a half-buffer pair)" if len(rec.files) == 2 else "") + f", reconstructed in {dt:.3f} s")
    dropped = stats.n_dropped if stats is not None else 0
    if rec.fireflies is not None and args.nonfinite == "drop":
        dropped = rec.fireflies.n_nonfinite  # removed before the split, so the base's statistics never saw them
    if dropped:
        msg += f" ({dropped} non-finite dropped)"
    if rec.fireflies is not None:
        msg += f", fireflies: {100 * rec.fireflies.moved_fraction:.3g} % of the luminance spread"
    if ref is not None:
        msg += f", relative MSE {relative_mse(rec.image, ref):.6g} against the log's reference"
    print(msg)
    _print_sanity(rec.sanity())
    for p in written:
        print(f"wrote {p}")
    return 0


#: Film size of a built-in scene, the Cornell box and an external renderer without --size.
DEFAULT_SIZE = "128x128"


# ----------------------------------------------------------------- adapt
def _renderer(args):
    """(the spec of the renderer the flags name, recorded in the log for --resume; the renderer).

    A Mitsuba scene file without ``--size`` renders at its own film size: the bridge reads it while
    loading the scene, and the spec records it."""
    from ..renderers.spec import renderer_from_spec

    sources = [x for x in (args.scene, args.renderer_cmd, args.mitsuba, args.blender) if x is not None]
    if len(sources) != 1:
        raise InputError("adapt", "renderer", "give exactly one of --scene NAME, --renderer-cmd CMD, "
                         "--mitsuba [SCENE.xml|cornell-box], --blender SCENE.blend, or --resume LOG")
    if args.camera is not None and args.blender is None:
        raise InputError("adapt", "--camera", "chooses the camera of a Blender scene (--blender)")
    if args.blender is not None:
        return _blender_renderer(args)
    if args.mitsuba not in (None, "cornell-box") and args.size is None:
        from ..renderers.mitsuba import MitsubaRenderer

        renderer = MitsubaRenderer(args.mitsuba, features="all" if args.features is None else args.features)
        return renderer.spec(), renderer
    spec = _renderer_spec(args)
    with film_size_flag(args.size):
        return spec, renderer_from_spec(spec)


def _blender_renderer(args):
    """(spec, renderer) of ``--blender SCENE.blend``: the file opened in bpy (its film size unless --size),
    after every flag is checked."""
    from ..renderers import blender as bl

    if args.sampler is not None:
        raise InputError("adapt", "--sampler", "chooses the sampler of a built-in scene (--scene); Cycles "
                         "continues each pixel's own pattern from the request's first_index")
    features = "all" if args.features is None else args.features
    bl.check_blender_features(features)
    size = None if args.size is None else parse_size(args.size)
    bl._check_blend(args.blender)
    renderer = bl.BlenderRenderer(args.blender, width=None if size is None else size[0],
                                  height=None if size is None else size[1], camera=args.camera, features=features)
    return renderer.spec(), renderer


def _refuse_spread_methods(method) -> None:
    """Refuse, before anything is rendered, a method whose rounds ask Cycles for counts that differ from
    pixel to pixel: Cycles renders one sample index over a rectangle, so such rounds render several times
    the samples they deliver (docs/blender.md, "What it costs")."""
    if method.name in ("gem", "awr") or (method.name == "auto" and method.params["sampling"] != "uniform"):
        raise InputError("adapt", "--method", f"{method.name}'s rounds ask for a different number of samples in "
                         "each pixel, which Cycles renders one sample index at a time over whole rectangles "
                         "(3.5-14x the time of a uniform log, docs/blender.md): with --blender use box, ci, splat, "
                         "nfor or auto --sampling uniform")


def _renderer_spec(args) -> dict:
    """The spec of the renderer the flags name (recorded in the log for --resume; one of them is named:
    :func:`_renderer`)."""
    from ..renderers.spec import command_spec, mitsuba_spec, scene_spec

    w, h = parse_size(DEFAULT_SIZE if args.size is None else args.size)
    if args.features is not None and args.mitsuba is None and args.scene is None:
        raise InputError("adapt", "--features", "chooses the per-sample features of the Mitsuba bridge "
                         "(--mitsuba) or of a built-in scene (--scene); an external renderer sends what it sends")
    if args.sampler is not None and args.scene is None:
        raise InputError("adapt", "--sampler", "chooses the sampler of a built-in scene (--scene); another "
                         "renderer samples as it does (it may continue each pixel's sequence from the request's "
                         "first_index, docs/renderer-protocol.md)")
    if args.scene is not None:
        from ..renderers.scenes import get_scene

        scene = get_scene(args.scene)
        feats = None
        if args.features is not None:
            if args.features not in ("all", "none"):
                raise InputError("adapt", "--features", f"{args.features!r}: with --scene, all (the scene's "
                                 f"{', '.join(scene.feature_names) or 'none'}) or none")
            feats = args.features == "all"
            if feats and not scene.feature_names:
                raise InputError("adapt", "--features", f"scene {scene.name!r} has no per-sample features "
                                 "(`mcrecon scenes`)")
        return scene_spec(scene.name, width=w, height=h, seed=args.seed, features=feats,
                          sampler=None if args.sampler in (None, "independent") else args.sampler)
    if args.renderer_cmd is not None:
        try:
            argv = shlex.split(args.renderer_cmd)
        except ValueError as exc:  # an unclosed quote
            raise InputError("--renderer-cmd", "command", f"{args.renderer_cmd!r}: {str(exc).lower()}; it is split "
                             "like a shell would (quote words with spaces, close every quote)") from None
        if not argv:
            raise InputError("--renderer-cmd", "command", "empty")
        return command_spec(argv, width=w, height=h, channels=args.channels.split(","), timeout=args.timeout)
    return mitsuba_spec(None if args.mitsuba == "cornell-box" else args.mitsuba, width=w, height=h,
                        features="all" if args.features is None else args.features)


def _refuse_run_flags(args) -> None:
    """A resumed run keeps its recorded settings: refuse flags that would change them."""
    ignored = [flag for flag, v in (("--scene", args.scene), ("--renderer-cmd", args.renderer_cmd),
                                    ("--mitsuba", args.mitsuba), ("--blender", args.blender),
                                    ("--camera", args.camera), ("--features", args.features), ("--sampler", args.sampler), ("--spp", args.spp),
                                    ("--log", args.log),
                                    ("--reference", args.reference)) if v is not None]
    ignored += [args.method_flags[k] for k in given_method_options(args)]
    if args.method != "box" or args.seed != 0 or args.nonfinite != "drop" or args.storage_dtype != "auto":
        ignored.append("--method/--seed/--nonfinite/--storage-dtype")
    if args.pipeline is not None:
        ignored.append("--pipeline/--no-pipeline")
    if ignored:
        raise InputError(str(args.resume), "resume", f"{', '.join(ignored)} cannot change a recorded run; "
                         "a resumed run keeps its settings (only --time-limit, -o, --png, --diagnostics, "
                         "--progress/--no-progress/--quiet apply)")


def _print_sanity(s) -> None:
    """One line: what the image does outside the range of its samples (metrics.output_sanity)."""
    if s is None:
        return
    print(f"output: {s['negative_pixels']} negative pixel(s) from non-negative samples, "
          f"{s['overshoot_pixels']} pixel(s) outside their 3x3 sample range (max {s['max_overshoot']:.4g})"
          + (f", {s['nonfinite_pixels']} non-finite" if s["nonfinite_pixels"] else ""))


def _run_times(res, t_total) -> str:
    """This session's wall time and its parts, which never add up to more than it.

    The parts are this session's rounds only (a resume's earlier sessions are
    named apart); pipelined, the renderer renders while the toolkit works, so
    the renderer's time is given with the time it waited for the toolkit.
    """
    new, old = res.rounds[res.resumed_rounds:], res.rounds[:res.resumed_rounds]
    r = sum(float(x["renderer_seconds"]) for x in new)
    k = sum(float(x["toolkit_seconds"]) for x in new)
    # the rest of the session: the final image, and the error after each round (--rounds-json)
    rest = f", final image {float(getattr(res, 'finish_seconds', 0.0) or 0.0):.2f} s"
    e = sum(float(x.get("eval_seconds", 0.0)) for x in new)
    if e > 0:
        rest += f", error after each round {e:.2f} s"
    if res.pipelined:
        text = (f"time {t_total:.2f} s (renderer {r:.2f} s, waiting for the toolkit {res.idle_seconds:.2f} s; "
                f"toolkit {k:.2f} s, overlapping the renderer{rest})")
    else:
        text = f"time {t_total:.2f} s (renderer {r:.2f} s, toolkit {k:.2f} s{rest})"
    if old:
        text += (f"; before this resume: {len(old)} round(s), renderer "
                 f"{sum(float(x['renderer_seconds']) for x in old):.2f} s, toolkit "
                 f"{sum(float(x['toolkit_seconds']) for x in old):.2f} s")
    return text


def _report_run(res, ref, t_total) -> None:
    from ..core.metrics import relative_mse

    # One count of samples (as `mcrecon info` and the round records): what the renderer delivered.
    n = res.samples
    w, h = res.stats.width, res.stats.height
    msg = (f"{res.method.name}: {len(res.rounds)} round(s), {n} samples ({n / (w * h):.2f} spp"
           + (f", {res.samples_dropped} non-finite dropped" if res.samples_dropped else "")
           + f"), stopped: {res.stopped}; " + _run_times(res, t_total))
    if ref is not None:
        msg += f"; relative MSE {relative_mse(res.image, ref):.6g}"
    print(msg)
    _print_sanity(res.sanity())


def _cmd_adapt(args):
    from ..adaptive import run as driver_run
    from ..io import read_log

    check_output(args.output, args.png, command=args.command)
    progress = args.progress
    if args.resume:
        _refuse_run_flags(args)
        t0 = time.perf_counter()
        res = driver_run.resume(args.resume, progress=progress, time_limit=args.time_limit)
        ref = read_log(args.resume).reference()
    else:
        from ..renderers.spec import reference_from_spec

        if args.spp is None:
            raise InputError("adapt", "--spp", "missing: give the sample budget in samples per pixel")
        if args.log is not None:  # an existing log is the driver's to refuse (it names --resume)
            check_log_output(args.log, flag="--log", overwrite=None)
        method = make_method(args.method, args, args.method_flags)
        if args.blender is not None:   # before Blender is started to read the scene
            _refuse_spread_methods(method)
        spec, renderer = _renderer(args)
        if args.reference is not None:
            from ..core.samples import check_reference
            from ..io import read_exr

            # checked here, where the file is known: the driver's check can name only "reference"
            ref = check_reference(read_exr(args.reference)[0], (renderer.height, renderer.width,
                                                                len(renderer.channels)), where=args.reference)
        else:
            ref = reference_from_spec(spec)
        # (a scene's flag, the Mitsuba bridge's names; a command renderer says nothing before its reply)
        sends = bool(getattr(renderer, "features", False))
        jit_notice(method_kernels(method, features=sends)
                   + (("renderers/scenes", "core", "filters") if args.scene is not None else ()))
        t0 = time.perf_counter()
        res = driver_run.adapt(renderer, method, spp=args.spp, seed=args.seed, log=args.log, reference=ref,
                           time_limit=args.time_limit, progress=progress, nonfinite=args.nonfinite,
                           renderer_spec=spec, track_error=args.rounds_json is not None and ref is not None,
                           storage_dtype=args.storage_dtype, metadata={"scene": spec.get("scene")},
                           pipeline=args.pipeline)
    t_total = time.perf_counter() - t0
    written = write_outputs(res.image, args.output, channels=res.stats.channels, png=args.png,
                            exposure=args.exposure, diagnostics=res.diagnostics(), diag_dir=args.diagnostics,
                            counts=res.stats.count)
    _report_run(res, ref, t_total)
    if args.rounds_json is not None:
        Path(args.rounds_json).write_text(json.dumps(res.rounds, indent=1))
        written.append(Path(args.rounds_json))
    for p in written:
        print(f"wrote {p}")
    return 0


# ----------------------------------------------------------------- small commands
def _compare_reference(path):
    """(reference image, its name): an EXR, or the reference a sample log keeps (``render-log`` stores one)."""
    from ..io import read_exr, read_log
    from ..io.images import EXR_MAGIC

    p = Path(path)
    try:
        with open(p, "rb") as fh:
            head = fh.read(8)
    except OSError:
        head = EXR_MAGIC  # read_exr names what is wrong (missing, a directory...)
    is_log = head == b"\x89HDF\r\n\x1a\n" or p.suffix.lower() in (".h5", ".hdf5")
    if head[:4] == EXR_MAGIC or not is_log:
        return read_exr(p)[0], str(p)
    log = read_log(p)
    ref = log.reference()
    if ref is None:
        raise InputError(str(p), "dataset /reference", "none: this sample log keeps no reference image; compare "
                         "against a reference EXR, or a log written by `mcrecon render-log` (which stores its "
                         "scene's exact reference)")
    return ref, f"{p}: dataset /reference"


def _cmd_compare(args):
    from ..io import read_exr
    from ..core.metrics import compare

    img, _ = read_exr(args.image)
    ref, ref_name = _compare_reference(args.reference)
    flip_mode = None if args.no_flip else ("ldr" if args.ldr_flip else "hdr")
    out = compare(img, ref, eps=args.eps, data_range=args.data_range, smape_eps=args.smape_eps,
                  flip_mode=flip_mode, names=(str(args.image), ref_name))
    if args.json:
        print(json.dumps(out, indent=2, sort_keys=True))
        return 0
    rows = [(f"relMSE (eps={out['relative_mse_eps']:g})", out["relative_mse"]),
            (f"SMAPE (eps={out['smape_eps']:g})", out["smape"]),
            ("1-SSIM", out["one_minus_ssim"])]
    if "flip" in out:
        rows.append((f"{out['flip_mode'].upper()}-FLIP", out["flip"]))
    rows += [("MSE", out["mse"]), ("RMSE", out["rmse"]),
             (f"PSNR (range={out['psnr_data_range']:g})", out["psnr"]), ("SSIM", out["ssim"])]
    for k, v in rows:
        print(f"{k:24s} {v:.6g}")
    for note in out.get("notes", []):
        print(f"note: {note}")
    return 0


# ----------------------------------------------------------------- parsers
def _outputs(sp) -> None:
    sp.add_argument("-o", "--output", help="output EXR path")
    sp.add_argument("--png", default=None, help="preview PNG path (default: next to the EXR)")
    sp.add_argument("--exposure", type=finite_float, default=0.0, help="preview exposure in stops")
    sp.add_argument("--diagnostics", default=None, metavar="DIR",
                    help="write the method's diagnostic maps (and sample density) as PNGs into DIR")
    sp.add_argument("--nonfinite", default="drop", choices=("drop", "zero", "raise"),
                    help="policy for NaN/Inf sample values (default drop, with a warning)")




def register(sub, command: str | None = None) -> None:
    """Add the main commands to the ``mcrecon`` sub-command parser.

    The method flags go to denoise, adapt and methods only when
    ``command`` is one of them, or None (every parser complete).
    """
    s = sub.add_parser("info", help="describe a sample log, or a pixel-statistics EXR (layout, features found)")
    s.add_argument("log", help="a sample log (.h5), or an EXR of per-pixel statistics (.exr)")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=_cmd_info)

    denoise = sub.add_parser("reconstruct", aliases=["denoise"], formatter_class=HelpFormatter,
                             help="reconstruct an image from a sample log or a pixel-statistics EXR (alias: denoise)")
    denoise.add_argument("log", help="a sample log (.h5), or an EXR of per-pixel statistics (.exr: mean, "
                         "variance, count; see docs/pixel-statistics-inputs.md)")
    _outputs(denoise)
    denoise.add_argument("--fireflies", default="none", choices=("none", "cascade"),  # fireflies.FIREFLY_MODES
                         help="cascade: split the samples into luminance cascades first; the method reconstructs "
                              "the base and rare bright parts are spread with the support their density needs "
                              "(energy kept; any method; needs a sample log, held in memory)")
    denoise.add_argument("--tile", type=int, default=None, metavar="N",
                         help="reconstruct in tiles of at most NxN pixels, each grown by the method's halo: the "
                              "untiled image, the log read one band of tiles at a time (memory: a band's statistics "
                              "and one tile's work; methods with a finite halo: box, ci, gem, nfor, auto (its "
                              "candidates in a pass over the tiles first, its whole-image decisions on the film); "
                              "every pixel needs 2 samples; docs/performance.md)")
    px = add_exr_read_flags(
        denoise, "pixel-statistics EXR input (a LOG ending in .exr)",
        "Layout presets, or an explicit mapping; the count from --spp, --count or the file's samplesPerPixel/spp "
        "attribute. Methods that need individual samples (splat, gem with --subpixel-exact-below > 0) refuse it; "
        "auto and nfor take a half-buffer pair (--half-buffer), and auto on one EXR its SURE candidates (box,gauss).")
    px.add_argument("--half-buffer", default=None, metavar="B.exr",
                    help="the other half of a half-buffer pair: an EXR of samples independent of LOG's (dual "
                         "buffers), read with the same layout flags (--spp/--count: each half's own); for methods "
                         "that use half buffers (auto, nfor)")
    denoise.set_defaults(func=_cmd_reconstruct)

    s = adapt = sub.add_parser("adapt", help="run adaptive rounds against a renderer", formatter_class=HelpFormatter)
    s.add_argument("--scene", default=None, help="built-in scene (see `mcrecon scenes`)")
    s.add_argument("--renderer-cmd", default=None, metavar="CMD",
                   help="external renderer command line with {request} and {reply} placeholders "
                        "(split like a shell would, never run through one)")
    s.add_argument("--mitsuba", default=None, nargs="?", const="cornell-box", metavar="SCENE.xml",
                   help="Mitsuba 3 bridge (optional extra): a scene file, default the Cornell box")
    s.add_argument("--blender", default=None, metavar="SCENE.blend",
                   help="Blender Cycles (optional extra, bpy): a .blend file; each round continues every pixel's "
                        "own Cycles sample pattern (methods that ask for samples per pixel: box, ci, splat, nfor)")
    s.add_argument("--camera", default=None, metavar="NAME",
                   help="with --blender: the camera object to render from (default: the scene's)")
    s.add_argument("--features", default=None, metavar="none|albedo,normal,depth",
                   help="with --mitsuba or --blender: the per-sample features of the primary hit it sends and the log stores "
                        "(default all three; none to switch off); with --scene: all or none (default: the "
                        "scene's, see `mcrecon scenes`)")
    add_sampler_flag(s)
    s.add_argument("--channels", default="R,G,B", help="channel names of an external renderer")
    s.add_argument("--timeout", type=float, default=600.0, help="seconds per round for an external renderer")
    s.add_argument("--size", default=None, help="film size WIDTHxHEIGHT (default 128x128; a --mitsuba scene "
                                                   "file or a --blender file: its own film's)")
    s.add_argument("--spp", type=float, default=None, help="sample budget, average samples per pixel")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--log", default=None, help="sample log to write (commits every round)")
    s.add_argument("--resume", default=None, metavar="LOG", help="continue a killed run from its log")
    s.add_argument("--time-limit", type=float, default=None, help="wall seconds")
    s.add_argument("--reference", default=None, metavar="EXR",
                   help="reference image for the error (built-in scenes have their own)")
    s.add_argument("--storage-dtype", default="auto", choices=("auto", "float32", "float64"),  # driver_schedule.STORAGE_DTYPES
                   help="precision of the stored positions/values (default auto: what the renderer sends, "
                        "float32 replies as float32, float64 replies as float64); the statistics see exactly "
                        "what is stored, so float32 storage of values like 1e6 +- 1e-3 loses their spread "
                        "(warned) and refuses values beyond float32's range")
    pipe = s.add_mutually_exclusive_group()
    pipe.add_argument("--pipeline", dest="pipeline", action="store_const", const=True, default=None,
                      help="render the next round while the toolkit commits and plans (one round of lag; "
                           "default: what the method declares: box and ci yes, gem and awr only when asked, "
                           "splat never)")
    pipe.add_argument("--no-pipeline", dest="pipeline", action="store_const", const=False,
                      help="strictly sequential rounds")
    s.add_argument("--rounds-json", default=None, metavar="FILE",
                   help="write per-round samples, renderer/toolkit seconds and (with a reference) the error")
    prog = s.add_mutually_exclusive_group()
    prog.add_argument("--progress", dest="progress", action="store_const", const=True, default=None,
                      help="per-round progress on stderr even when it is not a terminal (one line per event; "
                           "default: on a terminal only)")
    prog.add_argument("--no-progress", "--quiet", dest="progress", action="store_const", const=False,
                      help="no progress on stderr")
    _outputs(s)
    s.set_defaults(func=_cmd_adapt)

    # One flag per method option for both commands: --NAME, or --method-NAME where
    # a command has its own --NAME (ci's exposure: --method-exposure).
    # They need every method class: built only when one of these commands runs.
    flags = None
    if command is None or command in ("reconstruct", "denoise", "adapt", "methods"):
        taken = set(denoise._option_string_actions) | set(adapt._option_string_actions)
        flags = method_flags(taken)
        from ..methods import available_methods

        for p in (denoise, adapt):
            p.add_argument("--method", default="box", metavar="NAME",
                           help=f"reconstruction method: {', '.join(available_methods())} (default box); its "
                                "options are in the groups below; `mcrecon methods NAME` describes one")
            add_method_options(p, flags)
            p.set_defaults(method_flags=flags)

    s = sub.add_parser("compare", help="error metrics of an EXR against a reference EXR (or a sample log's reference)")
    s.add_argument("image")
    s.add_argument("reference", help="a reference EXR, or a sample log that stores one (`mcrecon render-log`)")
    s.add_argument("--eps", type=float, default=0.01, help="relative MSE epsilon (default 0.01)")
    s.add_argument("--data-range", type=float, default=None, help="PSNR data range (default: reference max)")
    s.add_argument("--smape-eps", type=float, default=0.01, help="SMAPE epsilon (default 0.01)")
    g = s.add_mutually_exclusive_group()
    g.add_argument("--ldr-flip", action="store_true",
                   help="LDR-FLIP on sRGB tone-mapped images instead of HDR-FLIP (the default)")
    g.add_argument("--no-flip", action="store_true", help="skip FLIP")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=_cmd_compare)

    s = sub.add_parser("scenes", help="list the built-in scenes")
    s.set_defaults(func=_cmd_scenes)
    s = sub.add_parser("methods", help="list the reconstruction methods, or describe one (options, inputs)")
    s.add_argument("name", nargs="?", default=None, metavar="NAME", help="a method to describe")
    s.add_argument("--json", action="store_true", help="the methods (or the one NAME) as JSON: options "
                   "(flag, type, default, valid values, variants) and inputs")
    s.set_defaults(func=_cmd_methods, method_flags=flags)

    s = sub.add_parser("render-log", help="dump a uniform sample log of a built-in scene (with its reference)")
    s.add_argument("--scene", required=True)
    s.add_argument("--spp", type=int, required=True)
    s.add_argument("--size", default="128x128")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("-o", "--output", required=True, help="the sample log to write (.h5)")
    s.add_argument("--overwrite", action="store_true", help="replace an existing -o log")
    s.add_argument("--features", action=argparse.BooleanOptionalAction, default=None,
                   help="store per-sample albedo, normal and depth in the log (default: the scene's, see "
                        "`mcrecon scenes`)")
    add_sampler_flag(s, default="independent")
    s.add_argument("--reference-exr", default=None, metavar="REF.exr",
                   help="also write the scene's exact reference (the one stored in the log) as an EXR, "
                        "e.g. for `mcrecon compare`")
    s.set_defaults(func=_cmd_render_log)

    s = sub.add_parser("mitsuba", help="Mitsuba 3 bridge (optional extra): reference images and uniform logs")
    ms = s.add_subparsers(dest="mitsuba_command", required=True, parser_class=OneLineParser)
    for name, hlp in (("reference", "render a high-spp reference EXR (pixel means of jittered samples)"),
                      ("log", "dump a uniform sample log (optionally with a reference) for offline denoising")):
        m = ms.add_parser(name, help=hlp)
        m.add_argument("--scene", default=None, help="scene XML (default: the built-in Cornell box)")
        m.add_argument("--size", default=None, help="film size WIDTHxHEIGHT (default: a scene file's own film, "
                                                    "the Cornell box 128x128)")
        m.add_argument("--spp", type=int, default=1024 if name == "reference" else 16)
        m.add_argument("--seed", type=int, default=0)
        if name == "log":
            m.add_argument("--reference-spp", type=int, default=None, help="also store a reference of this spp")
            m.add_argument("--features", default="all", metavar="none|albedo,normal,depth",
                           help="per-sample features of the primary hit to store (/features/NAME; default all "
                                "three: albedo, shading normal, camera-space depth; none to switch off)")
        if name == "log":
            m.add_argument("-o", "--output", required=True, help="the sample log to write (.h5)")
            m.add_argument("--overwrite", action="store_true", help="replace an existing -o log")
        else:
            m.add_argument("-o", "--output", required=True, help="the reference EXR to write (.exr)")
        m.set_defaults(func=_cmd_mitsuba)

    s = sub.add_parser("demo", help="the main job on a built-in scene: log, reconstruct, EXR + PNG, error")
    add_scene_flags(s)
    s.add_argument("--methods", default=None, help="comma-separated (default: every available method)")
    s.add_argument("--exposure", type=finite_float, default=0.0)
    s.add_argument("--out", default="mcrecon_demo")
    s.set_defaults(func=_cmd_demo)
