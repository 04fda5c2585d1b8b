"""OIDN on all the samples against OIDN on a half, per corpus scene: the true error ratio and its predictors.

Run (from the checkout, so that its mcrecon is imported)::

    PYTHONPATH=. python benchmarks/bench_oidn_full.py --half tuning [--size 128] [--scenes NAME,...]
        [--json out.json]

``auto`` scores OIDN on all the samples (``oidn``, ``oidn_aux``) by the
halves' cross-validation of OIDN run on each half times the constant
:data:`~mcrecon.methods.auto.blackbox.HALF_TO_FULL` (docs/methods/auto.md,
"OIDN candidates").  For each scene of the half (:mod:`corpus`), colour only
and, where the samples carry features, with the albedo and normal (fed as
auto feeds them: each half's prefiltered planes, merged for all the samples,
``clean_aux``), this prints the true ratio of OIDN-on-all's summed relative
squared error (eps 0.01, as ``relative_mse``) to OIDN-on-a-half's, the true
ratio of OIDN-on-all to the average of OIDN on each half (``NAME_halves``),
and what each per-scene predictor of the first ratio gives, from the
samples alone (sums of per-pixel estimates divided by auto's relative
denominator, over the pixels with samples in both halves):

* ``const``: :data:`HALF_TO_FULL`;
* ``quarters``: a power law in the sample count, ``E_half / E_quarter``, the
  halves' and the quarters' cross-validated errors (each quarter of a half
  scored against the other half's means; four more OIDN runs);
* ``disagree``: ``1 - V / (2 E_half)``, ``V`` the variance of OIDN on a half
  from the halves' disagreement (half the summed ``(F(A) - F(B))^2``): the
  bias kept and the variance halved;
* ``sure``: Monte-Carlo SURE of OIDN on all the samples (one probe, as
  ``estimate="sure"``) over ``E_half``.

Then per predictor the median, mean and worst ``|log(predicted / true)|``
(a predictor with no positive value counts as its constant fallback, and is
reported as ``fallback`` scenes).  The quarters split each half as the
halves split the samples (:func:`~mcrecon.core.halves.split_labels`).
About 2-6 CPU s a scene at 128^2, 50 at 512^2.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import corpus  # noqa: E402

PREDICTORS = ("const", "quarters", "disagree", "sure")


def _sample_set(source, features: bool):
    """The corpus case's samples as a SampleSet (a log read whole, with its albedo and normal)."""
    import mcrecon
    from mcrecon.core.samples import SampleSet

    if isinstance(source, SampleSet):
        return source
    log = mcrecon.read_log(source)
    names = ("albedo", "normal") if features else ()
    ch = log.read_all(features=names)
    return SampleSet(np.asarray(ch.positions), np.asarray(ch.values), width=log.width, height=log.height,
                     features={n: np.asarray(ch.features[n]) for n in names} or None,
                     sampler=getattr(log, "sampler", None))


def _halves(s, features: bool):
    from mcrecon.core.halves import split_halves

    return split_halves(s, features=("albedo", "normal") if features else ())


def _quarters(s, features: bool):
    """Each half of ``s`` split again: ``[(a of half 0, b of half 0), (a of half 1, b of half 1)]``."""
    from mcrecon.core.halves import pixel_counts, split_labels
    from mcrecon.core.samples import SampleSet

    totals = pixel_counts(s) if getattr(s, "sampler", "independent") != "independent" else None
    lab = split_labels(np.asarray(s.positions), s.width, s.height, np.zeros(s.width * s.height, np.int64),
                       totals=totals)
    out = []
    for h in (0, 1):
        m = lab == h
        f = {k: np.asarray(v)[m] for k, v in s.features.items()} if s.features else None
        sub = SampleSet(np.asarray(s.positions)[m], np.asarray(s.values)[m], width=s.width, height=s.height,
                        features=f, sampler=getattr(s, "sampler", None))
        q = _halves(sub, features)
        out.append((q.a, q.b))
    return out


def _rse(img, ref) -> float:
    from mcrecon.core.metrics import DEFAULT_EPS

    return float(np.sum((img - ref) ** 2 / (ref ** 2 + DEFAULT_EPS)))


