"""``mcrecon batch``: many sample logs or pixel-statistics EXRs -> one EXR each, on a Dask cluster
(:mod:`mcrecon.distributed`)."""

from __future__ import annotations

import argparse
import sys

from ._common import (HelpFormatter, add_exr_read_flags, add_method_options, exr_read_options, finite_float,
                      make_method, method_flags)

__all__ = ["register"]


def _cmd_batch(args):
    from ..distributed.batch import reconstruct_many
    from ..errors import InputError

    if args.workers is not None and args.scheduler is not None:
        raise InputError("batch", "--workers/--scheduler", "give one: --workers N starts a local cluster, "
                         "--scheduler ADDRESS uses a running one")
    if not args.logs and args.seed_sets is None:
        raise InputError("batch", "FRAME", "no frame given: sample logs or EXRs, or --seed-sets PATTERN")
    method = make_method(args.method, args, args.method_flags)
    res = reconstruct_many(args.logs, seed_sets=args.seed_sets, method=method, out_dir=args.out_dir, scheduler=args.scheduler,
                           workers=args.workers, nonfinite=args.nonfinite, force=args.force, png=args.png,
                           exposure=args.exposure, progress=False if args.quiet else None,
                           exr_options=exr_read_options(args, given_only=True) or None)
    done = sum(r["status"] == "done" for r in res.records)
    skipped = sum(r["status"] == "skipped" for r in res.records)
    for r in res.failed:
        sys.stderr.write(f"mcrecon: error: {r['error']}\n")
    print(f"{method.name}: {len(res.records)} frame(s): {done} reconstructed, {skipped} up to date, "
          f"{len(res.failed)} failed, in {res.seconds:.2f} s")
    if res.summary_csv is not None:
        print(f"wrote {res.summary_csv}\nwrote {res.summary_json}")
    return 2 if res.failed else 0


def _positive_int(text: str) -> int:
    """An argparse type: an integer >= 1."""
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid integer: {text!r}") from None
    if n < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: expected a positive integer")
    return n


def register(sub, command: str | None = None) -> None:
    """Add ``mcrecon batch`` to the ``mcrecon`` sub-command parser (its method flags only when
    ``command`` is ``batch`` or None: they need every method class)."""
    s = sub.add_parser("batch", help="reconstruct many sample logs or pixel-statistics EXRs on a Dask cluster "
                                     "(one EXR per frame)",
                       formatter_class=HelpFormatter,
                       description="Reconstruct every frame (a sample log, or a pixel-statistics EXR as "
                                   "`mcrecon reconstruct` reads one) into OUT_DIR/<frame name>.exr exactly as "
                                   "`mcrecon reconstruct` would, on a local Dask cluster (--workers) or a running "
                                   "scheduler (--scheduler). A rerun skips frames whose EXR is newer than the "
                                   "frame and readable (its header fits the frame); a failing "
                                   "frame is reported and the others complete (exit status 2). Writes "
                                   "OUT_DIR/batch_summary.csv and .json. Needs the dask extra: "
                                   "pip install 'mcrecon[dask]'.")
    s.add_argument("logs", nargs="*", metavar="FRAME", help="sample logs (.h5) or pixel-statistics EXRs (.exr), or "
                        "glob patterns (quote them: 'frames/*.h5', 'frames/*.exr'); a name that exists is that "
                        "file, literally")
    s.add_argument("--seed-sets", default=None, metavar="PATTERN",
                   help="frames that are seed sets (K >= 2 renders of each frame with different seeds): "
                        "'shot.####.seed*.exr' (quoted), # the frame number's digits, * the seed; each frame's "
                        "renders give its mean, variance and half buffers, written as OUT_DIR/shot.0001.exr "
                        "(docs/pixel-statistics-inputs.md#seed-sets)")
    s.add_argument("--out-dir", required=True, metavar="DIR", help="output directory (shared with the workers)")
    s.add_argument("--workers", type=_positive_int, default=None, metavar="N",
                   help="worker processes of the local cluster (default and at most: the cores, "
                        "and no more than the frames)")
    s.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="a running Dask scheduler, e.g. tcp://10.0.0.1:8786 (workers need mcrecon and the files)")
    s.add_argument("--force", action="store_true", help="reconstruct up-to-date frames too")
    s.add_argument("--png", action="store_true", help="also write each frame's PNG preview")
    s.add_argument("--exposure", type=finite_float, default=0.0, help="preview exposure in stops")
    s.add_argument("--nonfinite", default="drop", choices=("drop", "zero", "raise"),
                   help="policy for NaN/Inf sample values (default drop)")
    s.add_argument("--quiet", action="store_true", help="no progress bar")
    add_exr_read_flags(s, "pixel-statistics EXR frames (FRAME ending in .exr)",
                       "How every EXR frame is read, as `mcrecon reconstruct` reads one: layout presets, or an "
                       "explicit mapping; the count from --spp, --count or the file's samplesPerPixel/spp "
                       "attribute (Mitsuba's moment EXRs carry none: give --spp N). Refused when a frame is a "
                       "sample log.")
    s.set_defaults(func=_cmd_batch)
    if command not in (None, "batch"):
        return
    flags = method_flags(set(s._option_string_actions))
    from ..methods import available_methods

    s.add_argument("--method", default="box", metavar="NAME",
                   help=f"reconstruction method: {', '.join(available_methods())} (default box)")
    add_method_options(s, flags)
    s.set_defaults(func=_cmd_batch, method_flags=flags)
