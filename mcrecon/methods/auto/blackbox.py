"""``auto``'s OIDN candidates: Intel Open Image Denoise on all the samples' pixel means, and its error estimate.

OIDN run on half the samples is a weaker filter than OIDN on all of them
(it sees twice the noise), so the halves' cross-validation scores the wrong
image.  The candidates here are OIDN on the pixel means of *all* the
samples (``hdr=True``; the radiance is passed as it is, OIDN scales its
input itself), colour only (``oidn``) and with the albedo and normal
(``oidn_aux``), scored by one of :data:`ESTIMATES` (docs/methods/auto.md,
"OIDN candidates", measures each):

* ``sure``: Monte-Carlo SURE for a black box (Ramani, Blu, Unser 2008):
  ``(F(y) - y)^2 - v + 2 v div_i``, the divergence from one random probe,
  ``div_i ~ b_i (F(y + e s b) - F(y))_i / (e s_i)`` with ``b`` Rademacher
  and ``s = sqrt(v)`` the pixel's standard error (one more OIDN run);
* ``halves`` (the default): the halves' cross-validation of OIDN run on
  each half, ``((A - y_B)^2 - v_B + (B - y_A)^2 - v_A) / 2``, unbiased for
  the error of OIDN on half the samples, scaled by :data:`HALF_TO_FULL`
  (the measured ratio of OIDN-on-all to OIDN-on-half error; two more
  OIDN runs).  With the aux, OIDN on all the samples takes the halves'
  prefiltered albedo and normal merged (:func:`_merged_aux`).

With the halves the average of OIDN on each half is a candidate too
(``NAME_halves``, scored by the dual identity): neither image is better on
every scene.

``sure`` predicts the per-region error best where the noise is near
Gaussian, but Stein's lemma for a nonlinear filter needs that: on the
caustic its sum comes out negative, and with the albedo and normal it
under-estimates OIDN under defocus and motion blur, where auto then loses
to its colour-only run.  ``halves`` is the default; ``sure`` serves pixel
statistics without halves.

The inputs are one per-pixel estimate (``stats``: the pixel means, and
``v``, the variance of each mean) and, for ``halves``, two half estimates:
a cleaned estimate of the samples (as :class:`PixelStats` and its halves)
can be fed in their place.
"""

from __future__ import annotations

import numpy as np

from ...core.fill import mean_variance_policy
from ...core.halves import mean_variances
from ...core.stats import PixelStats
from ...core.metrics import DEFAULT_EPS
from .estimates import cross_validation_mse, relative_denominator_loo
from .features import Candidate, _filled, dual_candidate, feature_slices, prefiltered_features

__all__ = ["ESTIMATES", "HALF_TO_FULL", "oidn_candidate", "oidn_scores", "oidn_denoise", "oidn_filter", "oidn_image",
           "oidn_aux", "oidn_runs"]

#: Whether :func:`oidn_candidate` scores its halves' filter by the crossed vote (the global prior's default
#: where its vote is thin: :func:`.thinvote._thin_default`).
CROSSED = True
#: The error estimates :func:`oidn_candidate` knows.
ESTIMATES = ("sure", "halves")
#: The estimate auto uses when it has the halves.
ESTIMATE = "halves"
#: OIDN on all the samples over OIDN on one half, in summed relative squared error: 0.49-0.87 over the
#: built-in scenes with and without features but ``hdr`` (1.0-1.09), median 0.6 (128^2, 32 spp).
HALF_TO_FULL = 0.6
#: The probe's step in standard errors of the pixel mean.
PROBE_STEP = 0.5
#: OIDN's scratch memory limit (its ``maxMemoryMB``): above it OIDN denoises in overlapping tiles, the
#: same output bits (1920 x 1080), its scratch about 1 GB where unlimited it took 1.5 GB, beside the
#: statistics auto holds through every run.
OIDN_MEMORY_MB = 1000


#: Standard errors by which a black box scored by cross-validation (OIDN) must undercut the best plain
#: candidate's summed estimate to become the global prior's default (:func:`_guards`).
Z_BLACKBOX = 1.0
#: The candidates :data:`Z_BLACKBOX` applies to.
BLACK_BOXES = ("oidn", "oidn_aux", "oidn_halves", "oidn_aux_halves")

def _guards(cands) -> dict:
    """The global prior's guarded candidates: index -> the standard errors by which each must undercut.

    Feature-guided ones :data:`~.selection.Z_GLOBAL`; the black boxes (:data:`BLACK_BOXES`) the larger
    :data:`Z_BLACKBOX`: their cross-validated estimates carry noise independent of the Stein estimates
    of the linear filters (which share the pixel means' noise, so their differences are far less
    noisy).  Where every candidate's error is far below that noise (a flat field, 8 spp) a plain argmin
    of the sums makes OIDN the default at random: 20x the widest Gaussian's error there."""
    from .selection import Z_GLOBAL
    out = {}
    for k, c in enumerate(cands):
        if c.name in BLACK_BOXES:
            out[k] = max(Z_BLACKBOX, Z_GLOBAL if c.feature else 0.0)
        elif c.feature:
            out[k] = Z_GLOBAL
    return out