def measure(case) -> dict:
    """{"colour": {...}, "aux": {...}} (``aux`` only with features): true errors, estimates, predictions."""
    from mcrecon.core.halves import mean_variances
    from mcrecon.core.metrics import DEFAULT_EPS
    from mcrecon.methods.auto import blackbox as B
    from mcrecon.methods.auto.estimates import cross_validation_mse, relative_denominator_loo

    ref = case.reference
    s = _sample_set(case.source, case.features)
    hv = _halves(s, case.features)
    st = hv.merged()
    v, va, vb = mean_variances(st, hv)
    y = B._colour(st)
    den = relative_denominator_loo(y, v, st.count, eps=DEFAULT_EPS)
    both = ((hv.a.count > 0) & (hv.b.count > 0))[..., None]
    total = lambda m: float(np.sum(np.where(both, m / den, 0.0)))  # noqa: E731
    quarters = _quarters(s, case.features)
    probe = np.random.default_rng(0x0DE).choice(np.array([-1.0, 1.0]), size=y.shape)
    out = {}
    for aux in (False, True) if case.features else (False,):
        pa, pb = (B.oidn_aux(hv.a), B.oidn_aux(hv.b)) if aux else ((), ())
        full_aux = B._merged_aux(pa, pb, hv.a.count, hv.b.count) if aux else ()
        f = B.oidn_denoise(y, full_aux, clean_aux=aux)
        fa = B.oidn_denoise(B._colour(hv.a), pa, clean_aux=aux)
        fb = B.oidn_denoise(B._colour(hv.b), pb, clean_aux=aux)
        e_half = total(0.5 * (cross_validation_mse(fa, hv.b.mean, vb) + cross_validation_mse(fb, hv.a.mean, va)))
        var_half = total(0.5 * (fa - fb) ** 2)
        e_quarter, n = 0.0, 0
        for h, (qa, qb) in enumerate(quarters):
            other, vo = (hv.b, vb) if h == 0 else (hv.a, va)
            for q in (qa, qb):
                fq = B.oidn_denoise(B._colour(q), B.oidn_aux(q) if aux else (), clean_aux=aux)
                e_quarter += total(cross_validation_mse(fq, other.mean, vo))
                n += 1
        e_quarter /= n
        sd = np.sqrt(np.where(np.isfinite(v), np.maximum(v, 0.0), 0.0))
        moved = B.oidn_denoise(y + B.PROBE_STEP * sd * probe, full_aux, clean_aux=aux)
        sure = total((f - y) ** 2 - v + 2.0 * sd * probe * (moved - f) / B.PROBE_STEP)
        t_full, t_avg = _rse(f, ref), _rse(0.5 * (fa + fb), ref)
        t_half = 0.5 * (_rse(fa, ref) + _rse(fb, ref))
        pred = {"const": B.HALF_TO_FULL,
                "quarters": e_half / e_quarter if e_half > 0 and e_quarter > 0 else None,
                "disagree": 1.0 - 0.5 * var_half / e_half if e_half > 0 and var_half < 2 * e_half else None,
                "sure": sure / e_half if e_half > 0 and sure > 0 else None}
        out["aux" if aux else "colour"] = {
            "true_full_over_half": t_full / t_half, "true_full_over_average": t_full / t_avg,
            "estimated_over_true_half": e_half / t_half, "predicted": pred,
            "sums": {"true_full": t_full, "true_half": t_half, "true_average": t_avg, "e_half": e_half,
                     "var_half": var_half, "e_quarter": e_quarter, "sure_full": sure}}
    return out


def summarise(rows: dict) -> dict:
    """Per predictor: the median, mean and worst |log(predicted / true)| and the fallback count."""
    out = {}
    for p in PREDICTORS:
        errs, fallback = [], 0
        for r in rows.values():
            for d in r.values():
                x = d["predicted"][p]
                if x is None:
                    x, fallback = d["predicted"]["const"], fallback + 1
                errs.append(abs(np.log(x / d["true_full_over_half"])))
        out[p] = {"median": float(np.median(errs)), "mean": float(np.mean(errs)), "worst": float(np.max(errs)),
                  "fallback": fallback, "n": len(errs)}
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    corpus.add_arguments(ap, half="tuning")
    ap.add_argument("--json", default=None, help="write the results here")
    a = ap.parse_args(argv)
    rows = {}
    print("| scene | run | true all/half | true all/average | est./true half | "
          + " | ".join(PREDICTORS) + " |")
    print("|---|---|---|---|---|" + "---|" * len(PREDICTORS))
    for e in corpus.scenes(a.half, [x for x in a.scenes.split(",") if x] or None):
        if not corpus.is_built(e, size=a.size, spp=a.spp, ref_spp=a.ref_spp, root=a.root):
            print(f"skipped {e.name}: not built (python benchmarks/corpus.py --build --size {a.size} --spp {a.spp} "
                  f"--only {e.name})", flush=True)
            continue
        t = time.process_time()
        rows[e.name] = measure(corpus.load(e, size=a.size, spp=a.spp, ref_spp=a.ref_spp, root=a.root))
        for run, d in rows[e.name].items():
            p = " | ".join("-" if d["predicted"][k] is None else f"{d['predicted'][k]:.2f}" for k in PREDICTORS)
            print(f"| {e.name} | {run} | {d['true_full_over_half']:.3f} | {d['true_full_over_average']:.3f} | "
                  f"{d['estimated_over_true_half']:.2f} | {p} |", flush=True)
        print(f"  ({time.process_time() - t:.1f} CPU s)", file=sys.stderr, flush=True)
    summary = summarise(rows) if rows else {}
    print(f"\n{a.half} half, {a.size}x{a.size}, {a.spp} spp: |log(predicted / true all/half)| per predictor "
          "(a missing prediction takes the constant)\n")
    print("| predictor | median | mean | worst | no prediction |")
    print("|---|---|---|---|---|")
    for p, s in summary.items():
        print(f"| {p} | {s['median']:.3f} | {s['mean']:.3f} | {s['worst']:.3f} | {s['fallback']} of {s['n']} |")
    if a.json:
        Path(a.json).write_text(json.dumps({"settings": vars(a), "scenes": rows, "summary": summary}, indent=1))
    return rows


if __name__ == "__main__":
    main()
