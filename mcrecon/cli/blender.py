"""``mcrecon blender``: sample logs and reference images of a Blender Cycles scene (the optional bpy extra)."""

from __future__ import annotations

import time
from pathlib import Path

from ..errors import InputError
from ._common import OneLineParser, check_log_output, check_output, parse_size

__all__ = ["register"]


def _spp(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        raise InputError("--spp", "spp", f"{text!r}: expected a whole number of samples per pixel") from None
    if n < 1:
        raise InputError("--spp", "spp", f"{n}: expected at least 1 sample per pixel")
    return n


def _cmd_blender(args):
    from ..io import read_log, write_exr, write_png_preview
    from ..renderers import blender as bl

    spp = _spp(args.spp)
    size = None if args.size is None else parse_size(args.size)
    if args.blender_command == "reference":
        check_output(args.output, command="mcrecon blender reference")
    else:
        check_log_output(args.output, overwrite=args.overwrite)
        bl.check_blender_features(args.features)
    bl._check_blend(args.scene)
    if not bl.bpy_available():
        raise InputError("bpy", "import", bl.BPY_MISSING)
    t0 = time.perf_counter()
    if args.blender_command == "reference":
        ref, _ = bl.render_reference(args.scene, spp=spp, size=size, camera=args.camera, threads=args.threads)
        out = Path(args.output)
        write_exr(out, ref)
        write_png_preview(out.with_suffix(".png"), ref)
        print(f"rendered Cycles' own {ref.shape[1]}x{ref.shape[0]}, {spp}-spp image in "
              f"{time.perf_counter() - t0:.1f} s")
        print(f"wrote {out}\nwrote {out.with_suffix('.png')}")
    else:
        path = bl.dump_cycles_log(args.output, args.scene, spp=spp, size=size, camera=args.camera,
                                  features=args.features, threads=args.threads, overwrite=args.overwrite)
        lg = read_log(path)
        print(f"rendered a {lg.width}x{lg.height}, {spp}-spp log of Cycles' own samples in "
              f"{time.perf_counter() - t0:.1f} s")
        print(f"wrote {path}")
    return 0


def register(sub, command: str | None = None) -> None:
    """Add ``mcrecon blender log|reference`` to the ``mcrecon`` sub-command parser."""
    s = sub.add_parser("blender", help="Blender Cycles bridge (optional extra, bpy): sample logs of Cycles' own "
                                       "samples, and Cycles' own reference render")
    bs = s.add_subparsers(dest="blender_command", required=True, parser_class=OneLineParser)
    for name, hlp in (("log", "render a .blend scene sample by sample into a sample log (sample k of each pixel "
                              "= Cycles' sample k, stratification kept)"),
                      ("reference", "render Cycles' own image of a .blend scene (the same settings) as an EXR")):
        m = bs.add_parser(name, help=hlp)
        m.add_argument("scene", help="the .blend file")
        m.add_argument("--spp", required=True, help="samples per pixel (Cycles' samples)")
        m.add_argument("--size", default=None, help="film size WIDTHxHEIGHT (default: the file's resolution)")
        m.add_argument("--camera", default=None, help="camera object to render from (default: the scene's)")
        m.add_argument("--threads", type=int, default=None, help="Cycles' render threads (default: every core)")
        if name == "log":
            m.add_argument("--features", default="all", metavar="all|none|albedo,normal,depth",
                           help="per-sample features from Cycles' Denoising Albedo/Normal/Depth passes "
                                "(default all)")
            m.add_argument("-o", "--output", required=True, help="the sample log to write (.h5)")
            m.add_argument("--overwrite", action="store_true", help="replace an existing -o log")
        else:
            m.add_argument("-o", "--output", required=True, help="the reference EXR to write (.exr)")
        m.set_defaults(func=_cmd_blender)