def oidn_denoise(colour: np.ndarray, aux: tuple = (), *, clean_aux: bool = False) -> np.ndarray:
    """OIDN's ``RT`` filter of an (H, W, C) image, ``hdr=True``, quality high: (H, W, C) float64.

    One channel is denoised as grey (copied to three); beyond three, the first three are denoised and
    the rest kept.  ``aux``: ``(albedo,)`` or ``(albedo, normal)``, (H, W, 3) each.  The filter's
    output is :func:`oidn_filter`'s, placed by :func:`oidn_image`."""
    return oidn_image(colour, oidn_filter(colour, aux, clean_aux=clean_aux))


def oidn_filter(colour: np.ndarray, aux: tuple = (), *, clean_aux: bool = False,
                out: np.ndarray | None = None) -> np.ndarray:
    """OIDN's ``RT`` filter of an (H, W, C) image (float32 or float64: OIDN reads it as float32), ``hdr=True``,
    quality high: its (H, W, 3) float32 output, as OIDN writes it (:func:`oidn_image` makes the image), in
    ``out`` where given (C-contiguous float32, e.g. a file's memory map).  A C-contiguous (H, W, 3) float32
    ``colour`` is read where it lies (no float32 copy).

    The same OIDN calls as ``pyoidn.denoise`` (a CPU device, the filter's images shared, committed and
    executed), but on a device and filter of this call alone, released before it returns:
    ``pyoidn.denoise`` keeps its filter, with its scratch memory sized for the last image and that
    call's input and output arrays, for the rest of the process (about 1.3 GB at 1920 x 1080, held
    through auto's selection)."""
    from pyoidn import Device, Filter, OIDN_FORMAT_FLOAT3, OIDN_QUALITY_HIGH

    c = colour.shape[2]
    if c == 3 and colour.dtype == np.float32 and colour.flags.c_contiguous:
        rgb = colour
    else:
        rgb = np.zeros(colour.shape[:2] + (3,), np.float32)
        rgb[..., :min(c, 3)] = colour[..., :3]
        if c == 1:
            rgb[..., 1] = rgb[..., 2] = rgb[..., 0]
    images = [("color", rgb)] + [(name, np.ascontiguousarray(a, dtype=np.float32))
                                 for name, a in zip(("albedo", "normal"), aux)]
    den = np.empty(rgb.shape, np.float32) if out is None else out
    with Device() as device:
        device.commit()
        with Filter(device, "RT") as flt:
            for name, a in images + [("output", den)]:
                flt.set_image(name, a, OIDN_FORMAT_FLOAT3)
            flt.set_bool("hdr", True)
            flt.set_bool("cleanAux", bool(clean_aux and aux))
            flt.set_quality(OIDN_QUALITY_HIGH)
            flt.set_int("maxMemoryMB", OIDN_MEMORY_MB)
            flt.commit()
            flt.execute()
            error = device.get_error()
    if error is not None:
        raise RuntimeError(f"OIDN failed: {error}")
    return den


def oidn_image(colour: np.ndarray, den: np.ndarray) -> np.ndarray:
    """The (H, W, C) float64 image of OIDN's output ``den`` (:func:`oidn_filter`) on ``colour``: its first
    three channels OIDN's (one channel: the grey's first), the rest ``colour``'s.  Pixel by pixel, so a
    window of it is made from the windows of ``colour`` and ``den``."""
    c = colour.shape[2]
    out = colour.astype(np.float64)  # a copy: the channels beyond three kept, the first three replaced
    out[..., :min(c, 3)] = den[..., :min(c, 3)]
    return out


