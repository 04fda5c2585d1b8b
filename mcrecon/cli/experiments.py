"""The experiment commands: ``mcrecon experiment ...`` and ``mcrecon bias``.

Each only composes the public functions of :mod:`mcrecon.experiments`
and writes JSON/CSV numbers and PNG figures.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from ..errors import InputError
from ._common import (HelpFormatter, OneLineParser, add_method_options, add_scene_flags, make_method, method_flags,
                      parse_size)

__all__ = ["register"]


def _csv_list(text, conv=str, what="list"):
    items = [x.strip() for x in str(text).split(",") if x.strip()]
    try:
        return [conv(x) for x in items]
    except ValueError:
        raise InputError("experiment", what, f"{text!r}: expected a comma-separated list") from None


def _cmd_convergence(args):
    from ..experiments.convergence import run_convergence

    res = run_convergence(args.scene, methods=_csv_list(args.methods) if args.methods else None,
                          spp=_csv_list(args.spp, int, "--spp"), size=parse_size(args.size), seed=args.seed,
                          modes=_csv_list(args.modes, str, "--modes"),
                          oidn=None if args.oidn == "auto" else args.oidn == "yes",
                          out=args.out if args.out is not None else f"convergence_{args.scene}",
                          flip=None if args.flip == "auto" else args.flip == "yes", html=args.html,
                          features=args.features)
    for r in res.rows:
        flip = f"  FLIP {r['flip']:.4g}" if "flip" in r else ""
        print(f"{r['method']:6s} {r['mode']:8s} spp {r['spp']:4d}  relMSE {r['relative_mse']:.5g}  "
              f"SMAPE {r['smape']:.4g}  1-SSIM {r['one_minus_ssim']:.4g}{flip}  "
              f"renderer {r['renderer_seconds']:.3f} s  toolkit {r['toolkit_seconds']:.3f} s")
    for note in res.notes:
        print(f"note: {note}")
    for f in res.files:
        print(f"wrote {f}")
    return 0


def _cmd_report(args):
    from ..experiments.convergence import load_convergence
    from ..experiments.html_report import write_html_report

    out = Path(args.output)
    if out.suffix.lower() not in (".html", ".htm"):
        raise InputError(str(out), "-o", "expected a path ending in .html")
    result, scene = load_convergence(args.run_dir)
    run_dir = Path(args.run_dir)
    plots = [p for p in (run_dir / "convergence_spp.png", run_dir / "convergence_time.png") if p.exists()]
    print(f"wrote {write_html_report(out, result, scene=scene, plots=plots)}")
    return 0


def _cmd_oracle(args):
    from ..experiments.oracle import run_oracle

    res = run_oracle(args.scene, spp=args.spp, size=parse_size(args.size), seed=args.seed,
                     variance_spp=args.variance_spp,
                     methods=_csv_list(args.methods) if args.methods else None)
    if args.json:
        print(json.dumps(res, indent=2, sort_keys=True))
        return 0
    print(f"{res['scene']} {res['size'][0]}x{res['size'][1]}, {res['spp']} spp: oracle per-pixel "
          f"{res['oracle_per_pixel']:.4g}, best single scale {res['oracle_best_global']:.4g} "
          f"(sigma {res['oracle_best_global_sigma']:.3g} px), ceiling {res['ceiling']:.4g}")
    print(f"{'method':8s} {'relMSE':>10s} {'/ box':>8s} {'/ ceiling':>10s}")
    for name, r in res["methods"].items():
        print(f"{name:8s} {r['relative_mse']:10.4g} {r['to_box']:8.3g} {r['to_ceiling']:10.3g}")
    return 0


def _cmd_stability(args):
    args.out = args.out if args.out is not None else "stability"
    from ..experiments.stability import run_stability, write_stability_table

    rows = run_stability(methods=_csv_list(args.methods) if args.methods else None,
                         cases=_csv_list(args.cases) if args.cases else None, seed=args.seed)
    path = write_stability_table(rows, Path(args.out) / "stability.md")
    fails = [r for r in rows if not r["passed"]]
    print(f"{len(rows)} runs, {len(fails)} failure(s)")
    for r in fails:
        print(f"FAIL {r['case']} {r['method']} {r['mode']}: {r['error'] or r['warnings']}")
    print(f"wrote {path}\nwrote {path.with_suffix('.json')}")
    return 1 if fails else 0


def _cmd_gallery(args):
    args.out = args.out if args.out is not None else "gallery"
    from ..experiments.gallery import write_gallery

    path = write_gallery(args.out, scenes=_csv_list(args.scenes) if args.scenes else None,
                         methods=_csv_list(args.methods) if args.methods else None, size=parse_size(args.size),
                         spp=args.spp, seed=args.seed, html=args.html)
    print(f"wrote {path}")
    return 0


def _cmd_error_rate(args):
    args.out = args.out if args.out is not None else "error_rate"
    from ..experiments.error_rate import run_error_rate

    rep = run_error_rate(args.out, gammas=_csv_list(args.gammas, float, "--gammas"),
                         noise_vars=_csv_list(args.noise_vars, float, "--noise-vars"),
                         n_pixels=args.pixels, spp=args.spp, seed=args.seed)
    for r in rep["error_rate_vs_gamma"]:
        print(f"gamma {r['gamma']:.3f}  z {r['z']:.4f}  measured error rate {r['error_rate']:.4f}")
    print(f"unweighted S: error rate {rep['unweighted_error_rate']:.4f}")
    print(f"wrote {Path(args.out) / 'error_rate.json'}")
    return 0


def _cmd_normality(args):
    args.out = args.out if args.out is not None else f"normality_{args.scene}"
    from ..experiments.statistics import run_normality
    from ..renderers.scenes import SceneRenderer

    w, h = parse_size(args.size)
    renderer = SceneRenderer(args.scene, width=w, height=h, seed=args.seed)
    rep = run_normality(renderer, n_values=_csv_list(args.n, int, "--n"), m=args.m, seed=args.seed,
                        classes=args.classes, alpha=args.alpha, out=args.out)
    for r in rep["results"]:
        print(f"n = {r['n']:4d}: {100 * r['rejection_rate']:5.1f}% of {r['tests']} pixel-channel tests rejected "
              f"(chi2({r['df']}) critical {r['critical']:.2f})")
    print(f"wrote {Path(args.out) / 'normality.json'}")
    return 0


def _cmd_bias(args):
    args.out = args.out if args.out is not None else "bias_" + (Path(args.log).stem if args.log else str(args.scene))
    from ..experiments.statistics import run_bias

    if (args.log is None) == (args.scene is None):
        raise InputError("bias", "input", "give a LOG or --scene NAME (with --spp)")
    rule = make_method("ci", args, args.method_flags).rule  # the stopping rule of method ci
    if args.log is not None:
        source = args.log
    else:
        from ..renderers.scenes import get_scene, render_uniform

        w, h = parse_size(args.size)
        batch = render_uniform(get_scene(args.scene), width=w, height=h, spp=args.spp, seed=args.seed)
        source = {"positions": batch.positions, "values": batch.values, "width": w, "height": h}
    summary = run_bias(source, B=args.B, seed=args.seed, rule=rule, level=args.level,
                       threshold=args.threshold, out=args.out)
    print(json.dumps(summary, indent=1, default=float))
    print(f"wrote {Path(args.out) / 'bias.json'}")
    return 0


def register(sub, command: str | None = None) -> None:
    """Add the experiment commands to the ``mcrecon`` sub-command parser (bias's flags of method
    ci only when ``command`` is ``bias`` or None: they need the method class)."""
    r = sub.add_parser("report", help="the interactive HTML report of a convergence run's folder")
    r.add_argument("run_dir", metavar="RUN_DIR", help="the --out folder of `mcrecon experiment convergence`")
    r.add_argument("-o", "--output", required=True, metavar="HTML", help="the page to write (self-contained)")
    r.set_defaults(func=_cmd_report)
    ex = sub.add_parser("experiment", help="figures and tables: convergence, error-rate, stability, normality")
    es = ex.add_subparsers(dest="experiment", required=True, parser_class=OneLineParser)

    s = es.add_parser("convergence", help="relative MSE, SMAPE, 1-SSIM, FLIP against spp and wall time, per method")
    s.add_argument("--scene", default="soft_shadow")
    s.add_argument("--methods", default=None, help="comma-separated (default: all available)")
    s.add_argument("--spp", default="4,8,16,32,64,128")
    s.add_argument("--size", default="128x128")
    s.add_argument("--modes", default="uniform,adaptive")
    s.add_argument("--oidn", default="auto", choices=("auto", "yes", "no"))
    s.add_argument("--flip", default="auto", choices=("auto", "yes", "no"),
                   help="HDR-FLIP per point (auto: when flip-evaluator is installed)")
    s.add_argument("--features", action=argparse.BooleanOptionalAction, default=None,
                   help="render per-sample albedo, normal and depth for the methods that read them (auto, nfor, "
                        "splat; default: when the scene has them, as every built-in scene does)")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--out", default=None, metavar="DIR",
                   help="folder of the tables, plots and report (default: convergence_SCENE)")
    s.add_argument("--html", action="store_true",
                   help="also write OUT/report.html: one self-contained interactive report (flip between "
                        "methods, zoom, exposure, error maps)")
    s.set_defaults(func=_cmd_convergence)

    s = es.add_parser("oracle", help="the ceiling of Gaussian-scale selection on a scene, each method beside it")
    add_scene_flags(s, spp=32)
    s.add_argument("--variance-spp", type=int, default=256,
                   help="spp of the independent render that measures each pixel's variance")
    s.add_argument("--methods", default=None, help="comma-separated (default: every available method)")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=_cmd_oracle)

    s = es.add_parser("stability", help="every method on stiff and extreme inputs; outcome table")
    s.add_argument("--methods", default=None)
    s.add_argument("--cases", default=None, help="comma-separated case names (default: all)")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--out", default=None, metavar="DIR", help="output folder (default: named after the command)")
    s.set_defaults(func=_cmd_stability)

    s = es.add_parser("gallery", help="the documentation gallery: every scene and method (writes OUT/gallery.md)")
    s.add_argument("--scenes", default=None)
    s.add_argument("--methods", default=None)
    s.add_argument("--size", default="96x96")
    s.add_argument("--spp", type=int, default=16)
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--out", default=None, metavar="DIR", help="output folder (default: named after the command)")
    s.add_argument("--html", action="store_true",
                   help="also write OUT/gallery/SCENE.html, an interactive viewer per scene")
    s.set_defaults(func=_cmd_gallery)

    s = es.add_parser("error-rate", help="GEM's scale-selector error rate on a constant signal (Sec. 4.3)")
    s.add_argument("--gammas", default="0.05,0.1,0.15,0.2,0.25,0.3,0.35")
    s.add_argument("--noise-vars", default="0.1,1,10,100,1000")
    s.add_argument("--pixels", type=int, default=200_000, help="pixels of the constant signal")
    s.add_argument("--spp", type=int, default=32)
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--out", default=None, metavar="DIR", help="output folder (default: named after the command)")
    s.set_defaults(func=_cmd_error_rate)

    s = es.add_parser("normality", help="chi-square normality test of pixel estimates (Tamstorf & Jensen)")
    s.add_argument("--scene", default="depth_of_field")
    s.add_argument("--size", default="32x32")
    s.add_argument("--n", default="10,20,50", help="samples per estimate, comma-separated")
    s.add_argument("--m", type=int, default=100, help="independent estimates per pixel")
    s.add_argument("--classes", type=int, default=8)
    s.add_argument("--alpha", type=float, default=0.05)
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--out", default=None, metavar="DIR", help="output folder (default: named after the command)")
    s.set_defaults(func=_cmd_normality)

    s = sub.add_parser("bias", help="bootstrap bias of the adaptive stopping rule on a log or a scene",
                       description="Bootstrap bias of the adaptive stopping rule (Tamstorf & Jensen 1997); "
                                   "the rule is method ci's, set by its options below.",
                       formatter_class=HelpFormatter)
    s.add_argument("log", nargs="?", default=None)
    s.add_argument("--scene", default=None)
    s.add_argument("--spp", type=int, default=32)
    s.add_argument("--size", default="64x64")
    s.add_argument("--B", type=int, default=1000, help="bootstrap resamples (default 1000)")
    s.add_argument("--level", type=float, default=0.95, help="level of the reported bias interval")
    s.add_argument("--threshold", type=float, default=1 / 256, help="|bias| threshold reported (default 1/256)")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--out", default=None, metavar="DIR", help="output folder (default: named after the command)")
    s.set_defaults(func=_cmd_bias)
    if command in (None, "bias"):
        flags = method_flags(set(s._option_string_actions), prefix="--rule-", methods=["ci"])
        add_method_options(s, flags, methods=["ci"])
        s.set_defaults(method_flags=flags)
