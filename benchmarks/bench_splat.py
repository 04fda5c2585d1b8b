"""Throughput of the splat scatter loop against a plain ``np.add.at`` splat.

Both splat the same samples (jittered, sorted by pixel as a renderer's
reply is) with the same normalised Epanechnikov footprints into the same
RGB image; the ratio is measured in the same run, so machine load cancels
to first order.  Target (issue 5): >= 5 M samples/s at a mean kernel
radius of about 2 pixels.

``--limits`` prints the measured limits instead: relative MSE (eps 0.01)
of the ``paper`` and ``robust`` (default) variants side by side, each as a
ratio to the pixel mean (box) of the *same samples* measured in the same
run, on every built-in scene, offline (uniform samples) and adaptive (the
driver; its box column is the pixel mean of the run's own samples, and
``box run`` the error of a separate box run, which draws other samples),
then the caustic progressive run of the paper's variant round by round
(defaults 128x128, 32 spp for the table; 64x64, 64 spp for the caustic
rounds).  These were strict xfails in the tests; a table cannot fail
when the method gets better.

``--defaults`` prints the table of issue 26: the default (``robust``,
which filters), the default before it (``outliers``) and ``paper``, each as
a ratio to the pixel mean of the same samples (adaptive: of its own run's
samples; the box column is the default's), mean over the seeds, offline
and adaptive, on every built-in scene and, with Mitsuba installed, the
Cornell boxes of ``bench_defaults.py`` (``--no-mitsuba`` skips them).
``--convergence`` writes ``docs/images/splat_convergence.png``: relative MSE
against spp (4 .. 256, one uniform render per budget and seed) of the
default, box and the paper's variant on every built-in scene.

Run: ``python benchmarks/bench_splat.py [--size 512] [--spp 8] [--radius 2]``
     ``python benchmarks/bench_splat.py --limits [--size 128] [--spp 32] [--seeds 5 7]``
     ``python benchmarks/bench_splat.py --defaults [--size 128] [--spp 32] [--seeds 0 1 2 3] [--no-mitsuba]``
     ``python benchmarks/bench_splat.py --convergence [--size 128] [--seeds 0 1] [--out docs/images]``
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from mcrecon.adaptive.run import adapt
from mcrecon.methods.splat import ProgressiveSplatter, SplatMethod, doubling_schedule, splat
from mcrecon.methods.splat.kernels import _BOUNDARY_CODE, _splat_loop
from mcrecon.core.metrics import relative_mse
from mcrecon.renderers import scenes
from mcrecon.core.requests import SampleRequest, jittered_positions
from mcrecon.core.stats import PixelStats


def add_at_splat(pos, val, radius, width, height):
    """Baseline: normalised Epanechnikov footprints scattered with np.add.at, one offset at a time
    (interior normalisation, the renormalize remedy at the border)."""
    out = np.zeros((height, width, val.shape[1]))
    rmax = int(np.ceil(radius.max())) + 1
    cx = np.floor(pos[:, 0]).astype(np.int64)
    cy = np.floor(pos[:, 1]).astype(np.int64)
    offs = [(dx, dy) for dy in range(-rmax, rmax + 1) for dx in range(-rmax, rmax + 1)]
    wsum = np.zeros(pos.shape[0])
    ws = []
    for dx, dy in offs:
        ix, iy = cx + dx, cy + dy
        q = ((ix + 0.5 - pos[:, 0]) ** 2 + (iy + 0.5 - pos[:, 1]) ** 2) / radius ** 2
        w = np.where((q < 1) & (ix >= 0) & (ix < width) & (iy >= 0) & (iy < height), 1 - q, 0.0)
        ws.append(w)
        wsum += w
    inv = np.where(wsum > 0, 1.0 / np.where(wsum > 0, wsum, 1.0), 0.0)
    for (dx, dy), w in zip(offs, ws):
        ix, iy = cx + dx, cy + dy
        keep = w > 0
        np.add.at(out, (iy[keep], ix[keep]), val[keep] * (w[keep] * inv[keep])[:, None])
    return out


def bench_variants(size, spp, seeds):
    """Paper vs robust as ratios to box on the same samples, every built-in scene, offline and adaptive."""
    import mcrecon
    print(f"== relative MSE (eps 0.01) as ratio to box of the same samples, {size}x{size}, {spp} spp ==")
    print(f"{'scene':15s} {'seed':>4} {'mode':8s} {'box':>9} {'paper':>9} {'robust':>8} {'box run':>9}")
    for scene in scenes.scene_names():
        ref = scenes.reference_image(scene, size, size)
        for seed in seeds:
            b = scenes.render_uniform(scene, width=size, height=size, spp=spp, seed=seed)
            ss = mcrecon.SampleSet(b.positions, b.values, width=size, height=size)
            st = PixelStats(size, size)
            st.add(b.positions, b.values)
            eb = relative_mse(st.mean, ref)
            ep = relative_mse(mcrecon.reconstruct(ss, method=SplatMethod(variant="paper")), ref)
            er = relative_mse(mcrecon.reconstruct(ss, method=SplatMethod()), ref)
            print(f"{scene:15s} {seed:>4} {'offline':8s} {eb:9.3g} {ep / eb:9.3g} {er / eb:8.3g}")
            r = scenes.SceneRenderer(scene, width=size, height=size, seed=seed)
            rp = adapt(r, SplatMethod(variant="paper"), spp=spp, seed=seed, track_error=False)
            rr = adapt(r, SplatMethod(), spp=spp, seed=seed, track_error=False)
            eb = relative_mse(rp.stats.mean, ref)  # each against its own run's samples (N_0: 1 vs 16)
            eb_r = relative_mse(rr.stats.mean, ref)
            e_run = relative_mse(adapt(r, "box", spp=spp, seed=seed, track_error=False).image, ref)
            print(f"{scene:15s} {seed:>4} {'adaptive':8s} {eb:9.3g} {relative_mse(rp.image, ref) / eb:9.3g} "
                  f"{relative_mse(rr.image, ref) / eb_r:8.3g} {e_run:9.3g}")


def bench_limits(size, spp, seeds):
    """The caustic limits, each beside the pixel mean of the same samples (relative MSE, eps 0.01).

    1. One progressive run (rounds N_j = 2 N_{j-1}, every pixel each round):
       the error after each round, the pixel mean's, their ratio, and in how
       many rounds the error rose (on the other scenes it falls every round).
    2. The adaptive run (``SplatMethod`` through the driver) against box
       (uniform rounds) with the same renderer seed and budget.
    """
    ref = scenes.reference_image("caustic", size, size)
    print(f"== measured limits of the paper's variant on caustic: relative MSE (eps 0.01), {size}x{size} ==")
    for seed in seeds:
        r = scenes.SceneRenderer("caustic", width=size, height=size, seed=seed)
        sp = ProgressiveSplatter(size, size, 3)  # the paper's Fig. 3 (its defaults)
        st = PixelStats(size, size)
        rows, total = [], 0
        for j, n in enumerate(doubling_schedule(spp)):
            b = r.render(SampleRequest(size, size, counts=np.full((size, size), n), round_index=j, seed=seed))
            sp.add_round(b.positions, b.values)
            st.add(b.positions, b.values)
            total += n
            rows.append((total, relative_mse(sp.image, ref), relative_mse(st.mean, ref)))
        rises = sum(b[1] >= a[1] for a, b in zip(rows, rows[1:]))
        print(f"seed {seed}: progressive run, error rose in {rises} of {len(rows) - 1} doublings")
        print(f"  {'spp':>5} {'splat':>9} {'box':>9} {'splat/box':>10}")
        for tot, e, e_box in rows:
            print(f"  {tot:>5} {e:9.3g} {e_box:9.3g} {e / e_box:10.3g}")
        s = relative_mse(adapt(r, SplatMethod(variant="paper"), spp=spp, seed=seed, track_error=False).image, ref)
        bx = relative_mse(adapt(r, "box", spp=spp, seed=seed, track_error=False).image, ref)
        print(f"seed {seed}: adaptive run at {spp} spp: splat {s:.3g}, box {bx:.3g}, splat/box {s / bx:.3g}")


VARIANTS = ("robust", "outliers", "paper")


# ----------------------------------------------------------------------------
# Independent synthetic scenes with per-sample features (not the built-in scenes the defaults were
# tuned on): each sample's value is albedo x shading x noise, with the albedo, normal and depth of
# what it hit as features, and an exact reference (closed form, or quadrature where a lens blurs).
# ----------------------------------------------------------------------------

SYNTHETIC = ("flat", "edge", "checker_wall", "checker_lowc", "checker_dof")


def _checker(x, y, size, lo=(0.15, 0.2, 0.25), hi=(0.8, 0.7, 0.6)):
    """Albedo of a checkerboard of size/8 px squares; its lower quarter a finer one of size/32 px."""
    sq = np.where(y >= 0.75 * size, size / 32.0, size / 8.0)
    odd = ((np.floor(x / sq) + np.floor(y / sq)) % 2).astype(bool)
    return np.where(odd[:, None], np.asarray(lo), np.asarray(hi))


def _penumbra(x, size):
    """Visibility of an area light: 1 on the left, 0 on the right, linear over a 0.2 size penumbra."""
    return np.clip((0.6 * size - x) / (0.2 * size), 0.0, 1.0)


def _dof_radius(y, size):
    """Circle of confusion (radius, px) of the thin-lens scene: 0 at mid-height, size/20 at top/bottom."""
    return (size / 20.0) * np.abs(2.0 * y / size - 1.0)


def _vogel(n):
    """n points in the unit disc, evenly spread (Vogel's spiral): the lens quadrature of checker_dof."""
    k = np.arange(n) + 0.5
    r, t = np.sqrt(k / n), k * np.pi * (3.0 - np.sqrt(5.0))
    return np.stack([r * np.cos(t), r * np.sin(t)], axis=1)


class SyntheticScene:
    """One of :data:`SYNTHETIC`, ``size`` x ``size``: samples with features, an exact reference."""

    def __init__(self, name, size):
        if name not in SYNTHETIC:
            raise ValueError(f"{name!r}; valid: {', '.join(SYNTHETIC)}")
        self.name, self.size, self.channels = name, size, ("R", "G", "B")

    def _shade(self, x, y, rng):
        """(albedo, shading expectation, per-sample value, depth) at the hit points (x, y)."""
        size, n = self.size, len(x)
        u = rng.random(n) if rng is not None else None
        if self.name == "flat":  # constant 0.5, uniform noise per channel
            alb = np.full((n, 3), 0.5)
            mean = np.full((n, 3), 0.5)
            val = rng.random((n, 3)) if rng is not None else None
            return alb, mean, val, np.full(n, 3.0)
        if self.name == "edge":  # a sharp step 1 | 0.2 at a fractional column, noise U[0, 2)
            left = x < 0.5 * size + 0.3
            alb = np.where(left[:, None], 0.8, 0.16) * np.ones((n, 3))
            shade = np.full(n, 1.25)
        elif self.name == "checker_wall":  # checker albedo under an area light's penumbra
            alb = _checker(x, y, size)
            shade = 0.2 + 0.8 * _penumbra(x, size)
        elif self.name == "checker_lowc":  # a low-contrast checker the noise hides
            alb = _checker(x, y, size, lo=(0.45, 0.45, 0.45), hi=(0.6, 0.6, 0.6))
            shade = np.ones(n)
        else:  # checker_dof: the texture through a thin lens, soft light falloff
            alb = _checker(x, y, size)
            shade = 0.6 + 0.4 * np.cos(np.pi * (x / size - 0.5))
        mean = alb * shade[:, None]
        val = None
        if rng is not None:
            if self.name == "checker_wall":  # ambient 0.2 always, the light (0.8) if a light sample sees it
                vis = u < _penumbra(x, size)
                val = alb * (0.2 * 2 * rng.random(n) + 0.8 * vis * 2 * rng.random(n))[:, None]
            else:
                val = mean * (2.0 * u)[:, None]
        return alb, mean, val, 2.0 + 0.01 * x  # a slanted plane: depth varies smoothly

    def _hits(self, pos, rng):
        if self.name != "checker_dof":
            return pos[:, 0], pos[:, 1]
        r = _dof_radius(pos[:, 1], self.size)
        t, rr = 2 * np.pi * rng.random(len(pos)), np.sqrt(rng.random(len(pos)))
        lens = np.stack([rr * np.cos(t), rr * np.sin(t)], axis=1)
        return pos[:, 0] + r * lens[:, 0], pos[:, 1] + r * lens[:, 1]

    def samples(self, pos, rng):
        x, y = self._hits(pos, rng)
        alb, _, val, depth = self._shade(x, y, rng)
        n = len(pos)
        return val, {"albedo": alb, "normal": np.tile([0.0, 0.0, 1.0], (n, 1)), "depth": depth}

    def uniform(self, spp, seed, features=True):
        rng = np.random.default_rng([seed, 2026])
        pos = jittered_positions(np.full((self.size, self.size), spp), rng)
        val, feats = self.samples(pos, rng)
        return pos, val, (feats if features else None)

    def renderer(self, seed, features=True):
        from mcrecon.core.requests import SampleBatch
        from mcrecon.renderers.callable import CallableRenderer

        def fn(req):
            rng = np.random.default_rng([seed, 2026, req.round_index])
            pos = jittered_positions(req.counts, rng)
            val, feats = self.samples(pos, rng)
            return SampleBatch(pos, val, feats if features else {})
        return CallableRenderer(fn, width=self.size, height=self.size, name=self.name)

    def reference(self):
        """Pixel integrals: a 16 x 16 subpixel grid (the texture's edges lie on pixel boundaries, the
        penumbra and the falloff are smooth); through the lens 8 x 8 subpixels times 128 Vogel points of
        the disc (against 1024-spp renders at 64^2 the pixels' z-scores have rms 1.04: the quadrature error is a quarter of a 1024-spp standard error)."""
        dof = self.name == "checker_dof"
        size, sub = self.size, 8 if dof else 16
        g = (np.arange(sub) + 0.5) / sub
        lens = _vogel(128) if dof else np.zeros((1, 2))
        out = np.zeros((size, size, 3))
        for j in range(size):
            y = j + np.repeat(g, sub)
            x = (np.arange(size)[:, None] + np.tile(g, sub)[None, :]).ravel()
            yy = np.broadcast_to(y, (size, sub * sub)).ravel()
            acc = np.zeros((len(x), 3))
            r = _dof_radius(yy, size) if self.name == "checker_dof" else 0.0
            for lx, ly in lens:
                _, mean, _, _ = self._shade(x + r * lx, yy + r * ly, None)
                acc += mean
            out[j] = (acc / len(lens)).reshape(size, sub * sub, 3).mean(axis=1)
        return out


def bench_synthetic(size, spp, seeds, adaptive=True, names=SYNTHETIC):
    """The default with and without features, the old default and the paper on :data:`SYNTHETIC`."""
    import mcrecon
    cols = ("default", "default+features", "outliers", "paper")
    print(f"== splat / box of the same samples (relative MSE, eps 0.01), synthetic scenes, {size}x{size}, "
          f"{spp} spp, seeds {' '.join(map(str, seeds))} ==")
    print(f"{'scene':14s} {'mode':8s} {'box':>9} " + " ".join(f"{c:>17}" for c in cols))
    for name in names:
        sc = SyntheticScene(name, size)
        ref = sc.reference()
        for mode in ("offline", "adaptive") if adaptive else ("offline",):
            box, ratios = [], {c: [] for c in cols}
            for seed in seeds:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    if mode == "offline":
                        pos, val, feats = sc.uniform(spp, seed)
                        st = PixelStats(size, size)
                        st.add(pos, val)
                        eb = relative_mse(st.mean, ref)
                        plain = mcrecon.SampleSet(pos, val, width=size, height=size)
                        withf = mcrecon.SampleSet(pos, val, width=size, height=size, features=feats)
                        runs = {"default": (plain, {}), "default+features": (withf, {}),
                                "outliers": (plain, {"variant": "outliers"}), "paper": (plain, {"variant": "paper"})}
                        for c, (src, kw) in runs.items():
                            ratios[c].append(relative_mse(mcrecon.reconstruct(src, method=SplatMethod(**kw)), ref) / eb)
                    else:  # each against the pixel mean of its own run's samples (the default's rounds differ)
                        for c in cols:
                            kw = {"variant": c} if c in ("outliers", "paper") else {}
                            res = adapt(sc.renderer(seed, features=c == "default+features"), SplatMethod(**kw),
                                        spp=spp, seed=seed, track_error=False, progress=False)
                            e_own = relative_mse(res.stats.mean, ref)
                            eb = e_own if c == cols[0] else eb
                            ratios[c].append(relative_mse(res.image, ref) / e_own)
                box.append(eb)
            cells = " ".join(f"{np.mean(r):6.3f} [{min(r):.2f}-{max(r):.2f}]" for r in ratios.values())
            print(f"{name:14s} {mode:8s} {np.mean(box):9.3g} {cells}", flush=True)


def _scenes(size, mitsuba, ref_spp=2048):
    sys.path.insert(0, str(Path(__file__).parent))
    from bench_defaults import BuiltinScene, MitsubaScene
    out = [BuiltinScene(name, size) for name in scenes.scene_names()]
    if mitsuba:
        try:
            import mitsuba  # noqa: F401
        except ImportError:
            return out
        out += [MitsubaScene("cornell_box", size, ref_spp, False),
                MitsubaScene("cornell_small_light", size, ref_spp, True)]
    return out


def bench_defaults(size, spp, seeds, mitsuba):
    """Issue 26's table: each variant's relative MSE over box of the same samples, mean over the seeds."""
    import mcrecon
    print(f"== splat variants / box of the same samples (relative MSE, eps 0.01), {size}x{size}, {spp} spp, "
          f"seeds {' '.join(map(str, seeds))} ==")
    print(f"{'scene':20s} {'mode':8s} {'box':>9} " + " ".join(f"{v:>15}" for v in VARIANTS))
    for sc in _scenes(size, mitsuba):
        ref = sc.reference()
        for mode in ("offline", "adaptive"):
            box, ratios = [], {v: [] for v in VARIANTS}
            for seed in seeds:
                if mode == "offline":
                    pos, val = sc.uniform(spp, seed)
                    ss = mcrecon.SampleSet(pos, val, width=size, height=size)
                    st = PixelStats(size, size)
                    st.add(pos, val)
                    eb = relative_mse(st.mean, ref)
                    for v in VARIANTS:
                        with warnings.catch_warnings():
                            warnings.simplefilter("ignore")
                            ratios[v].append(relative_mse(mcrecon.reconstruct(ss, method=SplatMethod(variant=v)),
                                                          ref) / eb)
                else:  # each against the pixel mean of its own run's samples (the default's rounds differ)
                    for v in VARIANTS:
                        with warnings.catch_warnings():
                            warnings.simplefilter("ignore")
                            res = adapt(sc.renderer(seed), SplatMethod(variant=v), spp=spp, seed=seed,
                                        track_error=False, progress=False)
                        e_own = relative_mse(res.stats.mean, ref)
                        eb = e_own if v == VARIANTS[0] else eb
                        ratios[v].append(relative_mse(res.image, ref) / e_own)
                box.append(eb)
            cells = " ".join(f"{np.mean(r):6.3f} [{min(r):.2f}-{max(r):.2f}]" for r in ratios.values())
            print(f"{sc.name:20s} {mode:8s} {np.mean(box):9.3g} {cells}", flush=True)


def bench_convergence(size, seeds, out):
    """Relative MSE against spp, 4 .. 256: the default, box and the paper's variant, every built-in scene."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import mcrecon
    spps = [4, 8, 16, 32, 64, 128, 256]
    names = scenes.scene_names()
    fig, axes = plt.subplots(2, (len(names) + 1) // 2, figsize=(4 * ((len(names) + 1) // 2), 7.5))
    print(f"== relative MSE (eps 0.01) against spp, {size}x{size}, mean of seeds {' '.join(map(str, seeds))} ==")
    for ax, name in zip(axes.ravel(), names):
        ref = scenes.reference_image(name, size, size)
        curves = {"box": [], "splat (default)": [], "splat paper": []}
        for n in spps:
            e = {k: [] for k in curves}
            for seed in seeds:
                b = scenes.render_uniform(name, width=size, height=size, spp=n, seed=seed)
                ss = mcrecon.SampleSet(b.positions, b.values, width=size, height=size)
                st = PixelStats(size, size)
                st.add(b.positions, b.values)
                e["box"].append(relative_mse(st.mean, ref))
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    e["splat (default)"].append(relative_mse(mcrecon.reconstruct(ss, method=SplatMethod()), ref))
                    e["splat paper"].append(relative_mse(mcrecon.reconstruct(ss, method=SplatMethod(variant="paper")),
                                                         ref))
            for k in curves:
                curves[k].append(float(np.mean(e[k])))
        print(f"{name:15s} " + "  ".join(f"{k}: " + " ".join(f"{x:.3g}" for x in v) for k, v in curves.items()),
              flush=True)
        for (k, v), style in zip(curves.items(), ("k-o", "C0-s", "C3-^")):
            ax.loglog(spps, v, style, label=k, ms=4)
        ax.set_title(name)
        ax.set_xlabel("samples per pixel")
        ax.set_ylabel("relative MSE")
        ax.grid(True, which="both", alpha=0.3)
    for ax in axes.ravel()[len(names):]:
        ax.axis("off")
    axes.ravel()[0].legend()
    fig.suptitle(f"splat: error against spp ({size}x{size}, uniform renders, mean of {len(seeds)} seeds)")
    fig.tight_layout()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    tmp = out / ".splat_convergence.png.tmp"
    fig.savefig(tmp, format="png", dpi=90)
    os.replace(tmp, out / "splat_convergence.png")
    print(f"wrote {out / 'splat_convergence.png'}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=None, help="film side (default 512; 128 with --limits)")
    ap.add_argument("--spp", type=int, default=None, help="samples per pixel (default 8; 32 with --limits)")
    ap.add_argument("--radius", type=float, default=2.0, help="mean kernel radius in pixels")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--limits", action="store_true", help="print the measured-limits table instead")
    ap.add_argument("--seeds", type=int, nargs="+", default=[5, 7], help="renderer seeds of the limits table")
    ap.add_argument("--defaults", action="store_true", help="print issue 26's table of the variants instead")
    ap.add_argument("--convergence", action="store_true", help="write the convergence plot instead")
    ap.add_argument("--no-mitsuba", action="store_true", help="--defaults: built-in scenes only")
    ap.add_argument("--synthetic", action="store_true", help="print the synthetic scenes' table (with features)")
    ap.add_argument("--out", default=str(Path(__file__).parent.parent / "docs" / "images"),
                    help="--convergence: folder of the plot")
    a = ap.parse_args(argv)
    if a.defaults:
        bench_defaults(a.size or 128, a.spp or 32, a.seeds if a.seeds != [5, 7] else [0, 1, 2, 3],
                       not a.no_mitsuba)
        return
    if a.synthetic:
        bench_synthetic(a.size or 128, a.spp or 32, a.seeds if a.seeds != [5, 7] else [0, 1, 2])
        return
    if a.convergence:
        bench_convergence(a.size or 128, a.seeds if a.seeds != [5, 7] else [0, 1], a.out)
        return
    if a.limits:
        bench_variants(a.size or 128, a.spp or 32, a.seeds)
        bench_limits(64, 64, a.seeds)
        return
    a.size, a.spp = a.size or 512, a.spp or 8
    rng = np.random.default_rng(0)
    w = h = a.size
    pos = jittered_positions(np.full((h, w), a.spp), rng)
    n = pos.shape[0]
    val = rng.random((n, 3))
    # radii spread around the mean (0.5x .. 1.5x), as variable widths are
    radius = a.radius * (0.5 + rng.random(n))
    diam = 2.0 * radius

    splat(pos, val, diam, width=w, height=h, boundary="renormalize")  # JIT warm-up (both paths)
    best = best_serial = best_cpu = np.inf
    for _ in range(a.repeat):
        t = time.perf_counter()
        ours = splat(pos, val, diam, width=w, height=h, boundary="renormalize")
        best = min(best, time.perf_counter() - t)
        out = np.zeros_like(ours)
        ones = np.ones(n)
        t = time.perf_counter()
        c = time.process_time()
        _splat_loop(pos, val, ones, radius, _BOUNDARY_CODE["renormalize"], out)
        best_serial = min(best_serial, time.perf_counter() - t)
        best_cpu = min(best_cpu, time.process_time() - c)
    t = time.perf_counter()
    base = add_at_splat(pos, val, radius, w, h)
    t_base = time.perf_counter() - t
    err = np.abs(ours - base).max() / np.abs(base).max()
    print(f"samples: {n} ({w}x{h}, {a.spp} spp), mean radius {radius.mean():.2f} px, RGB float64")
    print(f"splat (numba, 2 blocks): {best:8.3f} s  {n / best / 1e6:8.2f} M samples/s")
    print(f"scatter loop, 1 thread:  {best_serial:8.3f} s  {n / best_serial / 1e6:8.2f} M samples/s "
          f"({n / best_cpu / 1e6:.2f} M per CPU second; load average {os.getloadavg()[0]:.1f} on "
          f"{os.cpu_count()} cores)")
    print(f"np.add.at splat:         {t_base:8.3f} s  {n / t_base / 1e6:8.2f} M samples/s")
    print(f"speed-up over np.add.at: {t_base / best:.1f}x (1 thread: {t_base / best_serial:.1f}x)   "
          f"max relative difference: {err:.2e}")
    print(f"target >= 5 M samples/s (wall, best path): "
          f"{'met' if n / min(best, best_serial) >= 5e6 else 'NOT met'}")


if __name__ == "__main__":
    main()