def oidn_aux(st: PixelStats) -> tuple:
    """OIDN's albedo and normal from a buffer's per-sample features, NL-means prefiltered.

    The features' pixel means prefiltered with their own weights (NFOR's Sec. 5.1: window 11^2, patch
    7^2, k = 0.5), then given to OIDN with ``clean_aux=True`` (docs/methods/auto.md measures the pixel
    means raw, raw with ``clean_aux``, and prefiltered: this measures best).  ``(albedo, normal)``,
    ``(albedo,)`` or ``()`` (OIDN takes a normal only beside an albedo).  A half whose features the
    feature candidates prefiltered already (:func:`~.features.prefiltered_features`) takes those planes:
    the same values, computed once."""
    from ...filters.nlmeans import nlmeans_filter

    stored = prefiltered_features(st, stored_only=True)   # a half's: the feature candidates' prefilter
    # each feature's components, as stored with those planes where they are (auto releases the normal's
    # statistics once prefiltered)
    sl = feature_slices(st)
    names = aux_names(sl)
    if not names:
        return ()
    if stored is not None:
        return tuple(np.ascontiguousarray(stored[..., sl[n]]) for n in names)
    f = np.concatenate([_filled(st.features[n].mean, st.features[n].count) for n in names], axis=2)
    var = np.concatenate([mean_variance_policy(st.features[n]) for n in names], axis=2)
    pf = nlmeans_filter(f, f, var, radius=5, patch=3, k=0.5)
    return tuple(np.ascontiguousarray(pf[..., 3 * k:3 * k + 3]) for k in range(len(names)))


def oidn_runs(names, aux: bool) -> list:
    """auto's OIDN candidates, in their order, as ``(name, aux, halves_only)`` (:func:`oidn_candidate`'s):
    colour-only OIDN where ``names`` (the colour candidates) list it, on its halves alone where ``aux`` (OIDN
    with the albedo and normal, which replaces it on all the samples); then that one."""
    return ([("oidn", False, aux)] if "oidn" in names else []) + ([("oidn_aux", True, False)] if aux else [])


def aux_names(slices: dict) -> list:
    """The features OIDN takes of those at ``slices`` (:func:`~.features.feature_slices`): ``["albedo",
    "normal"]``, ``["albedo"]`` or ``[]`` (three components each; a normal only beside an albedo)."""
    names = []
    for name in ("albedo", "normal"):
        if name not in slices or slices[name].stop - slices[name].start != 3:
            break
        names.append(name)
    return names


def _merged_aux(a_half: tuple, b_half: tuple, ca: np.ndarray, cb: np.ndarray) -> tuple:
    """All the samples' albedo and normal from the two halves' prefiltered planes (:func:`oidn_aux`): their
    average weighted by each pixel's sample counts, as the pixel means merge (a pixel without samples in
    either half takes the plain average of the halves' filled planes).

    The halves are prefiltered anyway (the feature candidates' regressions, OIDN on each half): merging
    them costs one pass where prefiltering all the samples' features again costs an NL-means filter
    (window 11^2, patch 7^2) of every plane.  OIDN on all the samples is given nearly the same guide
    (the corpus: auto's error within 1 % on every feature scene, docs/methods/auto.md)."""
    ca = np.asarray(ca, np.float64)[..., None]
    cb = np.asarray(cb, np.float64)[..., None]
    n = ca + cb
    wa = np.where(n > 0, ca / np.where(n > 0, n, 1.0), 0.5)
    return tuple(np.ascontiguousarray(wa * pa + (1.0 - wa) * pb) for pa, pb in zip(a_half, b_half))


def _colour(st: PixelStats) -> np.ndarray:
    """A buffer's pixel means with its empty pixels filled (OIDN takes no holes)."""
    return _filled(st.mean, st.count)


