"""The ``auto`` method: per-pixel selection among reconstructions by their estimated error.

Candidates (option ``candidates``): the pixel mean (``box``), every
Gaussian scale of GEM's final filter bank (``gauss``), cross-filtered
non-local means (``nlm``), OIDN on all the samples (``oidn``; with the
albedo and normal ``oidn_aux``, a feature candidate that replaces it where
the samples carry an albedo; ``oidn_halves`` stays) and the black boxes
``awr`` and ``splat``.  Each comes with a per-pixel MSE estimate
(:mod:`mcrecon.methods.auto.estimates`): Stein's estimate for the linear filters (box,
Gaussians, and NL-means whose weights come from the other half of the
samples), dual-buffer cross-validation for the black boxes run on each
half, and for OIDN the halves' cross-validation scaled to the full-sample
filter (:mod:`.blackbox`).  The estimates,
relative to a reference-free ``mu^2 + eps``, are smoothed (a normalised
Gaussian of ``smooth`` pixels) and every pixel takes the candidate of least
smoothed estimate.  ``docs/methods/auto.md`` derives every estimator.
"""

from __future__ import annotations

import copy
import dataclasses
import warnings

import numpy as np


from ...errors import InputError, McreconWarning
from ...core.metrics import DEFAULT_EPS
from ...core.halves import Halves, mean_variances
from .estimates import (cross_validation_mse, relative_denominator,
    sure, sure_filter_bank)
from ...core.stats import PixelStats
from ..base import AdaptiveState, Method, MethodInputs, Option, Requirements, RunState, uniform_counts
from ...core.safeguard import (albedo_divisor, neighbourhood_mean_variance, pooled_mean_variance, safeguard_variance,
    sample_range_bounds)
from ...core.fill import fill_empty_pixels
from ...filters.gaussian import final_sigmas
from .features import (DEFAULT_FEATURE_CANDIDATES, FEATURE_CANDIDATES, MIX_WEIGHTS, Candidate,
    _feature_bilateral, dual_candidate, feature_candidates, prefiltered_features,
    feature_slices, release_prefiltered, seed_prefiltered)
from .blackbox import BLACK_BOXES, Z_BLACKBOX, _guards, oidn_candidate, oidn_runs  # noqa: F401
from .thinvote import thin_vote_shown
from ...core.nets import covered_even_plan
from .onesided import one_sided
from .rim import rim_box
from .clamp import safeguarded
from .nlmeans import nlmeans_cross
from .proxy import REGRESSIONS, regression_share
from ...filters.masked import MaskedSmoothing, smooth_masked
from .passes import _mean_c, _picked, _stored
from .selection import _global_prior, _largest_remainder, _region_guard, _relative_choice

__all__ = ['AutoMethod', 'AutoRun', 'CANDIDATES', 'DEFAULT_CANDIDATES', 'DEFAULT_FEATURE_CANDIDATES', 'DUAL_BUFFER',
           'FEATURE_CANDIDATES', 'MIX_WEIGHTS']

#: Every candidate name ``candidates`` accepts.
CANDIDATES = ("box", "gauss", "nlm", "awr", "splat", "oidn")
#: Candidates that need the samples split into two halves.
DUAL_BUFFER = ("nlm", "awr", "splat")
#: Placement of the adaptive rounds' samples (option ``sampling``).
SAMPLINGS = ("gem", "uniform", "greedy")
#: The measured default (docs/methods/auto.md, "Choosing the default candidates").
DEFAULT_CANDIDATES = "box,gauss,nlm,oidn"

_WHERE = "method auto"
#: Standard errors of the pixel mean beyond which a candidate's departure from it counts as bias.
Z_BIAS = 2.0
#: Where the global default is one of :data:`BLACK_BOXES`, the clamp's standard error at the pixels that
#: take it is at least this fraction of the one from the mean per-sample variance of the 5 x 5
#: neighbourhood (:func:`~mcrecon.core.safeguard.neighbourhood_mean_variance`).
WIDE_SD = 0.5
#: The region guard's smoothing, in units of ``smooth``.
GUARD = 2.0


def agreeing_variance(v: np.ndarray, count: np.ndarray, pooled: np.ndarray | None = None,
                      divisor: np.ndarray | None = None) -> np.ndarray:
    """``pooled`` (default ``v``) where the samples of a pixel all agree (``v = 0``), floored there by the
    typical variance of its 5 x 5 neighbourhood.

    A pixel whose samples all missed a rare component its neighbours found (an indirectly lit wall at
    32 spp: a sample in 25 carries the light) has ``v = 0``; so does its 3 x 3 median
    (:func:`pooled_mean_variance`) when most of its 3 x 3 neighbours missed it too.  Its pixel mean's
    error estimate is then 0 and the clamp's interval ``y +- k sd`` a point: the pixel stays black beside
    lit ones whatever the candidates say.  The median over 5 x 5 pixels is 0 only where most of 25
    pixels agree: an exactly black region, or a caustic's line a few pixels wide on black, keep their
    zero interval.  ``divisor``: as :func:`safeguard_variance` (the pooling in units of the albedo).
    """
    base = v if pooled is None else pooled
    zero = (v == 0) & (count > 0)[..., None]
    if not zero.any():
        return base
    d2 = 1.0 if divisor is None else divisor * divisor
    wide = pooled_mean_variance(v / d2, count, radius=2) * d2
    return np.where(zero, np.maximum(base, wide), base)


