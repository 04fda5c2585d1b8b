"""CLI registration of the experiment commands (``mcrecon experiment ...``, ``mcrecon bias``).

Each command only composes the public functions of :mod:`mcrecon.experiments`
and the method modules, and writes JSON/CSV numbers and PNG figures.
"""

from __future__ import annotations

import json
from pathlib import Path

from .errors import InputError


def _csv_list(text, conv=str, what="list"):
    items = [x.strip() for x in str(text).split(",") if x.strip()]
    try:
        return [conv(x) for x in items]
    except ValueError:
        raise InputError("experiment", what, f"{text!r}: expected a comma-separated list") from None


def _size(text):
    from .cli import _parse_size

    return _parse_size(text)


def cmd_convergence(args):
    from .experiments.convergence import run_convergence

    res = run_convergence(args.scene, methods=_csv_list(args.methods) if args.methods else None,
                          spp=_csv_list(args.spp, int, "--spp"), size=_size(args.size), seed=args.seed,
                          modes=_csv_list(args.modes, str, "--modes"),
                          oidn=None if args.oidn == "auto" else args.oidn == "yes", out=args.out)
    for r in res.rows:
        print(f"{r['method']:6s} {r['mode']:8s} spp {r['spp']:4d}  relMSE {r['relative_mse']:.5g}  "
              f"SSIM {r['ssim']:.4f}  renderer {r['renderer_seconds']:.3f} s  toolkit {r['toolkit_seconds']:.3f} s")
    for f in res.files:
        print(f"wrote {f}")
    return 0


def cmd_stability(args):
    from .experiments.stability import run_stability, write_stability_table

    rows = run_stability(methods=_csv_list(args.methods) if args.methods else None,
                         cases=_csv_list(args.cases) if args.cases else None, seed=args.seed)
    path = write_stability_table(rows, Path(args.out) / "stability.md")
    fails = [r for r in rows if not r["passed"]]
    print(f"{len(rows)} runs, {len(fails)} failure(s)")
    for r in fails:
        print(f"FAIL {r['case']} {r['method']} {r['mode']}: {r['error'] or r['warnings']}")
    print(f"wrote {path}\nwrote {path.with_suffix('.json')}")
    return 1 if fails else 0


def cmd_gallery(args):
    from .experiments.gallery import write_gallery

    path = write_gallery(args.out, scenes=_csv_list(args.scenes) if args.scenes else None,
                         methods=_csv_list(args.methods) if args.methods else None, size=_size(args.size),
                         spp=args.spp, seed=args.seed)
    print(f"wrote {path}")
    return 0


def register(sub) -> None:
    """Add the experiment sub-commands to the ``mcrecon`` parser."""
    from .cli import _OneLineParser

    ex = sub.add_parser("experiment", help="figures and tables: convergence, error-rate, stability, normality")
    es = ex.add_subparsers(dest="experiment", required=True, parser_class=_OneLineParser)

    s = es.add_parser("convergence", help="relative MSE/RMSE/SSIM against spp and wall time, per method")
    s.add_argument("--scene", default="soft_shadow")
    s.add_argument("--methods", default=None, help="comma-separated (default: all available)")
    s.add_argument("--spp", default="4,8,16,32,64,128")
    s.add_argument("--size", default="128x128")
    s.add_argument("--modes", default="uniform,adaptive")
    s.add_argument("--oidn", default="auto", choices=("auto", "yes", "no"))
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--out", required=True)
    s.set_defaults(func=cmd_convergence)

    s = es.add_parser("stability", help="every method on stiff and extreme inputs; outcome table")
    s.add_argument("--methods", default=None)
    s.add_argument("--cases", default=None, help="comma-separated case names (default: all)")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--out", required=True)
    s.set_defaults(func=cmd_stability)

    s = es.add_parser("gallery", help="the documentation gallery: every scene and method (writes OUT/gallery.md)")
    s.add_argument("--scenes", default=None)
    s.add_argument("--methods", default=None)
    s.add_argument("--size", default="96x96")
    s.add_argument("--spp", type=int, default=16)
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--out", required=True)
    s.set_defaults(func=cmd_gallery)

    try:
        from . import experiments_stats_cli
    except ImportError:
        return
    experiments_stats_cli.register(sub, es)