def oidn_candidate(name: str, stats: PixelStats, v: np.ndarray, halves=None, *, aux: bool = False,
                   estimate: str | None = None, halves_only: bool = False, variances=None,
                   aux_planes=None) -> list[Candidate]:
    """OIDN on all the samples' pixel means (``stats``) with its per-pixel MSE estimate, and with the
    ``halves`` estimate also ``NAME_halves``: the average of OIDN on each half, with the halves'
    dual-buffer estimate (:func:`~.features.dual_candidate`).

    ``v``: the variance of each pixel mean.  ``aux``: with the albedo and normal (:func:`oidn_aux`).
    ``estimate``: one of :data:`ESTIMATES` (default :data:`ESTIMATE`); ``halves`` needs ``halves``
    (without them: ``sure``).  ``halves_only``: with the ``halves`` estimate, ``NAME_halves`` alone (two
    denoiser runs, not three).  ``variances``: the halves' means' variances ``(v_A, v_B)`` their
    cross-validation reads (None: :func:`~mcrecon.core.halves.mean_variances` of ``halves``).
    ``aux_planes``: each half's :func:`oidn_aux` planes, computed before (a film's, from its features read
    band by band: ``halves`` may then hold the colour alone).  NaN where a pixel has no sample (or no
    sample in a half)."""
    estimate = ESTIMATE if estimate is None else estimate
    if estimate not in ESTIMATES:
        raise ValueError(f"oidn_candidate: estimate {estimate!r}; valid: {', '.join(ESTIMATES)}")
    if halves is None or (aux and aux_planes is None and "albedo" not in halves.a.features):
        estimate = "sure"
    halves_only = halves_only and estimate == "halves"
    y = _colour(stats)
    a_half = b_half = ()
    if aux and estimate == "halves":
        a_half, b_half = (oidn_aux(halves.a), oidn_aux(halves.b)) if aux_planes is None else aux_planes
    if halves_only:
        img = None
    elif len(a_half) == len(b_half) > 0:
        # the halves' prefiltered planes, merged: no third prefilter of the same features
        img = oidn_denoise(y, _merged_aux(a_half, b_half, halves.a.count, halves.b.count), clean_aux=aux)
    else:
        a_full = oidn_aux(stats) if aux else ()
        img = oidn_denoise(y, a_full, clean_aux=aux)
    if estimate == "sure":
        s = np.sqrt(np.where(np.isfinite(v), np.maximum(v, 0.0), 0.0))
        # a fixed probe: the same samples give the same image (pinned outputs, resumed runs)
        b = np.random.default_rng(0x0DE).choice(np.array([-1.0, 1.0]), size=y.shape)
        moved = oidn_denoise(y + PROBE_STEP * s * b, a_full, clean_aux=aux)
        d = img - y
        return [_full_candidate(name, img, d * d - v + 2.0 * s * b * (moved - img) / PROBE_STEP, stats.count, aux)]
    ha, hb = halves.a, halves.b
    fa = oidn_denoise(_colour(ha), a_half, clean_aux=aux)
    fb = oidn_denoise(_colour(hb), b_half, clean_aux=aux)
    # a stratified sampler's from its halves' difference
    va, vb = mean_variances(stats, halves)[1:] if variances is None else variances
    his = (None, None)
    if CROSSED:
        from ...core.safeguard import sample_range_bounds
        his = (sample_range_bounds(ha)[1], sample_range_bounds(hb)[1])
    cands, terms = oidn_scores(name, img, fa, fb, y, v, stats.count,
                               ((ha.mean, ha.count, va, his[0]), (hb.mean, hb.count, vb, his[1])), aux=aux)
    if terms is not None:
        from .selection import crossed_total
        crossed = crossed_total(terms)
        for c in cands:
            c.crossed = crossed
    return cands


def _full_candidate(name: str, img: np.ndarray, mse: np.ndarray, count: np.ndarray, aux: bool) -> Candidate:
    """OIDN on all the samples as a candidate: its image (0 where not finite) and estimate (NaN where a pixel
    has no sample)."""
    has = (count > 0)[..., None]
    return Candidate(name, np.where(np.isfinite(img), img, 0.0), np.where(has, mse, np.nan), feature=aux)


def oidn_scores(name: str, img, fa: np.ndarray, fb: np.ndarray, y: np.ndarray, v: np.ndarray, count: np.ndarray,
                halves: tuple, *, aux: bool = False) -> tuple:
    """The ``halves`` estimate's candidates of OIDN (:func:`oidn_candidate`) from its images and a frame's
    colour planes, pixel by pixel but for the crossed vote's 3 x 3 neighbourhoods: ``(candidates, terms)``.

    ``img``: OIDN on all the samples (None: ``NAME_halves`` alone), ``fa``, ``fb``: on each half (float64
    images, :func:`oidn_image`); ``y``, ``v``, ``count``: all the samples' pixel means (empty pixels
    filled), their variance and counts; ``halves``: each half's ``(means, counts, means' variances, top of
    the sample range)`` (the top None without the crossed vote).  ``terms``: the crossed vote's per-pixel
    terms of each half (:func:`~.selection.crossed_terms`; None without :data:`CROSSED`), whose
    :func:`~.selection.crossed_total` over the film is each candidate's ``crossed``.  On a band of rows
    grown by one each side, the band's rows are the film's bit for bit (a film's candidates a band at a
    time: :mod:`.tiled`)."""
    (ma, ca, va, hia), (mb, cb, vb, hib) = halves
    cva = cross_validation_mse(fa, mb, vb)
    cvb = cross_validation_mse(fb, ma, va)
    cv = 0.5 * (cva + cvb)
    # the average of the two halves' OIDN, scored without bias by the dual identity: computed for the
    # estimate anyway, and better than OIDN on all the samples on some scenes (soft shadows, depth of
    # field: docs/methods/auto.md)
    extra = [dual_candidate(name + "_halves", fa, fb, cva, cvb, ca, cb, feature=aux)]
    terms = None
    if CROSSED:
        from .selection import crossed_terms
        den = relative_denominator_loo(y, v, count, eps=DEFAULT_EPS)
        terms = [crossed_terms(cva, ma, va, ca, hia, den), crossed_terms(cvb, mb, vb, cb, hib, den)]
    if img is None:
        return extra, terms
    both = ((ca > 0) & (cb > 0))[..., None]
    cv = np.where(both, HALF_TO_FULL * cv, np.nan)
    return [_full_candidate(name, img, cv, count, aux)] + extra, terms