def _all_samples_box(cands):
    """The index of colour-only OIDN on all the samples (``oidn``), None without it: the global prior's
    candidate where rare huge samples are around (``_global_prior(rare=)``).

    Not ``oidn_aux`` on frames with features: the tests for rare huge samples read colour units, and on a
    texture a dark square beside light ones passes them without any rare light; there the feature-guided
    defaults already place the light by the albedo (docs/methods/auto.md, step 3a)."""
    names = [c.name for c in cands]
    return names.index("oidn") if "oidn" in names else None


def _store(cands: list) -> list:
    """``cands`` with each image and estimate held as the selection reads them (:func:`.passes._stored`:
    float32, C order), in place."""
    for c in cands:
        c.image, c.mse = _stored(c.image), _stored(c.mse)
    return cands


def _release_features(halves: Halves | None, stats: PixelStats, fnames, *, oidn_after: bool) -> bool:
    """Drop the halves' feature statistics but the albedo where no reader of them is left
    (:meth:`~mcrecon.core.halves.Halves.release_features`: transient halves only); returns whether
    they were dropped.

    The prefiltered planes (kept, stored again with their layout under the halves' new feature set)
    serve OIDN's albedo and normal and the regressions; dnlm and the selection's albedo divisor
    (merged from the halves' on read) read the albedo alone.  Only xbil, the regression proxy (the
    caller's to rule out) and a prefilter not computed yet (by OIDN with ``oidn_after``, or by the
    regressions) read the rest."""
    if halves is None or not halves.a.features or "xbil" in fnames:
        return False
    pf = [prefiltered_features(hf, stored_only=True) for hf in halves]
    if any(p is None for p in pf) and ((oidn_after and "oidn_aux" in fnames) or set(fnames) & set(REGRESSIONS)):
        return False
    slices = [feature_slices(hf) for hf in halves]
    if not halves.release_features(keep=("albedo",), merged=stats):
        return False
    for hf, planes, sl in zip(halves, pf, slices):
        if planes is not None:
            seed_prefiltered(hf, planes, slices=sl)
    return True


def _bank(y, v, count, sigmas, *, box: bool) -> list:
    """The SURE candidates (``box`` first where asked, then one Gaussian per ``sigmas``), stored.

    One scale at a time (:func:`sure_filter_bank` of that scale alone, the same values and SURE maps as
    the whole bank's): the bank of all scales in float64 beside their stored copies is 1.3 GB at
    1920 x 1080."""
    out = []
    for i, s in enumerate([sigmas[k:k + 1] for k in range(len(sigmas))] or [sigmas]):
        sb = sure_filter_bank(y, v, count, s)
        if i == 0 and box:
            out += _store([Candidate("box", sb.values[0], sb.sure[0])])
        out += _store([Candidate(f"gauss{x:.3g}", sb.values[k + 1], sb.sure[k + 1]) for k, x in enumerate(sb.sigmas)])
        del sb
    return out


def _oidn_available() -> bool:
    try:
        import pyoidn  # noqa: F401
    except Exception:
        return False
    return True


@dataclasses.dataclass(eq=False)
class AutoRun(RunState):
    """Per-run state of :class:`AutoMethod` (``halves``: those of the committed samples, :meth:`Method.observe`)."""

    #: Names of the last reconstruction's candidates in ``choice`` order (the feature-guided ones
    #: included: which of them run depends on the features the samples carry).
    candidate_names: list | None = None
    #: GEM's run state for ``sampling="gem"`` (its selection's diagnostics only; planning reads the statistics).
    gem_run: object = None
    #: The last reconstruction's tile proxy verdict (:func:`.proxy.regression_share`, a :class:`.proxy.Verdict`:
    #: the share of its tiles' pixels the regression candidates took, the tiles' two least summed estimates);
    #: None where it did not run.
    regression_verdict: object = None
    #: A tile's ``(y0, y1, x0, x1)`` in its film (set by the tiles' driver; :meth:`AutoMethod.for_tiles`).
    window: tuple | None = None

    @property
    def regression_share(self) -> float | None:
        """The share of the proxy's tiles' pixels the regression candidates took (None: no proxy ran)."""
        return None if self.regression_verdict is None else self.regression_verdict.share


