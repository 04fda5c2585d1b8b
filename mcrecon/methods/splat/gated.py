"""The default's gated splat of a round, one pass per run of a pixel's samples (mirror and none boundaries).

Every footprint of :func:`.kernels._splat_gated_loop` is centred on its
pixel's centre, so a neighbour q of pixel p lies at an integer offset
``o = q - p`` and the share one consistent sample k of p sends q is
``a_k (1 - |o|^2 / m^2)`` for ``|o| < m``, ``m = min(r_k, reach(p, q))``
(``reach`` -1 where the gate refuses q), with ``a_k = val_k e_k / s(r_k)``
the sample's energy over its footprint's weight sum ``s(r_k)``.  For the
samples of one pixel that is a sum over the samples whose radius exceeds
``|o|``, split at ``reach``: with the samples sorted by radius, two suffix
sums (of ``a_k`` and of ``a_k / r_k^2``) give the pixel's whole deposit at
an offset from two indices: the first sample whose radius exceeds ``|o|``
(a table over the integer ``|o|^2`` the run reaches, filled in one pass)
and the first beyond ``reach`` (a few steps on from it).  So a run of n
samples of one pixel costs one pass over its widest footprint instead of n
footprints, and writes each covered pixel once.  ``s(r)`` comes from a table of the lattice points by ``|o|^2``
(the mirror and none boundaries normalise over the unbounded grid, so it
depends on r only).  What the gate keeps from the footprints goes home,
as in the per-sample loop.  A sample whose footprint covers its own centre
only (``r <= 1``) is deposited as the loop deposits it, so where every
footprint has narrowed to one pixel the image is the loop's (the pixel
mean) bit for bit; elsewhere it is the loop's to rounding (a pixel's terms
are added in another order; energy stays exact).  Each pixel receives the
deposits of the runs in sample order, so bands of rows give one thread's
bits (:mod:`.bands`).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from .kernels import _kernel_radius, _reflect, _same_pixel_stats

__all__: list[str] = []

#: The gate's answers kept per pixel: the neighbours at most GATE_HALF rows and columns away.
GATE_HALF = 2
GATE_SIDE = 2 * GATE_HALF + 1


@numba.njit(cache=True, nogil=True)
def lattice_tables(n2_max):
    """``cnt[L]``, ``sq[L]``: the number of integer offsets o with ``|o|^2 <= L`` and the sum of their
    ``|o|^2``, for ``0 <= L <= n2_max``: the weight sum of a footprint of radius r is
    ``cnt[L] - sq[L] / r^2`` with L the largest integer below ``r^2``."""
    cnt = np.zeros(n2_max + 1)
    sq = np.zeros(n2_max + 1)
    rr = int(math.sqrt(n2_max)) + 1
    for dy in range(-rr, rr + 1):
        for dx in range(-rr, rr + 1):
            n2 = dx * dx + dy * dy
            if n2 <= n2_max:
                cnt[n2] += 1.0
                sq[n2] += n2
    for n2 in range(1, n2_max + 1):
        cnt[n2] += cnt[n2 - 1]
        sq[n2] += sq[n2 - 1]
    return cnt, sq


@numba.njit(cache=True, nogil=True, inline="always")
def _footprint_sum(r2, cnt, sq):
    """The weight sum ``sum over |o| < r of 1 - |o|^2 / r^2`` of a footprint on the pixel grid (r^2 > 0)."""
    lim = int(math.ceil(r2)) - 1  # the largest integer |o|^2 strictly below r^2
    return cnt[lim] - sq[lim] / r2


@numba.njit(cache=True, nogil=True)
def _splat_gated_runs(pos, val, w_round, inv_counts, frac, radius, r_edge, gs, fs, k2, mode, out, gate,
                      outlier_radius, default_radius, width_sum, width_n, k0, k1, j0, j1):
    """:func:`.kernels._splat_gated_loop` (its arguments up to ``out``; ``mode`` 0 mirror or 2 none), one run
    of consecutive samples of a pixel at a time (the module's docstring).  ``gate`` (H W, :data:`GATE_SIDE`
    ^ 2) int8, zero before a round's first band: the gate's answers between on-film neighbours at most
    :data:`GATE_HALF` apart along each axis (1 passes, 2 refuses, 0 not asked yet), stored for both pixels
    of a pair when one asks: the test is symmetric in p and q, so the other reads it (bands on separate
    threads may both ask: they store the same answer).  In the same pass, the terms of
    :func:`.kernels._add_widths` (``outlier_radius``, ``radius`` as its spread radius, ``default_radius``)
    go to ``width_sum`` and ``width_n`` (H, W), each pixel's in sample order: the same sums, without a
    pass of their own.  Returns 0: a footprint on the pixel grid always covers its own centre, so no
    sample falls back."""
    h = out.shape[0]
    w = out.shape[1]
    nc = out.shape[2]
    rmax = 0.0
    for k in range(k0, k1):
        if radius[k] > rmax:
            rmax = radius[k]
    cnt, sq = lattice_tables(int(math.ceil(rmax * rmax)) + 1)
    cap = 64
    r2s = np.empty(cap)
    amp = np.empty((cap, nc))
    sa = np.empty((cap + 1, nc))  # suffix sums of a_k
    sb = np.empty((cap + 1, nc))  # ... and of a_k / r_k^2
    dep = np.empty(nc)
    first = np.empty(64, np.int64)
    home = np.empty(nc)
    k = k0
    while k < k1:
        px = min(max(int(math.floor(pos[k, 0])), 0), w - 1)
        py = min(max(int(math.floor(pos[k, 1])), 0), h - 1)
        end = k + 1
        while end < k1 and min(max(int(math.floor(pos[end, 0])), 0), w - 1) == px \
                and min(max(int(math.floor(pos[end, 1])), 0), h - 1) == py:
            end += 1
        inside = j0 <= py < j1
        if inside:  # the run's kernel diameters (:func:`.kernels._add_widths`), in sample order
            ws = width_sum[py, px]
            wn = width_n[py, px]
            for t in range(k, end):
                r = _kernel_radius(outlier_radius[t], radius[t], default_radius)
                if r > 0.0:
                    ws += 2.0 * r
                    wn += 1
            width_sum[py, px] = ws
            width_n[py, px] = wn
        base = w_round * inv_counts[py, px]
        for c in range(nc):
            home[c] = 0.0
        n = 0
        for t in range(k, end):
            e = base * (1.0 - frac[t])
            if e == 0.0:
                continue
            r = radius[t]
            if not r * r > 1.0:  # stays in its pixel (no other centre within r), deposited as the loop does
                if inside:
                    for c in range(nc):
                        out[py, px, c] += val[t, c] * e
                continue
            if n == cap:
                cap *= 2
                r2s = np.concatenate((r2s, np.empty(cap - n)))
                amp = np.concatenate((amp, np.empty((cap - n, nc))))
                sa = np.empty((cap + 1, nc))
                sb = np.empty((cap + 1, nc))
            r2 = r * r
            f = e / _footprint_sum(r2, cnt, sq)
            # insertion into the run's samples sorted by r^2 (a run holds a pixel's few samples)
            i = n
            while i > 0 and r2s[i - 1] > r2:
                r2s[i] = r2s[i - 1]
                for c in range(nc):
                    amp[i, c] = amp[i - 1, c]
                i -= 1
            r2s[i] = r2
            for c in range(nc):
                amp[i, c] = val[t, c] * f
            n += 1
        if n:
            rmax2 = r2s[n - 1]
            # a footprint reaches rows less than its radius away (mirroring folds a row no further)
            dd = j0 - py if py < j0 else py - j1 + 1
            if dd > 0 and not dd * dd < rmax2:
                n = 0
        if n:
            for c in range(nc):
                sa[n, c] = 0.0
                sb[n, c] = 0.0
            for i in range(n - 1, -1, -1):
                for c in range(nc):
                    sa[i, c] = sa[i + 1, c] + amp[i, c]
                    sb[i, c] = sb[i + 1, c] + amp[i, c] / r2s[i]
            rp = r_edge[py, px]
            rr = int(math.ceil(math.sqrt(rmax2)))
            # first[L]: the first sample whose r^2 exceeds L (searchsorted's side right), for every
            # integer |o|^2 = L the footprints reach: one pass over the run, not a search per offset
            lim = int(math.ceil(rmax2))
            if lim >= first.shape[0]:
                first = np.empty(2 * (lim + 1), np.int64)
            i = 0
            for n2 in range(lim + 1):
                while i < n and r2s[i] <= n2:
                    i += 1
                first[n2] = i
            for dy in range(-rr, rr + 1):
                j = py + dy
                jj = j if 0 <= j < h else _reflect(j, h)
                row_in = j0 <= jj < j1 and (mode != 2 or 0 <= j < h)
                if not row_in and not inside:
                    continue
                for dx in range(-rr, rr + 1):
                    n2 = dx * dx + dy * dy
                    if not n2 < rmax2:
                        continue
                    i_d = first[n2]  # the first radius beyond n2 (n: none)
                    i = px + dx
                    ii = i if 0 <= i < w else _reflect(i, w)
                    # the reach where the gate passes; beyond it (or at a reach of 0) q gets what a refused
                    # q gets, so the gate is asked only within it
                    re = min(rp, r_edge[jj, ii])
                    if re > 0.0 and n2 < re * re:
                        if jj == j and ii == i and -GATE_HALF <= dx <= GATE_HALF and -GATE_HALF <= dy <= GATE_HALF:
                            t = (dy + GATE_HALF) * GATE_SIDE + dx + GATE_HALF
                            ans = gate[py * w + px, t]
                            if ans == 0:
                                ans = 1 if _same_pixel_stats(gs, fs, py, px, jj, ii, k2) else 2
                                gate[py * w + px, t] = ans
                                gate[jj * w + ii, GATE_SIDE * GATE_SIDE - 1 - t] = ans
                            passes = ans == 1
                        else:
                            passes = _same_pixel_stats(gs, fs, py, px, jj, ii, k2)
                        if not passes:
                            re = -1.0
                    re2 = re * re
                    if re > 0.0 and n2 < re2:
                        i_re = i_d  # the first radius beyond re2 > n2: at or after i_d, a few steps on
                        while i_re < n and r2s[i_re] <= re2:
                            i_re += 1
                        g = 1.0 - n2 / re2
                        for c in range(nc):
                            dep[c] = (sa[i_d, c] - sa[i_re, c]) - n2 * (sb[i_d, c] - sb[i_re, c]) + sa[i_re, c] * g
                        if row_in and (mode != 2 or 0 <= i < w):
                            for c in range(nc):
                                out[jj, ii, c] += dep[c]
                        if inside and i_re < n:  # the gate keeps part of the footprints: it stays home
                            for c in range(nc):
                                home[c] += (sa[i_d, c] - n2 * sb[i_d, c]) - dep[c]
                    elif inside:  # refused, or beyond the reach: the footprints' weight here stays home
                        for c in range(nc):
                            home[c] += sa[i_d, c] - n2 * sb[i_d, c]
        if inside and n:
            for c in range(nc):
                out[py, px, c] += home[c]
        k = end
    return 0
