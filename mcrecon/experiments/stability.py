"""Stability of every method on stiff and extreme inputs.

Each case is a tiny renderer (a function of film positions) with a size,
a budget, a value dtype and a non-finite policy.  Every method runs it
offline (a uniform log) and adaptively (through the driver).  For each
run the table records: whether the image is finite, which warnings
escaped (numpy ``RuntimeWarning`` s are failures; ``McreconWarning`` s
are documented policies and are listed), the ratio of the image mean to
the sample mean (methods that preserve energy or the mean promise ~1),
and any exception.
"""

from __future__ import annotations

import dataclasses
import json
import tempfile
import time
import traceback
import warnings
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from ..io import write_log
from ..methods import available_methods, get_method
from ..renderers.callable import CallableRenderer
from ..core.requests import SampleBatch, jittered_positions
from ..offline.reconstruction import reconstruct

__all__ = ["CASES", "StabilityCase", "run_stability", "write_stability_table"]


@dataclasses.dataclass(frozen=True)
class StabilityCase:
    name: str
    description: str
    width: int
    height: int
    spp: int
    values: Callable  # (positions (N, 2), rng) -> (N, 3)
    dtype: str = "float32"
    nonfinite: str = "drop"


def _flat(pos, rng, level=0.5):
    return level + rng.uniform(-0.25, 0.25, (len(pos), 3))


def _zeros97(pos, rng):
    hit = rng.random(len(pos)) < 0.03
    return np.where(hit[:, None], 40.0, 0.0) * np.ones((1, 3))


