"""auto's tile proxy on the corpus's feature scenes (docs/methods/auto.md, "Cost").

Per scene and variant: relMSE / box, CPU s, the regression candidates' share of the choice, the
proxy's share and the two candidates of least summed estimate on its tiles (the proxy computes the
regressions where the share reaches the threshold or one of those is a regression the whole image's
global prior would default to or blend with: :meth:`proxy.Verdict.computes`).  Variants: ``full``
(auto with the proxy off), ``skip`` (the regressions never computed), ``proxy``
(``regression_proxy=0``: the proxy runs and records its share, the regressions are always computed,
so its image is ``full``'s and its extra CPU seconds are the proxy's), ``on`` (the proxy deciding at
:data:`proxy.REGRESSION_SHARE`: its image is ``full``'s where it computes the regressions, ``skip``'s
where not).  ``--tile 32`` forces
the proxy at 128^2 (four 32^2 tiles), where it does not run by default.  ``--out``: JSON, resumed.

    MCRECON_CORPUS_DIR=/tmp/corpus_cache python benchmarks/bench_regression_proxy.py --half tuning \
        --size 128 --tile 32 --out proxy128_tuning.json
"""
import argparse, json, sys, time
from pathlib import Path
import numpy as np
WT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(WT / "benchmarks"))
import bench_corpus, corpus  # noqa: E402
import mcrecon  # noqa: E402
from mcrecon.methods import get_method  # noqa: E402
from mcrecon.methods.auto import proxy  # noqa: E402
from mcrecon.core.metrics import relative_mse  # noqa: E402

VAR = {"full": {"regression_proxy": None}, "skip": {"feature_candidates": "dnlm,fbil,oidn_aux"},
       "proxy": {"regression_proxy": 0.0}, "on": {"regression_proxy": proxy.REGRESSION_SHARE}}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--half", default="tuning")
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--tile", type=int, default=None)
    ap.add_argument("--scenes", default="")
    ap.add_argument("--variants", default="full,skip,proxy")
    ap.add_argument("--out", required=True)
    a = ap.parse_args()
    if a.tile:
        proxy.TILE, proxy.MAX_AREA = a.tile, 100.0
    bench_corpus._warm_up(["auto"])
    rows = {}
    if Path(a.out).exists():
        rows = json.loads(Path(a.out).read_text())
    for e in corpus.scenes(a.half, [x for x in a.scenes.split(",") if x] or None):
        if e.name in rows or not corpus.is_built(e, size=a.size, spp=32, ref_spp=1024):
            continue
        case = corpus.load(e, size=a.size, spp=32, ref_spp=1024)
        if not case.features:
            continue
        st = bench_corpus._stats(case)
        e_box = relative_mse(st.mean, case.reference)
        row = {}
        for v in a.variants.split(","):
            t = time.process_time()
            res = mcrecon.reconstruct(case.source, method=get_method("auto", **VAR[v]), full=True)
            dt = time.process_time() - t
            names = res.run.candidate_names
            ch = res.run.diagnostics["choice"].astype(np.int64)
            reg = float(np.mean(np.array([proxy.is_regression(n) for n in names])[ch]))
            row[v] = {"ratio": relative_mse(res.image, case.reference) / e_box, "cpu_s": dt, "reg_share": reg,
                      "proxy_share": res.run.regression_share,
                      "least": (res.run.regression_verdict or [None] * 3)[1:3]}
        rows[e.name] = row
        print(e.name, " ".join(f"{v}: {r['ratio']:.4f} {r['cpu_s']:.1f}s reg {r['reg_share']:.3f} proxy {r['proxy_share']} {r['least']}"
                               for v, r in row.items()), flush=True)
        Path(a.out).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
