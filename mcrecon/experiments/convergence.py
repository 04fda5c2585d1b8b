"""Error against samples and against run time, per method, uniform and adaptive.

For each sample budget the *uniform* mode renders one uniform sample log
of the scene and reconstructs it with every method (the same samples for
all, as in GEM's Fig. 11); the *adaptive* mode runs each adaptive method
through the driver with the same budget.  Every point records relative
MSE, RMSE and SSIM against the scene's exact reference, and wall time split
into renderer and toolkit.  Every point also records SMAPE, 1 - SSIM and,
when ``flip-evaluator`` is installed, NVIDIA's HDR-FLIP (``flip``); the
reports (``report.md``, and ``report.html`` with ``html=True``) give them
all.  Intel Open Image Denoise (``pyoidn``) joins as
an outside peer on the box-filtered uniform samples when it is installed.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import tempfile
import time
import warnings
from pathlib import Path
from typing import Sequence

import numpy as np

from ..errors import InputError, McreconWarning
from ..io import write_exr, write_false_colour, write_log, write_png_preview
from ..methods import available_methods, get_method, method_class
from ..core.metrics import flip as flip_metric
from ..core.metrics import flip_available, relative_mse, relative_mse_map, rmse, smape, ssim
from ..offline.reconstruction import reconstruct

__all__ = ["run_convergence", "ConvergenceResult", "oidn_available", "oidn_denoise"]


def oidn_available() -> bool:
    try:
        import pyoidn  # noqa: F401
    except Exception:
        return False
    return True


def oidn_denoise(image: np.ndarray) -> np.ndarray:
    """Intel OIDN on an HDR colour image (per-pixel means, uncorrelated noise)."""
    import pyoidn

    img = np.ascontiguousarray(image[..., :3], dtype=np.float32)
    return np.asarray(pyoidn.denoise(img, hdr=True, quality="high"), dtype=np.float64)


@dataclasses.dataclass
class ConvergenceResult:
    rows: list
    images: dict  # (method, mode) -> image at the report spp
    maps: dict  # (method, mode) -> sample density at the report spp
    reference: np.ndarray
    report_spp: int
    files: list
    eps: float = 0.01  # relative MSE's
    smape_eps: float = 0.01
    flip: bool = False  # rows carry HDR-FLIP ("flip")
    notes: list = dataclasses.field(default_factory=list)


#: SMAPE's eps in the convergence reports (metrics.smape's default).
SMAPE_EPS = 0.01

#: What a convergence run directory records besides its rows (read by :func:`load_convergence`).
RUN_FILE = "convergence_run.json"


def load_convergence(run_dir) -> tuple[ConvergenceResult, str]:
    """A convergence run written by :func:`run_convergence` (``out=``), read back: (result, scene).

    Reads ``convergence.json`` (the rows), ``convergence_run.json`` (scene,
    report spp, metric settings) and the linear images ``images/*.exr``
    with the density maps ``images/*_density.npy``.  A missing or damaged
    file is an :class:`~mcrecon.errors.InputError` naming it.
    """
    from ..errors import InputError
    from ..io import read_exr

    run_dir = Path(run_dir)

    def load_json(name):
        path = run_dir / name
        try:
            return json.loads(path.read_text())
        except FileNotFoundError:
            raise InputError(str(path), "file", "does not exist: RUN_DIR must be the --out folder of "
                             "`mcrecon experiment convergence` (written by this version)") from None
        except (OSError, ValueError) as exc:
            raise InputError(str(path), "file", f"not readable JSON ({' '.join(str(exc).split())})") from None

    if not run_dir.is_dir():
        raise InputError(str(run_dir), "RUN_DIR", "is not a folder; give the --out folder of "
                         "`mcrecon experiment convergence`")
    rows = load_json("convergence.json")
    meta = load_json(RUN_FILE)
    try:
        keys = [(str(m), str(mode)) for m, mode in meta["images"]]
        scene, report_spp = str(meta["scene"]), int(meta["report_spp"])
        eps, smape_eps, flip = float(meta["eps"]), float(meta["smape_eps"]), bool(meta["flip"])
        notes = [str(n) for n in meta.get("notes", [])]
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(str(run_dir / RUN_FILE), "fields", f"malformed ({exc!r}); write the run again") from None
    _check_rows(run_dir / "convergence.json", rows)
    ref = read_exr(run_dir / "images" / "reference.exr")[0].astype(np.float64)
    images, maps = {}, {}
    for key in keys:
        stem = f"{key[0]}_{key[1]}"
        img = read_exr(run_dir / "images" / f"{stem}.exr")[0].astype(np.float64)
        if img.shape != ref.shape:
            raise InputError(str(run_dir / "images" / f"{stem}.exr"), "shape",
                             f"{img.shape}, the reference is {ref.shape}")
        images[key] = img
        dens = run_dir / "images" / f"{stem}_density.npy"
        if dens.exists():
            try:
                d = np.load(dens, allow_pickle=False)
            except (OSError, ValueError) as exc:
                raise InputError(str(dens), "file", f"not a numpy array ({' '.join(str(exc).split())})") from None
            if d.shape != ref.shape[:2]:
                raise InputError(str(dens), "shape", f"{d.shape}, expected {ref.shape[:2]}")
            maps[key] = d
    result = ConvergenceResult(rows, images, maps, ref, report_spp, [], eps=eps, smape_eps=smape_eps, flip=flip,
                               notes=notes)
    return result, scene


#: The fields of a convergence.json record the report reads, by kind.
_ROW_TEXT = ("method", "mode")
_ROW_COUNTS = (("spp", 1), ("samples", 0))
_ROW_SECONDS = ("renderer_seconds", "toolkit_seconds", "wall_seconds")
_ROW_METRICS = ("relative_mse", "smape", "one_minus_ssim", "rmse")
_ROW_OPTIONAL_METRICS = ("flip", "ssim")


def _check_rows(path: Path, rows) -> None:
    """Refuse convergence.json records the report cannot show as written (missing fields, text for a
    number, a non-finite time), naming the file, the record and the field."""
    if not isinstance(rows, list) or not all(isinstance(r, dict) for r in rows):
        raise InputError(str(path), "rows", "expected a list of objects")

    def number(v):
        return isinstance(v, (int, float)) and not isinstance(v, bool)

    for i, r in enumerate(rows):
        def bad(field, expected):
            got = "missing" if field not in r else f"{r[field]!r}"
            return InputError(str(path), f"record {i} field {field}", f"{got}: expected {expected}; write the run "
                              "again (`mcrecon experiment convergence --out`)")

        for k in _ROW_TEXT:
            if not isinstance(r.get(k), str) or not r[k]:
                raise bad(k, "a name (text)")
        for k, least in _ROW_COUNTS:
            v = r.get(k)
            if not (isinstance(v, int) and not isinstance(v, bool) and v >= least):
                raise bad(k, f"a whole number >= {least}")
        for k in _ROW_SECONDS:
            v = r.get(k)
            if not (number(v) and math.isfinite(v) and v >= 0):
                raise bad(k, "a finite number of seconds >= 0")
        for k in _ROW_METRICS + _ROW_OPTIONAL_METRICS:
            if (k in r or k in _ROW_METRICS) and not number(r.get(k)):
                raise bad(k, "a number (NaN or Infinity where the metric is not finite)")


def _metrics(img, ref, eps, use_flip=False):
    s = ssim(img, ref)
    out = {"relative_mse": relative_mse(img, ref, eps=eps), "rmse": rmse(img, ref), "ssim": s,
           "smape": smape(img, ref, eps=SMAPE_EPS), "one_minus_ssim": 1.0 - s}
    if use_flip:
        out["flip"] = flip_metric(img, ref, hdr=True)
    return out


def run_convergence(scene: str = "soft_shadow", *, methods: Sequence[str] | None = None,
                    spp: Sequence[int] = (4, 8, 16, 32, 64, 128), size: tuple[int, int] = (128, 128),
                    seed: int = 0, modes: Sequence[str] = ("uniform", "adaptive"), oidn: bool | None = None,
                    out=None, eps: float = 0.01, report_spp: int | None = None, flip: bool | None = None,
                    html: bool = False, features: bool | None = None) -> ConvergenceResult:
    """Run the convergence experiment; write CSV, JSON, plots and a report into ``out``.

    Parameters
    ----------
    scene : str
        A built-in scene name.
    methods : sequence of str, optional
        Default: every available method (those that need per-sample
        features left out, with a note, when the run renders none).
    spp : sequence of int
        Average samples per pixel of each point.
    modes : subset of {'uniform', 'adaptive'}
        Adaptive points are run for methods whose sampling is adaptive.
    oidn : bool, optional
        Add Intel OIDN on the uniform box image (default: when installed).
    out : path-like, optional
        Output directory (nothing is written when None).
    report_spp : int, optional
        Budget whose images go into the report (default: 32 if present, else the largest).
    flip : bool, optional
        Record HDR-FLIP per point (default: when ``flip-evaluator`` is
        installed; True without it raises).
    html : bool
        Also write ``report.html``, the interactive report
        (:mod:`mcrecon.experiments.html_report`), when ``out`` is given.
    features : bool, optional
        Render the per-sample features (albedo, normal, depth) with every
        sample, for the methods that read them (``auto``, ``nfor``,
        ``splat``).  Default: when the scene has them (every built-in
        scene), so each method gets what ``reconstruct`` gives it on a
        ``render-log --features`` log of the same scene and seed.  The
        colour samples are the same either way.

    Raises
    ------
    InputError
        Before anything is rendered, for a method that needs features when
        the run renders none.  The samples go through a temporary folder
        that is removed on success and on failure.
    """
    from ..adaptive.run import adapt
    from ..io.logformat import cast_positions
    from ..renderers.scenes import SceneRenderer, get_scene, reference_image, render_uniform

    sc = get_scene(scene)
    if features is None:
        features = bool(sc.feature_names)
    # validated as the renderer does (True is refused for a scene without features)
    features = SceneRenderer(sc, width=1, height=1, features=features).features
    notes = []
    if methods:
        methods = list(methods)
        for m in methods:
            method_class(m)  # clear error for an unknown name
        for m in methods:
            _check_gets_features(m, sc, features)
    else:
        methods = available_methods()
        left_out = [m for m in methods if not features and _needs_features(m)]
        methods = [m for m in methods if m not in left_out]
        if left_out:
            notes.append(f"{', '.join(left_out)} left out: this run renders no per-sample features")
    bad = sorted(set(modes) - {"uniform", "adaptive"})
    if bad:
        raise InputError("convergence", "modes", f"unknown {bad}; valid: uniform, adaptive")
    spp = sorted({int(s) for s in spp})
    if not spp or spp[0] < 1:
        raise InputError("convergence", "spp", f"{spp}: expected positive integers")
    w, h = size
    ref = reference_image(sc, w, h)
    if oidn is None:
        oidn = oidn_available()
    if flip is None:
        flip = flip_available()
        if not flip:
            notes.append("FLIP omitted: flip-evaluator is not installed (pip install flip-evaluator)")
    elif flip and not flip_available():
        raise InputError("convergence", "flip", "flip-evaluator is not installed: pip install flip-evaluator")
    if flip and ref.shape[2] not in (1, 3):
        flip = False
        notes.append(f"FLIP omitted: it compares 1 or 3 (RGB) channels, the scene has {ref.shape[2]}")
    if report_spp is None:
        report_spp = 32 if 32 in spp else spp[-1]
    rows, images, maps = [], {}, {}
    with tempfile.TemporaryDirectory(prefix="mcrecon-convergence-") as tmp:
        tmpdir = Path(tmp)
        # One-time costs (numba compiling a method's kernels) fall in the first run of each method:
        # a run on a tiny film first keeps them out of every timed point.
        _warm_up(sc, methods, modes, tmpdir, features=features, seed=seed)
        for s in spp:
            if "uniform" in modes:
                t0 = time.perf_counter()
                batch = render_uniform(sc, width=w, height=h, spp=s, seed=seed, features=features)
                t_render = time.perf_counter() - t0
                # float32, as render-log writes the scene (the images are those of its log)
                f32 = {k: np.asarray(v, np.float32) for k, v in batch.features.items()} if batch.features else None
                log = write_log(tmpdir / f"u{s}.h5", cast_positions(batch.positions, np.float32),
                                np.asarray(batch.values, np.float32), width=w, height=h, channels=sc.channels,
                                features=f32, reference=ref)
                box_img = None
                for name in methods:
                    m = get_method(name)
                    t1 = time.perf_counter()
                    img = _in_run(scene, s, "uniform", lambda: reconstruct(log, method=m))
                    dt = time.perf_counter() - t1
                    if name == "box":
                        box_img = img
                    rows.append({"scene": scene, "method": name, "mode": "uniform", "spp": s,
                                 "samples": len(batch), "renderer_seconds": t_render, "toolkit_seconds": dt,
                                 "wall_seconds": t_render + dt, **_metrics(img, ref, eps, flip)})
                    if s == report_spp:
                        images[(name, "uniform")] = img
                if oidn:
                    if box_img is None:
                        box_img = reconstruct(log, method="box")
                    t1 = time.perf_counter()
                    img = oidn_denoise(box_img)
                    dt = time.perf_counter() - t1
                    rows.append({"scene": scene, "method": "oidn", "mode": "uniform", "spp": s,
                                 "samples": len(batch), "renderer_seconds": t_render, "toolkit_seconds": dt,
                                 "wall_seconds": t_render + dt, **_metrics(img, ref, eps, flip)})
                    if s == report_spp:
                        images[("oidn", "uniform")] = img
                if s == report_spp:
                    images[("input", "uniform")] = box_img if box_img is not None else reconstruct(log, method="box")
                log.unlink()
            if "adaptive" in modes:
                for name in methods:
                    m = get_method(name)
                    if not m.adaptive:
                        continue
                    renderer = SceneRenderer(sc, width=w, height=h, seed=seed, features=features)
                    t0 = time.perf_counter()
                    res = _in_run(scene, s, "adaptive", lambda: adapt(renderer, m, spp=s, seed=seed, reference=ref,
                                                                      track_error=False, progress=False))
                    wall = time.perf_counter() - t0
                    rows.append({"scene": scene, "method": name, "mode": "adaptive", "spp": s,
                                 "samples": res.stats.n_samples, "renderer_seconds": res.renderer_seconds,
                                 "toolkit_seconds": wall - res.renderer_seconds, "wall_seconds": wall,
                                 **_metrics(res.image, ref, eps, flip)})
                    if s == report_spp:
                        images[(name, "adaptive")] = res.image
                        maps[(name, "adaptive")] = res.stats.count
    result = ConvergenceResult(rows, images, maps, ref, report_spp, [], eps=eps, smape_eps=SMAPE_EPS,
                               flip=bool(flip), notes=notes)
    if out is not None:
        result.files = _write_convergence(result, out, scene=scene, html=html)
    return result


def _needs_features(name: str) -> bool:
    return get_method(name).requires.features == "required"


def _check_gets_features(name: str, sc, features: bool) -> None:
    """Refuse, before anything renders, a method that needs features in a run that renders none."""
    if features or not _needs_features(name):
        return
    fix = "drop --no-features (features=False)" if sc.feature_names else f"scene {sc.name!r} has none"
    raise InputError("convergence", "methods", f"{name} needs per-sample features (albedo, normal, depth) and "
                     f"this run renders none: {fix}, or leave {name} out of --methods")


def _in_run(scene: str, spp: int, mode: str, fn):
    """``fn()`` with McreconWarnings silenced; an InputError about the run's temporary log is said of the
    run instead (the log is gone when the user reads the message)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", McreconWarning)
        try:
            return fn()
        except InputError as exc:
            if "mcrecon-convergence-" not in exc.where:
                raise
            raise InputError(f"convergence {scene} {mode} {spp} spp", exc.field,
                             exc.problem.replace(exc.where, "the run's samples")) from None


def _warm_up(sc, methods, modes, tmpdir: Path, *, features: bool, seed: int) -> None:
    """Run every method once on an 8x8, 2-spp film: numba compiles (or loads) its kernels here, not in
    the first timed point."""
    from ..adaptive.run import adapt
    from ..renderers.scenes import SceneRenderer, render_uniform

    batch = render_uniform(sc, width=8, height=8, spp=2, seed=seed, features=features)
    log = write_log(tmpdir / "warm_up.h5", batch.positions, batch.values, width=8, height=8,
                    channels=sc.channels, features=batch.features or None)
    for name in methods:
        m = get_method(name)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                if "uniform" in modes:
                    reconstruct(log, method=m)
                if "adaptive" in modes and m.adaptive:
                    adapt(SceneRenderer(sc, width=8, height=8, seed=seed, features=features), m, spp=2, seed=seed,
                          track_error=False, progress=False)
            except (InputError, ValueError, RuntimeError):  # the timed run says what is wrong, on its own input
                pass
    log.unlink()


def metrics_table(rows, *, flip: bool) -> list[str]:
    """Markdown table lines of rows: relative MSE, SMAPE, 1 - SSIM, FLIP (when ``flip``), RMSE and times."""
    head = "| method | mode | spp | relative MSE | SMAPE | 1−SSIM |" + (" FLIP |" if flip else "")
    head += " RMSE | renderer s | toolkit s |"
    out = [head, "|---|---|---:" + "|---:" * (head.count("|") - 4) + "|"]
    for r in rows:
        line = (f"| {r['method']} | {r['mode']} | {r['spp']} | {r['relative_mse']:.4g} | {r['smape']:.4g} | "
                f"{r['one_minus_ssim']:.4g} |")
        if flip:
            line += f" {r['flip']:.4g} |"
        line += f" {r['rmse']:.4g} | {r['renderer_seconds']:.3f} | {r['toolkit_seconds']:.3f} |"
        out.append(line)
    return out


def metrics_legend(result: ConvergenceResult) -> str:
    """One Markdown sentence defining the metrics of the tables."""
    text = (f"relative MSE: mean (img − ref)² / (ref² + ε), ε = {result.eps:g}; SMAPE: mean |img − ref| / "
            f"(|img| + |ref| + ε), ε = {result.smape_eps:g}; 1−SSIM on the sRGB previews; ")
    text += ("FLIP: NVIDIA's HDR-FLIP (flip-evaluator), mean over pixels; " if result.flip else
             "FLIP: not computed (" + ("; ".join(n for n in result.notes if "FLIP" in n) or "disabled") + "); ")
    return text + "lower is better for all."


def plot_points(rows, method: str, mode: str, xkey: str) -> tuple[list, list]:
    """The x and relative-MSE values of one method's line, in budget order.

    Against ``spp`` x is the budget.  Against ``wall_seconds`` x is the
    cumulative wall time of the method's runs up to each budget.  Each
    budget is a run of its own, and on a shared machine a run's own time
    jitters by more than the step between two budgets, so a line through
    the runs' own times would run back and forth in time; the sum grows with
    every budget, and the line reads left to right as the error falls.
    """
    pts = sorted((r["spp"], r[xkey], r["relative_mse"]) for r in rows if r["method"] == method and r["mode"] == mode)
    xs = [p[1] for p in pts]
    if xkey != "spp":
        xs = np.cumsum(xs).tolist()
    return xs, [p[2] for p in pts]


def _write_convergence(result: ConvergenceResult, out, *, scene: str, html: bool = False) -> list:
    """CSV, JSON, two log-log plots, images, a Markdown report and (``html``) the interactive one."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out)
    (out / "images").mkdir(parents=True, exist_ok=True)
    files = []
    keys = list(result.rows[0].keys()) if result.rows else []
    with open(out / "convergence.csv", "w", newline="") as f:
        wr = csv.DictWriter(f, fieldnames=keys)
        wr.writeheader()
        wr.writerows(result.rows)
    files.append(out / "convergence.csv")
    (out / "convergence.json").write_text(json.dumps(result.rows, indent=1))
    files.append(out / "convergence.json")
    (out / RUN_FILE).write_text(json.dumps({
        "scene": scene, "report_spp": result.report_spp, "eps": result.eps, "smape_eps": result.smape_eps,
        "flip": result.flip, "notes": list(result.notes),
        "images": [[m, mode] for (m, mode) in sorted(result.images)]}, indent=1))
    files.append(out / RUN_FILE)
    lines = sorted({(r["method"], r["mode"]) for r in result.rows})
    for xkey, fname, xlabel in (("spp", "convergence_spp.png", "average samples per pixel"),
                                ("wall_seconds", "convergence_time.png",
                                 "cumulative wall time [s] of the runs up to each budget")):
        fig, ax = plt.subplots(figsize=(6, 4.5), dpi=100)
        # one colour per method (its uniform line solid, its adaptive one dashed): ten colours for up to ten
        # methods, where one per line would repeat among a full run's 12 lines
        colour = {m: f"C{i % 10}" for i, m in enumerate(sorted({m for m, _ in lines}))}
        for method, mode in lines:
            xs, ys = plot_points(result.rows, method, mode, xkey)
            ax.loglog(xs, ys, "o-" if mode == "uniform" else "s--", color=colour[method], label=f"{method} ({mode})")
        ax.set_xlabel(xlabel)
        ax.set_ylabel("relative MSE")
        ax.set_title(f"{scene}")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(out / fname)
        plt.close(fig)
        files.append(out / fname)
    ref = result.reference
    write_png_preview(out / "images" / "reference.png", ref)
    write_exr(out / "images" / "reference.exr", ref)
    gallery = [("reference", "images/reference.png", None)]
    for (method, mode), img in sorted(result.images.items()):
        stem = f"{method}_{mode}"
        write_png_preview(out / "images" / f"{stem}.png", img)
        write_exr(out / "images" / f"{stem}.exr", img)  # linear: `mcrecon report` rebuilds the viewer from it
        if (method, mode) in result.maps:
            np.save(out / "images" / f"{stem}_density.npy", np.asarray(result.maps[(method, mode)]))
        write_false_colour(out / "images" / f"{stem}_error.png", relative_mse_map(img, ref), log=True,
                           vmin=1e-5, vmax=1.0)
        dens = None
        if (method, mode) in result.maps:
            write_false_colour(out / "images" / f"{stem}_density.png", result.maps[(method, mode)])
            dens = f"images/{stem}_density.png"
        gallery.append((f"{method} ({mode})" if method != "input" else "noisy input (box)", f"images/{stem}.png",
                        (f"images/{stem}_error.png", dens)))
    md = [f"# Convergence: {scene}", "",
          f"Relative MSE (ε = {result.eps:g}) against average spp and against wall time (per method, the "
          "cumulative time of its runs up to each budget; each method runs once on a tiny film first, so "
          f"compiling its kernels is not timed); images at "
          f"{result.report_spp} spp." + (" Interactive viewer: [report.html](report.html)." if html else ""), "",
          "![relative MSE vs spp](convergence_spp.png) ![relative MSE vs time](convergence_time.png)", "",
          metrics_legend(result), ""]
    md += metrics_table(sorted(result.rows, key=lambda r: (r["method"], r["mode"], r["spp"])), flip=result.flip)
    md += ["", "## Images (sRGB preview), relative-error maps (log scale 1e-5..1) and sample densities", "",
           "| image | picture | error | density |", "|---|---|---|---|"]
    for label, pic, extra in gallery:
        err = f"![]({extra[0]})" if extra else ""
        dens = f"![]({extra[1]})" if extra and extra[1] else ""
        md.append(f"| {label} | ![]({pic}) | {err} | {dens} |")
    (out / "report.md").write_text("\n".join(md) + "\n")
    files.append(out / "report.md")
    if html:
        from .html_report import write_html_report

        files.append(write_html_report(out / "report.html", result, scene=scene,
                                       plots=[out / "convergence_spp.png", out / "convergence_time.png"]))
    return files