def _firefly(pos, rng):
    v = _flat(pos, rng)
    v[len(v) // 2] = 1e6
    return v


def _tiny_huge(pos, rng):
    left = pos[:, :1] < 8
    return np.where(left, 1e-6, 1e6) * rng.uniform(0.5, 1.5, (len(pos), 3))


def _with_nonfinite(pos, rng):
    v = _flat(pos, rng)
    if len(v) < 2:
        return v
    k = rng.choice(len(v), size=max(len(v) // 100, 2), replace=False)
    v[k[::2], 0] = np.nan
    v[k[1::2], 1] = np.inf
    return v


def _offset(pos, rng):
    return 1e6 + rng.uniform(-1e-3, 1e-3, (len(pos), 3))


def _bright_edge(pos, rng):
    return np.where(np.hypot(pos[:, :1] - 8, pos[:, 1:] - 8) < 4, 500.0, 1e-3) * np.ones((1, 3))


CASES: list[StabilityCase] = [
    StabilityCase("one_spp", "1 sample per pixel, flat noise", 16, 16, 1, _flat),
    StabilityCase("zeros_97", "97% zero samples, rare value 40", 16, 16, 8, _zeros97),
    StabilityCase("firefly", "a single 1e6 firefly in a flat image", 16, 16, 4, _firefly),
    StabilityCase("tiny_and_huge", "1e-6 beside 1e6 in one image", 16, 16, 4, _tiny_huge),
    StabilityCase("bright_edge", "500 beside 1e-3, zero variance inside each region", 16, 16, 4, _bright_edge),
    StabilityCase("constant", "constant 0.7: zero variance everywhere", 16, 16, 4, lambda p, r: np.full((len(p), 3), 0.7)),
    StabilityCase("all_zero", "all samples 0", 16, 16, 4, lambda p, r: np.zeros((len(p), 3))),
    StabilityCase("nan_inf_drop", "1% NaN/Inf samples, policy drop", 16, 16, 4, _with_nonfinite, nonfinite="drop"),
    StabilityCase("nan_inf_zero", "1% NaN/Inf samples, policy zero", 16, 16, 4, _with_nonfinite, nonfinite="zero"),
    StabilityCase("size_1x1", "1x1 film", 1, 1, 8, _flat),
    StabilityCase("size_1xN", "1x17 film", 17, 1, 4, _flat),
    StabilityCase("size_Nx1", "17x1 film", 1, 17, 4, _flat),
    StabilityCase("size_prime", "31x29 film", 31, 29, 4, _flat),
    StabilityCase("offset_1e6", "1e6 +- 1e-3 (variance estimators)", 16, 16, 8, _offset, dtype="float64"),
    StabilityCase("float64", "flat noise, float64 values", 16, 16, 4, _flat, dtype="float64"),
]


def _samples(case: StabilityCase, counts, seed):
    rng = np.random.default_rng(seed)
    pos = jittered_positions(counts, rng)
    return pos, np.asarray(case.values(pos, rng), dtype=case.dtype)


def _run_one(fn):
    """Call fn, collecting warnings; returns (image or None, warnings, error)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            img = fn()
            err = None
        except Exception as exc:  # recorded, reported as a failure
            img = None
            err = f"{type(exc).__name__}: {exc}"
            tb = traceback.format_exc(limit=3)
            err += " | " + tb.strip().splitlines()[-3].strip() if tb.count("\n") > 2 else ""
    names = sorted({f"{w.category.__name__}: {str(w.message)[:80]}" for w in caught})
    return img, names, err


def run_stability(*, methods: Sequence[str] | None = None, cases: Sequence[str] | None = None,
                  modes: Sequence[str] = ("offline", "adaptive"), seed: int = 0) -> list[dict]:
    """Run every (case, method, mode); return one row per run (by default every method that reads
    featureless samples: the cases carry no features)."""
    from ..adaptive.run import adapt

    # the cases' samples carry no features: a method that requires them (nfor) only refuses them
    methods = list(methods) if methods else [m for m in available_methods()
                                              if get_method(m).requires.features != "required"]
    chosen = [c for c in CASES if cases is None or c.name in cases]
    rows = []
    tmp = Path(tempfile.mkdtemp(prefix="mcrecon-stability-"))
    for case in chosen:
        counts = np.full((case.height, case.width), case.spp, np.int64)
        pos, val = _samples(case, counts, seed)
        finite = np.isfinite(val).all(axis=1)
        kept = val[finite] if case.nonfinite == "drop" else np.where(np.isfinite(val), val, 0)
        sample_mean = float(np.mean(kept))
        log = write_log(tmp / f"{case.name}.h5", pos, val, width=case.width, height=case.height)
        for name in methods:
            for mode in modes:
                method = get_method(name)
                t0 = time.perf_counter()
                if mode == "offline":
                    img, warns, err = _run_one(lambda: reconstruct(log, method=method, nonfinite=case.nonfinite))
                else:
                    def fn(req, case=case):
                        rng = np.random.default_rng(req.seed)
                        p = jittered_positions(req.counts, rng) if req.counts is not None else np.zeros((0, 2))
                        if req.positions is not None:
                            p = np.concatenate([p, req.positions])
                        return SampleBatch(p, np.asarray(case.values(p, rng), dtype=case.dtype))
                    r = CallableRenderer(fn, width=case.width, height=case.height, name=case.name)
                    img, warns, err = _run_one(lambda: adapt(r, method, spp=case.spp, seed=seed, progress=False,
                                                              nonfinite=case.nonfinite,
                                                              storage_dtype=case.dtype).image)
                dt = time.perf_counter() - t0
                ok_finite = img is not None and bool(np.isfinite(img).all())
                runtime_warnings = [w for w in warns if w.startswith("RuntimeWarning")]
                mean_ratio = None
                if img is not None and ok_finite and sample_mean != 0:
                    mean_ratio = float(np.mean(img) / sample_mean)
                rows.append({"case": case.name, "description": case.description, "method": name, "mode": mode,
                             "finite": ok_finite, "error": err, "warnings": warns,
                             "runtime_warnings": len(runtime_warnings), "mean_ratio": mean_ratio,
                             "seconds": dt, "passed": ok_finite and err is None and not runtime_warnings})
        log.unlink()
    try:
        tmp.rmdir()
    except OSError:
        pass
    return rows


def write_stability_table(rows: list[dict], path) -> Path:
    """A Markdown outcome table (and the rows as JSON beside it)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.with_suffix(".json").write_text(json.dumps(rows, indent=1))
    methods = sorted({r["method"] for r in rows}, key=lambda m: (m != "box", m))
    modes = sorted({r["mode"] for r in rows}, reverse=True)
    lines = ["# Stability on stiff and extreme inputs", "",
             "Generated by `mcrecon experiment stability`. Each cell: `ok` (finite image, no exception, no numpy "
             "RuntimeWarning) or `FAIL`, then the ratio of the image mean to the mean of the kept samples "
             "of the offline log. Adaptive runs draw their own samples (the firefly case, for instance, "
             "puts one firefly into every round), so their ratio is only indicative; offline, box and splat "
             "promise 1 (equal spp per pixel; energy preservation). "
             "Documented policy warnings (McreconWarning: dropped NaN/Inf samples, filled empty pixels) are "
             "expected and listed below the table.", "",
             "| case | " + " | ".join(f"{m} {md}" for m in methods for md in modes) + " |",
             "|---|" + "---|" * (len(methods) * len(modes))]
    by = {(r["case"], r["method"], r["mode"]): r for r in rows}
    cases = list(dict.fromkeys(r["case"] for r in rows))
    for c in cases:
        cells = []
        for m in methods:
            for md in modes:
                r = by.get((c, m, md))
                if r is None:
                    cells.append("")
                    continue
                mr = f" {r['mean_ratio']:.3g}" if r["mean_ratio"] is not None else ""
                cells.append(("ok" if r["passed"] else "FAIL") + mr)
        desc = next(r["description"] for r in rows if r["case"] == c)
        lines.append(f"| {c}: {desc} | " + " | ".join(cells) + " |")
    notes = sorted({(r["method"], r["mode"], w) for r in rows for w in r["warnings"]})
    fails = [r for r in rows if not r["passed"]]
    lines += ["", "## Failures", ""] + ([f"- {r['case']} / {r['method']} {r['mode']}: {r['error'] or r['warnings']}"
                                          for r in fails] or ["none"])
    lines += ["", "## Warnings seen (documented policies)", ""] + [f"- {m} {md}: {w}" for m, md, w in notes]
    path.write_text("\n".join(lines) + "\n")
    return path