class AutoMethod(Method):
    """Per-pixel choice among candidate reconstructions by their estimated error.

    Options (keyword-only; also the CLI flags and ``mcrecon methods auto``):
    :attr:`options`.  Without features a run is the colour-only one, bit
    for bit; with an albedo (and normal) OIDN on all the samples runs with
    them (``oidn_aux``) in place of the colour-only ``oidn``.

    Diagnostics: ``choice`` (candidate index per pixel, in the order of
    :meth:`candidate_names`), ``estimated_mse`` (mean over channels of the
    chosen candidate's unbiased estimate), ``estimated_rel_mse`` (the
    smoothed relative estimate the choice minimised), ``sample_density``.
    """

    name = "auto"
    run_type = AutoRun
    adaptive = True
    initial_spp = 4
    #: ``sampling="gem"``: a round in whole nets whose committed samples show a rare component and make a thin
    #: vote (:func:`.thinvote.thin_vote_shown`) is the even round (:meth:`even_under_rare`).
    thin_even = True
    options = (
        Option("candidates", str, DEFAULT_CANDIDATES, "comma-separated candidate reconstructions: "
               + ", ".join(CANDIDATES) + " (nlm/awr/splat split every pixel's samples into two halves: "
               "they need the samples or a half-buffer pair; splat only offline; oidn runs on all the samples and is "
               "scored from the halves when there are halves; with halves and oidn_aux only their average oidn_halves)"),
        Option("feature_candidates", str, DEFAULT_FEATURE_CANDIDATES, "when the statistics carry features: "
               "comma-separated feature-guided candidates added to candidates, on the halves: nfor (first-order "
               "regression on the other half's weights and features, Bitterli et al. 2016; SURE), nfor_own (the "
               "same on the half's own), dnlm (NL-means of the colour divided by the albedo), mix (nfor_own and "
               "dnlm averaged 1:2, 1:1, 2:1), xbil (cross-bilateral, Rousselle et al. 2013); fbil (bilateral "
               "with feature weights only, SURE) from pixel statistics without halves; oidn_aux (OIDN on all the "
               "samples with the prefiltered albedo and normal); none: colour only"),
        Option("regression_proxy", float, None, nullable=True, help="with features: compute the regression "
               "candidates (nfor, nfor_own, mix) over the whole image only where auto's choice gives them at "
               "least this share of the pixels of a few tiles, or the tiles' summed estimates make one of them "
               "the global default or its blend partner (a tile proxy, run on frames of about 424^2 and more; "
               "0.1 measured, docs/methods/auto.md, Cost); None: always compute them", min=0.0, max=1.0),
        Option("scales", int, 8, "Gaussian scales of the gauss candidates (GEM's final bank)", min=1, max=16),
        Option("smooth", float, 2.0, "sigma (px) of the smoothing of the error maps before the choice "
               "(0: none)", min=0.0, max=32.0),
        Option("nlm_radius", int, 3, "NL-means search window radius r ((2r+1)^2 pixels)", min=1, max=15),
        Option("nlm_patch", int, 1, "NL-means patch radius f ((2f+1)^2 pixels)", min=0, max=5),
        Option("nlm_k", float, 0.45, "NL-means damping k of the variance-normalised distance", min=0.0,
               min_open=True),
        Option("initial_spp", int, 4, "samples per pixel of the uniform initial pass (>= 4: two per half)",
               min=1),
        Option("iterations", int, 4, "adaptive rounds after the initial pass", min=1),
        Option("sampling", str, "gem", "adaptive runs: gem (GEM's greedy relative-MSE placement for part of each "
               "round, the rest uniform; measured best, docs/methods/auto.md), uniform rounds, or greedy placement "
               "by auto's own error estimates", SAMPLINGS),
        Option("uniform_share", float, 0.5, "sampling='gem': share of each adaptive round spread uniformly "
               "(a defence against GEM's estimates where they mislead)", min=0.0, max=1.0),
        Option("net_counts", int, -1, "sampling='gem': 1 spends each round in whole nets (the uniform share "
               "breadth-first, GEM's counts rounded so every pixel's total is a power of two: a full net of a "
               "stratified sampler; mcrecon.core.nets), 0 the counts as they fall, -1 (default) follows the "
               "renderer: 1 where it declares a stratified sampler (Renderer.sampler 'sobol'), 0 for independent "
               "samples (docs/adaptive.md)", choices=(-1, 0, 1)),
        Option("safeguard", float, 4.0, nullable=True, help="clamp each pixel into mean +- k standard errors "
               "of its mean and into the range of the samples around it (k; None: no clamp)", min=0.0),
        Option("global_prior", float, 3.0, nullable=True, help="z: every pixel takes the candidate of least "
               "summed estimate over the image unless another's smoothed estimate is lower by more than z "
               "standard errors for all the other candidates' tests together (None: off, the plain per-pixel "
               "choice; docs/methods/auto.md)", min=0.0),
    )

    def _configure(self, params: dict) -> None:
        names = [c.strip().lower() for c in str(params["candidates"]).split(",") if c.strip()]
        if not names:
            raise InputError(self.where, "candidates", f"{params['candidates']!r}: no candidate; valid: "
                             + ", ".join(CANDIDATES))
        bad = [c for c in names if c not in CANDIDATES]
        if bad:
            raise InputError(self.where, "candidates", f"{bad[0]!r} is not valid; valid: " + ", ".join(CANDIDATES))
        if len(set(names)) != len(names):
            raise InputError(self.where, "candidates", f"{params['candidates']!r} names a candidate twice")
        if "oidn" in names and not _oidn_available():
            raise InputError(self.where, "candidates", "'oidn' needs the Python package pyoidn "
                             "(pip install pyoidn); valid without it: "
                             + ", ".join(c for c in CANDIDATES if c != "oidn"))
        ordered = tuple(c for c in CANDIDATES if c in names)
        params["candidates"] = ",".join(ordered)
        object.__setattr__(self, "_names", ordered)
        fnames = [c.strip().lower() for c in str(params["feature_candidates"]).split(",") if c.strip()]
        if fnames in ([], ["none"]):
            fnames = []
        bad = [c for c in fnames if c not in FEATURE_CANDIDATES]
        if bad:
            raise InputError(self.where, "feature_candidates", f"{bad[0]!r} is not valid; valid: none or "
                             + ", ".join(FEATURE_CANDIDATES))
        if len(set(fnames)) != len(fnames):
            raise InputError(self.where, "feature_candidates", f"{params['feature_candidates']!r} names a candidate "
                             "twice")
        if "oidn_aux" in fnames and not _oidn_available():
            raise InputError(self.where, "feature_candidates", "'oidn_aux' needs the Python package pyoidn "
                             "(pip install pyoidn); leave it out without it")
        fordered = tuple(c for c in FEATURE_CANDIDATES if c in fnames)
        params["feature_candidates"] = ",".join(fordered) or "none"
        object.__setattr__(self, "_feature_names", fordered)
        if params["sampling"] == "gem":  # its planner, with GEM's defaults
            from .. import get_method
            object.__setattr__(self, "_gem", get_method("gem"))

    @property
    def requires(self) -> Requirements:
        # the dual-buffer candidates need the samples split in two, or two half buffers a
        # renderer wrote (half_buffers: the pair stands in for the samples; with SURE
        # candidates alone the pair is merged into the statistics of all the samples)
        # features: read when the source has them and a feature candidate is on (nfor/xbil/dnlm on the
        # halves, fbil without them, oidn_aux with or without); a source without
        # features gives exactly the colour-only run
        # statistics_options: on pixel statistics alone (one EXR) the SURE candidates need neither
        return Requirements(samples=any(c in DUAL_BUFFER for c in self._names), half_buffers=True,
                            features="optional" if self._feature_names else "none",
                            statistics_options={"candidates": "box,gauss"})

    def halo(self, width, height):
        """A tile's selection's reach (:func:`.tiled.selection_reach`); None with awr, splat or the proxy."""
        from .tiled import selection_reach
        whole = bool({"awr", "splat"} & set(self._names)) or self.params["regression_proxy"] is not None
        return None if whole else selection_reach(self.params["smooth"], GUARD)

    def candidate_reach(self) -> int:
        """Pixels of context the candidates at a pixel read (:func:`.tiled.candidate_reach`)."""
        from .tiled import candidate_reach
        return candidate_reach(self.params, "gauss" in self._names)

    def tile_grid(self) -> tuple[int, int]:
        """Tiles start on the NL-means kernels' bands of rows, as nfor's do (their running sums restart there)."""
        from ...filters.nlmeans import BAND
        return BAND, 1

    def for_tiles(self, inputs: MethodInputs, each_tile=None) -> "AutoMethod":
        """A copy holding the film's pass (:func:`.tiled.film_pass`), whose selection of a tile
        (:attr:`AutoRun.window`) reads that tile's candidates from it."""
        from .tiled import film_pass
        tiled = copy.copy(self)
        object.__setattr__(tiled, "_film", film_pass(self, inputs, each_tile))
        return tiled

    def candidate_names(self) -> list[str]:
        """Names of the colour candidates in ``choice`` order (``gauss`` expands to one per scale, ``oidn``
        to ``oidn`` and ``oidn_halves``: the latter only where the run has halves, the former left out where
        ``oidn_aux`` replaces it, with an albedo in the samples and halves).

        With features the feature-guided candidates follow them; a run's own list, those included,
        is :attr:`AutoRun.candidate_names` after its reconstruction."""
        out = []
        for c in self._names:
            if c == "gauss":
                out += [f"gauss{s:.3g}" for s in final_sigmas(self.params["scales"])]
            elif c == "oidn":
                out += ["oidn", "oidn_halves"]
            else:
                out.append(c)
        return out

    # ------------------------------------------------------------ candidates
    def _candidates(self, stats: PixelStats, halves: Halves | None, nonfinite: str, *, given=None, run=None,
                    scales=(None, None), units=(None, None)):
        """Every candidate (choice order), the pixel means, their variance and the counts.

        ``given``: the OIDN candidates, already computed (the proxy's mosaic and a film's tiles take crops
        of the whole image's).  ``scales``, ``units``: each half's prefiltered features' scales for the
        regressions and its dnlm unit (a tile's: the film's, :mod:`.tiled`).  ``run``: where given, the regressions may be left out by the tile proxy
        (``regression_proxy``, :func:`.proxy.regression_share`), whose share is stored on it."""
        p = self.params
        y = stats.mean
        count = stats.count
        # s^2 / n, or for a stratified sampler's prefix-block halves their difference (core.halves)
        v, va, vb = mean_variances(stats, halves)
        # the selection's variance (its relative denominators, the clamp, the bias floor, the global prior) is
        # a many-degree one: for prefix-block halves g s^2 / n with their pooled gain, since a median of
        # neighbours or an interval on a one-degree square is narrow where the square is small by chance
        v_sel = mean_variances(stats, halves, pooled=True)[0] if halves is not None and \
            halves.sampler != "independent" else v
        # The OIDN runs first, then the feature-guided candidates, then the rest (listed in choice order
        # all the same): OIDN's scratch memory (about 1.4 GB at 1920 x 1080) then meets only the
        # statistics, and the regressions' working arrays, the largest of a frame's, only OIDN's three
        # candidates besides, not every colour candidate's image and estimate as well
        aux = self._aux_replaces_oidn(stats)
        regress = set(REGRESSIONS) & set(self._feature_names)
        if aux and regress and halves is not None and "albedo" in halves.a.features:
            # the halves' prefiltered features, computed once for OIDN's albedo and normal and the
            # regressions after it (the same planes either way)
            prefiltered_features(halves.a)
            prefiltered_features(halves.b)
        # the features' statistics past their last reader go before OIDN's scratch memory meets them
        released = given is None and (run is None or p["regression_proxy"] is None) and \
            _release_features(halves, stats, self._feature_names, oidn_after=True)
        if given is None:
            # each candidate held in the selection's dtype from its creation on (_stored: float32; the
            # next one's working memory then meets half the bytes)
            made = {name: _store(oidn_candidate(name, stats, v, halves, aux=ax, halves_only=only, variances=(va, vb)))
                    for name, ax, only in oidn_runs(self._names, aux)}
            black, black_aux = made.get("oidn", []), made.get("oidn_aux", [])
        else:
            black = [c for c in given if not c.feature]   # in the order above: colour-only OIDN's first
            black_aux = [c for c in given if c.feature]
        fnames = self._feature_names
        with_features = bool(fnames) and halves is not None and bool(halves.a.features)
        if run is not None:
            run.regression_verdict = None
        if run is not None and with_features and regress and p["regression_proxy"] is not None:
            # the regressions are half of a frame's time with features and most frames give them no
            # pixel: judged on a few tiles first (docs/methods/auto.md, "Cost")
            pf = [prefiltered_features(hf, stored_only=True) for hf in (halves.a, halves.b)]
            verdict = regression_share(self, stats, halves, nonfinite, black + black_aux, pf, steady=BLACK_BOXES)
            run.regression_verdict = verdict
            if verdict is not None and not verdict.computes(p["regression_proxy"]):
                fnames = tuple(n for n in fnames if n not in REGRESSIONS)
        released = released or (with_features and _release_features(halves, stats, fnames, oidn_after=False))
        # each stored as built: its float64 image and estimate go before the next one's working arrays
        guided = feature_candidates(fnames, halves.a, halves.b, variances=(va, vb),
                                    store=lambda c: _store([c])[0], scales=scales, units=units) \
            if with_features else []
        if with_features:  # dnlm read the halves' albedo last; the selection's divisor reads its merge alone
            halves.release_features(merged=stats, merged_keep=("albedo",))
        v_sure = agreeing_variance(v, count)
        out: list[Candidate] = []
        names = self._names
        if "box" in names or "gauss" in names:
            sig = final_sigmas(p["scales"]) if "gauss" in names else np.zeros(0)
            out += _bank(y, v_sure, count, sig, box="box" in names)
        dual = [c for c in names if c in DUAL_BUFFER]
        if dual and halves is None:
            warnings.warn(f"{_WHERE}: candidates {', '.join(dual)} need the samples (two halves); only pixel "
                          "statistics are available, so auto falls back to the SURE candidates "
                          "(box, gauss; and oidn, scored by Monte-Carlo SURE)", McreconWarning, stacklevel=4)
            dual = []
            if not out:
                sb = sure_filter_bank(y, v_sure, count, final_sigmas(p["scales"]))
                out = [Candidate("box", sb.values[0], sb.sure[0])]
        if dual:
            ha, hb = halves.a, halves.b
            ya, yb = ha.mean, hb.mean
            if "nlm" in dual:
                fa, wa, fb, wb = nlmeans_cross(ya, va, ha.count, yb, vb, hb.count, radius=p["nlm_radius"],
                                               patch=p["nlm_patch"], k=p["nlm_k"])
                sa = sure(ya, va, fa, wa)
                sbb = sure(yb, vb, fb, wb)
                out += _store([self._dual("nlm", fa, fb, sa, sbb, ha.count, hb.count)])
                del fa, wa, fb, wb, sa, sbb
            for name in ("awr", "splat"):
                if name not in dual:
                    continue
                if name == "splat" and halves.source is None:
                    warnings.warn(f"{_WHERE}: the splat candidate needs the samples themselves (offline "
                                  "reconstruction of a log or SampleSet); left out of this run",
                                  McreconWarning, stacklevel=4)
                    continue
                a, b = self._black_box(name, halves, nonfinite)
                out += _store([self._dual(name, a, b, cross_validation_mse(a, yb, vb),
                                          cross_validation_mse(b, ya, va), ha.count, hb.count)])
                del a, b
        out += black + guided + black_aux
        del black, guided, black_aux
        if halves is not None:  # their last readers were the regressions: not held through the selection
            release_prefiltered(halves.a, halves.b)
        if "fbil" in self._feature_names and stats.features and halves is None:
            # only without halves: beside the halves' candidates its estimate, biased where the features
            # are noisy (defocus), cost auto 2.3x on the built-in checker_dof (docs/methods/auto.md)
            out += _store([_feature_bilateral(stats, y, v)])
        return out, y, v_sel, count

    def _aux_replaces_oidn(self, stats: PixelStats) -> bool:
        """Whether OIDN with the albedo and normal on all the samples (``oidn_aux``) replaces colour-only
        OIDN on all the samples (``oidn``; its halves' average ``oidn_halves`` stays).

        Where the samples carry an albedo, colour-only OIDN on all the samples adds nothing auto keeps
        (the corpus' feature scenes: auto's error within 1 %, docs/methods/auto.md, "OIDN candidates")
        and costs a denoiser run; the halves' average stays, as the halves' runs are its estimate: under
        defocus the albedo misleads OIDN and colour-only OIDN on the halves is auto's best candidate
        (without it auto's error rises 1.3x on the corpus' depth of field with features)."""
        return "oidn_aux" in self._feature_names and "albedo" in stats.features

    _dual = staticmethod(dual_candidate)

    def _black_box(self, name, halves: Halves, nonfinite):
        from .. import get_method
        ha, hb = halves
        if name == "awr":
            m = get_method("awr")
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", McreconWarning)
                return (np.asarray(m.reconstruct(MethodInputs(ha)), dtype=np.float64),
                        np.asarray(m.reconstruct(MethodInputs(hb)), dtype=np.float64))
        # splat: the samples of each half (rounds dropped: single-round replay)
        m = get_method("splat")
        out = []
        for ss in halves.sample_sets():
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", McreconWarning)
                out.append(np.asarray(m.reconstruct(MethodInputs(None, ss, None, nonfinite)), dtype=np.float64))
        return out[0], out[1]

    # -------------------------------------------------------------- choice
    def _select(self, run: "AutoRun", stats: PixelStats, halves, nonfinite="drop", *, given=None, candidates=None):
        # given: the proxy's mosaic (its OIDN candidates cropped from the whole image's); no proxy inside it.
        # candidates: _candidates' result, computed before (the proxy reads their sums on its tiles too)
        film = getattr(self, "_film", None)   # a tile of a film (for_tiles): its candidates from the film's pass
        if film is not None and candidates is None:
            candidates = film.tile_inputs(run.window, self.where)
        cands, y, v, count = candidates if candidates is not None else self._candidates(
            stats, halves, nonfinite, given=given, run=run if given is None else None)
        run.candidate_names = [c.name for c in cands]
        _store(cands)  # the selection's passes read C order, as stored (a given list may not be yet)
        den = relative_denominator(y, v, count, eps=DEFAULT_EPS)
        smooth = self.params["smooth"]
        # Smoothed estimates, floored by each pixel's own evidence of bias: a
        # candidate whose value departs from the pixel mean by more than
        # Z_BIAS standard errors has at least (|x - y| - z sqrt v)^2 of
        # squared bias there, whatever its neighbours say (the smoothing
        # would otherwise let noisy bright neighbours vote a blur into an
        # exact dark pixel beside them).
        # The clamp's interval and the bias floor use each pixel's variance floored by its
        # neighbourhood's (pooled_mean_variance): a pixel whose samples missed a rare bright
        # component has a small variance of its own and a true value far outside its mean +- 4 sd
        # (a small light on a texture: a clamp on the pixel's own variance puts the hole back).
        # The unbiased estimates themselves keep v.
        # With an albedo the neighbourhood is pooled, and the heavy-tail rule's median taken, in units
        # of each pixel's albedo (albedo_divisor): a light square beside dark ones would otherwise have
        # its interval narrowed by theirs.
        divisor = albedo_divisor(stats) if self.params["safeguard"] is not None else None
        v_safe = v if self.params["safeguard"] is None else agreeing_variance(
            v, count, safeguard_variance(v, count, divisor), divisor)
        smoothing = MaskedSmoothing(smooth)
        rel, choice = _relative_choice(cands, den, y, np.sqrt(v_safe), count, smoothing, Z_BIAS)
        h, w = count.shape
        bounds = v_wide = None
        on_default = np.zeros((h, w), bool)
        prior = {}
        if self.params["global_prior"] is not None and len(cands) > 1 and smooth > 0:
            bounds = sample_range_bounds(stats)
            steady = [k for k, c in enumerate(cands) if c.name in BLACK_BOXES]
            if steady and self.params["safeguard"] is not None:
                # A black box is the default only after a significant whole-image test; at its pixels
                # the interval comes from the neighbourhood's mean per-sample variance too: under rare
                # huge samples the median's interval excludes the truth at most pixels whose samples
                # missed them (the reference itself, clamped so, keeps 0.19 of the pixel mean's error
                # on the corpus' tuning caustic and spotlit texture), and OIDN's value there would be
                # pulled back onto the noise.  Elsewhere (other defaults: NL-means smears an HDR
                # emitter's rim through a wide interval) the median's stands.
                v_wide = np.maximum(v_safe, (WIDE_SD * WIDE_SD) * agreeing_variance(
                    v, count, neighbourhood_mean_variance(v, count, divisor=divisor), divisor))
            # the default's smoothed estimate again, not every candidate's kept until the default is known
            choice, on_default = _global_prior(cands, lambda k: smoothing([_mean_c(cands[k].mse, den)])[0], rel,
                                               choice, y, v, count, bounds, smooth, self.params["global_prior"],
                                               self.params["safeguard"], _guards(cands), divisor,
                                               steady=steady, steady_var=v_wide, rare=_all_samples_box(cands),
                                               rim=rim_box(cands),
                                               info=prior, fixed=None if film is None else film.default,
                                               heavy=one_sided(stats) if film is None else None)
        if cands[0].name == "box" and smooth > 0:
            # Region guard: where the chosen candidates' unbiased estimates,
            # summed over a neighbourhood (relative, as the metric sums them),
            # exceed the pixel mean's, the region keeps the pixel mean.  Not where the pixel holds
            # the global prior's default: its sum over the whole image beat the mean's, a far less
            # noisy test than a neighbourhood's (docs/methods/auto.md, "Selection rule").
            choice = _region_guard(cands, den, choice, on_default, GUARD * smooth)
        img, raw_abs, est_rel = _picked(cands, rel, choice)
        if cands[0].name == "box":  # the pixel mean's own bits where it is chosen: its stored image is y rounded
            at = choice == 0
            img[at] = y[at]
        img = fill_empty_pixels(img, count, source=_WHERE) if (count == 0).any() else img
        img[~np.isfinite(img)] = 0.0
        if self.params["safeguard"] is not None:
            safeguarded(img, cands, choice, stats, y, v, count, level=self.params["safeguard"], v_safe=v_safe,
                        v_wide=v_wide, bounds=bounds, on_default=on_default, prior=prior, scale=divisor)
        fin = np.isfinite(raw_abs)
        if not fin.all():
            raw_abs = np.where(fin, raw_abs, smooth_masked(raw_abs, max(smooth, 1.0)))
        run.diagnostics = {
            "choice": choice.astype(np.float64),
            "estimated_mse": np.where(np.isfinite(raw_abs), raw_abs, 0.0),
            "estimated_rel_mse": np.where(np.isfinite(est_rel), est_rel, 0.0),
            "sample_density": count.astype(np.float64),
        }
        return np.asarray(img, dtype=np.float64), est_rel

    # ------------------------------------------------------------- offline
    def reconstruct_run(self, run: "AutoRun", inputs: MethodInputs) -> np.ndarray:
        """The per-pixel choice: (H, W, C) float64.

        The dual-buffer candidates read the two halves ``inputs.halves``
        (split from the samples by the dispatcher, a pair a renderer wrote,
        or an adaptive run's own, :meth:`Method.run_inputs`); without them
        (statistics only) only the SURE candidates run (a warning says so).
        The SURE candidates see ``inputs.stats``: with halves, their merge.
        """
        stats = inputs.stats if inputs.stats is not None else inputs.halves.merged()
        halves = inputs.halves if any(c in DUAL_BUFFER for c in self._names) else None
        img, _ = self._select(run, stats, halves, inputs.nonfinite)
        return img

    # ------------------------------------------------------------ adaptive
    def plan(self, run: "AutoRun", state: AdaptiveState):
        """After the initial pass (uniform ``initial_spp``), rounds as ``sampling`` says.

        ``gem`` (default): :meth:`Method.plan` with :meth:`place`; in whole nets the net gate (``nets.net_plan``),
        where a rare component keeps it off :meth:`even_under_rare`; independent: ``nets.covered_even_plan``.
        ``uniform``: doubling uniform rounds.  ``greedy``: ``iterations``
        rounds placing samples greedily.  Each greedy round reconstructs
        with every candidate, takes the chosen result's smoothed relative
        error estimate ``e_p`` and sends ``n_p`` samples in proportion to
        ``e_p * d / (n_p + d)`` (``d`` the round's average spp): the fall of
        the variance part of the error from d more samples, as GEM's Sec. 5
        (n_eff = n, conservative for filtered pixels).  Integer counts by
        largest remainders (ties by pixel index): deterministic, so a
        resumed run plans the same.
        """
        p = self.params
        if p["sampling"] == "gem":
            return covered_even_plan(self, state, threshold=self._gem.rare_gate(state)) or super().plan(run, state)
        remaining = state.remaining
        if remaining <= 0:
            return None
        if p["sampling"] == "uniform":
            # The estimates that pick a filter well are too noisy per pixel to place samples
            # (docs/methods/auto.md, "Adaptive sampling"): uniform rounds doubling the total
            # after the initial_spp pass, like box.
            n = self.doubling_round(state)
            return state.request(counts=uniform_counts(state.width, state.height, n, state.rng))
        npix = state.width * state.height
        left = p["iterations"] - state.iteration
        n_round = remaining if left <= 1 else max(1, remaining // left)
        halves = run.halves if any(c in DUAL_BUFFER for c in self._names) else None
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", McreconWarning)
            _, est = self._select(run, state.stats, halves)
        n = state.stats.count.astype(np.float64)
        d = n_round / npix
        pri = np.where(np.isfinite(est), np.maximum(est, 0.0), 0.0) * (d / (n + d))
        pri = np.where(n == 0, np.inf, pri)
        counts = _largest_remainder(pri, n_round)
        return state.request(counts=counts)

    def even_under_rare(self, run: "AutoRun", state: AdaptiveState) -> bool:
        """Whether a round in whole nets that the net gate leaves to the plan (a rare component shows,
        :func:`~mcrecon.core.nets.net_plan`) is the even round: where the committed samples make the global
        prior's vote thin (:func:`.thinvote.thin_vote_shown`), an OIDN candidate running.  The final default is
        then a black box, which neither GEM's estimates nor the gate's colour-only reconstruction of the halves
        score, and whose error follows the pixel means' (the tuning spotlit texture: the adaptive pixel means
        err 1.06-1.26x the uniform render's, auto's image 1.05-1.55x; docs/adaptive.md).  Rounds of
        independent samples keep the allocation (the default checker_spot: 1.00 with even rounds against
        0.82)."""
        p = self.params
        # oidn_aux runs only where the samples carry an albedo (_aux_replaces_oidn)
        black_box = "oidn" in self._names or self._aux_replaces_oidn(state.stats)
        return self.thin_even and black_box and p["global_prior"] is not None and \
            thin_vote_shown(state.stats, run.halves, p["safeguard"])

    def place(self, run: "AutoRun", state: AdaptiveState, n: int):
        """GEM's placement (Sec. 5) of ``n`` samples; :meth:`Method.plan` spreads ``uniform_share`` uniformly.

        Rounds: ``iterations`` after the initial pass (iteration i sends
        ``remaining // (iterations - i)``).  The GEM part is GEM's own
        planning with its default options on the committed statistics: its
        adaptive scale selection, the estimated relative MSE of the
        selected filters and :meth:`GEMMethod.place_greedy` (pipelined, the
        pending samples counted).  The uniform part keeps every pixel's
        share of samples at least ``uniform_share`` of a uniform run's, so
        a pixel whose GEM estimate misleads is never starved.

        Why the uniform part: auto's own greedy placement and GEM's placement
        alone lose to uniform sampling on depth of field; with half of each
        round uniform, auto beats uniform sampling on every built-in scene
        (docs/methods/auto.md, "Adaptive sampling", has the table).
        """
        if n <= 0:
            return np.zeros((0, 2))
        if int(state.stats.count.sum()) == 0:  # nothing committed to place by (every sample dropped as NaN)
            return uniform_counts(state.width, state.height, n, state.rng)
        gem = self._gem
        npix = state.width * state.height
        if run.gem_run is None:
            run.gem_run = gem.start(state.width, state.height, state.stats.channels)
        # the floor's gate of 5 whatever the sampler: gem's 3 for independent samples costs auto's
        # checker_spot (1.00 against 0.818) and checker_wall (docs/adaptive.md)
        sel = gem.select(run.gem_run, state.stats, final=False, want_mse=True)
        return gem.place_greedy(sel, sel.image, state, n, max(1, int(round(state.budget / npix))))
