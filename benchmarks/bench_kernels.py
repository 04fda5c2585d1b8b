"""The parts of one regression window and of one offset's weights, in CPU microseconds (docs/methods/nfor.md).

Per window of a collaborative regression (radius 9: 361 positions; 7 feature columns, so 10 with the
constant and the pixel offsets; 3 colours): the normal equations (:func:`window_algebra._normal_equations`,
over the window padded to :data:`window_algebra.NE_PAD`), the Cholesky solve, the predictions and the
leverages (auto's centre weight); per pixel, the weights of 361 offsets (:func:`nlmeans.offset_distances`,
3 channels, patch 3, then the largest channel's ``exp_neg``).  One thread, random data of the right
shapes; each figure is the least of ``--repeat`` runs of ``--calls`` calls (the machine may be shared:
the least is the one least disturbed).

``--stages LOG``: instead, ``nfor``'s stages on a log with features (one in-process
``mcrecon.reconstruct(LOG, method="nfor")``, each stage of :func:`pipeline.denoise_planes` wrapped:
CPU seconds of the process, both threads; ``nlmeans_filter`` is called four times: the two halves'
feature prefilters, the selection map, the second pass's features).

    python benchmarks/bench_kernels.py
    python benchmarks/bench_kernels.py --stages LOG.h5
"""
from __future__ import annotations

import argparse
import time

import numba
import numpy as np

from mcrecon.filters import nlmeans, window_algebra


@numba.njit(cache=False)
def _normal(k, xt, wv, yt, a, bm, d, npad):
    for _ in range(k):
        window_algebra._normal_equations(xt, wv, yt, a, bm, d, d, npad)


@numba.njit(cache=False)
def _solve(k, a0, b0, a, bm, tmp, d):
    for _ in range(k):
        a[:] = a0
        bm[:] = b0
        window_algebra._solve_spd(a, bm, d, bm.shape[1], tmp)


@numba.njit(cache=False)
def _predict(k, xt, beta, yp, d, n):
    for _ in range(k):
        window_algebra._predict(xt, beta, yp, d, n)


@numba.njit(cache=False)
def _leverages(k, chol, xt, zt, lev, d, n):
    for _ in range(k):
        window_algebra._leverages(chol, xt, zt, lev, d, n)


@numba.njit(cache=False)
def _weights(k, g, v, pd, vs, ic, dist, out, f):
    w = g.shape[2]
    for _ in range(k):
        nlmeans.offset_distances(g, v, 2, 3, 16, 32, f, np.float32(0.25), np.float32(nlmeans.NLM_EPS),
                                 np.float32(nlmeans.DISTANCE_CLAMP), pd, vs, ic, dist)
        for rr in range(16):
            for t in range(w):
                m = max(dist[0, rr, t], dist[1, rr, t], dist[2, rr, t])
                out[rr * w + t] = nlmeans.exp_neg(max(float(m), 0.0))


def nfor_stages(log: str) -> None:
    """One ``reconstruct(log, method="nfor")`` with the pipeline's stages wrapped: CPU seconds per call."""
    import functools
    import os

    import mcrecon
    from mcrecon.methods.nfor import method, pipeline

    calls: list = []

    def wrap(mod, name):
        f = getattr(mod, name)

        @functools.wraps(f)
        def timed(*a, **k):
            c0 = time.process_time()
            out = f(*a, **k)
            calls.append((name, time.process_time() - c0))
            return out
        setattr(mod, name, timed)

    for name in ("prefilter_features", "cross_regression", "nlmeans_filter_shared", "nlmeans_filter",
                 "collaborative_regression"):
        wrap(pipeline, name)
    wrap(method, "denoise_planes")
    rng = np.random.default_rng(0)  # a tiny film first: the kernels loaded (or compiled) outside the timing
    m = 16 * 16 * 8
    mcrecon.reconstruct(mcrecon.SampleSet(rng.random((m, 2)) * 16, rng.random((m, 3)), width=16, height=16,
                                          features={"albedo": rng.random((m, 3)), "normal": rng.random((m, 3))}),
                        method="nfor")
    calls.clear()
    c0 = time.process_time()
    mcrecon.reconstruct(log, method="nfor")
    total = time.process_time() - c0
    print(f"nfor stages on {log}: reconstruct() CPU {total:.2f} s, load {os.getloadavg()[0]:.1f}")
    for name, t in calls:
        print(f"  {name:28s} {t:7.2f}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--calls", type=int, default=5000)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--stages", metavar="LOG", help="nfor's stages on this log with features instead")
    args = ap.parse_args(argv)
    if args.stages:
        nfor_stages(args.stages)
        return 0
    rng = np.random.default_rng(0)
    r, d, nc = 9, 10, 3
    n = (2 * r + 1) ** 2
    npad = (n + window_algebra.NE_PAD - 1) // window_algebra.NE_PAD * window_algebra.NE_PAD
    xt = np.zeros((d, npad))
    xt[:, :n] = rng.standard_normal((d, n))
    yt = np.zeros((nc, npad))
    yt[:, :n] = rng.standard_normal((nc, n))
    wv = np.zeros(npad)
    wv[:n] = rng.uniform(0, 1, n)
    a0 = (xt[:, :n] * wv[:n]) @ xt[:, :n].T + 1e-3 * np.eye(d)
    b0 = (xt[:, :n] * wv[:n]) @ yt[:, :n].T
    chol = np.linalg.cholesky(a0)
    w = 512
    g = rng.random((3, 64, w)).astype(np.float32)
    v = (0.01 * rng.random((3, 64, w))).astype(np.float32)
    f = 3
    parts = {
        "normal equations (a window)": (_normal, (xt, wv, yt, np.zeros((d, d)), np.zeros((d, nc)), d, npad), 1),
        "Cholesky solve (a window)": (_solve, (a0, b0, np.zeros((d, d)), np.zeros((d, nc)), np.zeros(d), d), 1),
        "predictions (a window)": (_predict, (xt, np.linalg.solve(a0, b0), np.zeros((nc, n)), d, n), 1),
        "leverages (a window, auto)": (_leverages, (chol, xt, np.zeros((d, window_algebra.LEVERAGE_BLOCK)), np.zeros(n),
                                                    d, n), 1),
        "weights of 361 offsets (a pixel)": (_weights, (g, v, np.zeros((3, 16 + 2 * f, w + 2 * f), np.float32),
                                                        np.zeros(w + 2 * f), np.zeros(w + 2 * f),
                                                        np.zeros((3, 16, w), np.float32), np.zeros(16 * w, np.float32),
                                                        f), n / (16 * w)),
    }
    for name, (fn, fargs, per) in parts.items():
        fn(1, *fargs)
        calls = args.calls if per == 1 else max(1, args.calls // 10)  # a call of the weights: 16 rows of w pixels
        best = min(_timed(fn, calls, fargs) for _ in range(args.repeat))
        print(f"{name:36s} {best / calls * per * 1e6:8.3f} us")
    return 0


def _timed(fn, calls, fargs) -> float:
    c0 = time.process_time()
    fn(calls, *fargs)
    return time.process_time() - c0


if __name__ == "__main__":
    raise SystemExit(main())
