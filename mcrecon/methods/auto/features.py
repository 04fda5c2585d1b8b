"""``auto``'s feature-guided candidates: filters of the half buffers that read the per-sample features.

Each candidate comes with an unbiased estimate of its MSE: a filter of one
half from that half alone (:func:`feature_guided_half`) by cross-validation
against the other half, NFOR's cross-buffer regression (:func:`_regressions`)
by Stein's estimate with its exact centre weight, ``fbil`` (pixel statistics
without halves, :func:`_feature_bilateral`) by Stein's estimate.
``docs/methods/auto.md`` ("With per-sample features") measures each.
"""

from __future__ import annotations

import dataclasses
import functools
import warnings
import weakref

import numpy as np

from ...core.features import layout_of
from ...core.fill import fill_empty_pixels, mean_variance_policy
from ...core.stats import PixelStats
from ...errors import McreconWarning
from .estimates import cross_validation_mse, dual_buffer_mse, sure

__all__ = ["Candidate", "DEFAULT_FEATURE_CANDIDATES", "FEATURE_CANDIDATES", "MIX_WEIGHTS", "dual_candidate",
           "feature_candidates", "feature_guided_half",
           "release_prefiltered", "seed_prefiltered"]

#: Feature-guided candidates (option ``feature_candidates``), used when the samples carry features.
FEATURE_CANDIDATES = ("nfor", "nfor_own", "dnlm", "mix", "xbil", "fbil", "oidn_aux")
#: The measured default of ``feature_candidates`` (docs/methods/auto.md, "With per-sample features").
DEFAULT_FEATURE_CANDIDATES = "nfor,nfor_own,dnlm,mix,fbil,oidn_aux"
#: Weights of ``nfor_own`` in the ``mix`` candidates (``w nfor_own + (1 - w) dnlm`` per half).
MIX_WEIGHTS = (1 / 3, 1 / 2, 2 / 3)

_WHERE = "method auto"


@dataclasses.dataclass(eq=False)
class Candidate:
    name: str
    image: np.ndarray   # (H, W, C)
    mse: np.ndarray     # (H, W, C) unbiased estimate (NaN: undefined at that pixel, +inf: impossible)
    feature: bool = False   # guided by the features (the global prior's default test treats these apart)
    #: a black box's crossed vote (:func:`.selection.crossed_sum`), shared by the two candidates of one
    #: filter's halves; None where it was not computed
    crossed: float | None = None


def dual_candidate(name, a, b, est_a, est_b, ca, cb, feature=False) -> Candidate:
    """The candidate ``(a + b) / 2`` of two filtered halves with the MSE of the average from the halves' unbiased
    estimates (:func:`~.estimates.dual_buffer_mse`)."""
    both = (np.asarray(ca) > 0) & (np.asarray(cb) > 0)
    img = 0.5 * (a + b)
    mse = dual_buffer_mse(a, b, est_a, est_b)
    # a pixel without a sample in one half: no unbiased estimate (NaN, filled by
    # the smoothing); its value comes from the half that has one (the feature
    # candidates fill a half's empty pixels from its neighbours, so both are finite there)
    only_b = (np.asarray(cb) > 0) & ~(np.asarray(ca) > 0)
    img = np.where(both[..., None], img, np.where(only_b[..., None] | ~np.isfinite(a), b, a))
    mse = np.where(both[..., None], mse, np.nan)
    img = np.where(np.isfinite(img), img, 0.0)
    return Candidate(name, img, mse, feature)


def _filled(a: np.ndarray, count: np.ndarray) -> np.ndarray:
    """``a`` with empty pixels (``count == 0``) taken from their nearest sampled neighbour; ``a`` itself
    when none is empty (the colour's fill already warned for the run)."""
    if not (count == 0).any():
        return a
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", McreconWarning)
        return fill_empty_pixels(a.copy(), count, source=_WHERE)


def _feature_planes(st: PixelStats) -> tuple[np.ndarray, np.ndarray]:
    """Every feature component of ``st`` as (H, W, D) pixel means (empty pixels filled) and the
    variance of those means (:func:`mean_variance_policy`)."""
    names = st.feature_names
    f = np.concatenate([_filled(st.features[n].mean, st.features[n].count) for n in names], axis=2)
    fv = np.concatenate([mean_variance_policy(st.features[n]) for n in names], axis=2)
    return f, fv


class _HalfPlanes:
    """One half buffer's inputs to the feature-guided filters, each computed once and only if asked for:
    its colour and the variance of its means (also the other half's cross-validation needs), its
    features with their variances (:func:`_feature_planes`), and those features NL-means prefiltered
    (NFOR's Sec. 5.1 with the half's own weights: window 11^2, patch 7^2, k = 0.5)."""

    def __init__(self, half: PixelStats):
        self.half = half

    @functools.cached_property
    def colour(self) -> np.ndarray:
        return _filled(self.half.mean, self.half.count)

    @functools.cached_property
    def variance(self) -> np.ndarray:
        return mean_variance_policy(self.half)

    @functools.cached_property
    def features(self) -> tuple[np.ndarray, np.ndarray]:
        return _feature_planes(self.half)

    @functools.cached_property
    def prefiltered(self) -> np.ndarray:
        # the stored planes when computed already (auto computes them before OIDN): the unfiltered
        # planes, 14 float64 planes a half with albedo, normal and depth, are then never built
        stored = prefiltered_features(self.half, stored_only=True)
        return stored if stored is not None else prefiltered_features(self.half, planes=self.features)


#: Each buffer's prefiltered feature planes (:func:`prefiltered_features`), kept while the buffer lives,
#: with the sample counts they were computed from.
_PREFILTERED: "weakref.WeakKeyDictionary[PixelStats, tuple]" = weakref.WeakKeyDictionary()


def _stamp(st: PixelStats) -> tuple:
    # samples added to the buffer after the prefilter change its counts: the stored planes are then stale
    return (int(st.count.sum()),) + tuple(int(st.features[n].count.sum()) for n in st.feature_names)


def feature_slices(st: PixelStats) -> dict:
    """Where each feature's components lie among the planes of :func:`prefiltered_features`: as stored with
    them where they are for these samples (auto releases the statistics of the features read for those
    planes alone once they are computed, :func:`~.method._release_features`), else as ``st``'s features
    (their layout: no merge of features merged on read)."""
    got = _PREFILTERED.get(st)
    if got is not None and got[0] == _stamp(st):
        return dict(got[2])
    out, k = {}, 0
    for n, c in layout_of(st.features).items():
        out[n] = slice(k, k + c)
        k += c
    return out


def prefiltered_features(st: PixelStats, *, planes=None, stored_only: bool = False) -> np.ndarray | None:
    """Every feature component of ``st`` (:func:`_feature_planes`) NL-means prefiltered with its own weights
    (NFOR's Sec. 5.1 with one buffer: window 11^2, patch 7^2, k = 0.5), (H, W, D).

    Computed once per buffer: the regression candidates and OIDN's albedo and normal of the same half
    (:func:`~.blackbox.oidn_aux`) read the same planes.  The filter weighs each channel by that channel
    alone, so a subset of the planes is bit-identical to prefiltering that subset by itself.
    ``planes``: ``_feature_planes(st)`` if already at hand.  ``stored_only``: None unless already
    computed for these samples.
    """
    from ...filters.nlmeans import nlmeans_filter

    stamp = _stamp(st)
    got = _PREFILTERED.get(st)
    if got is not None and got[0] == stamp:
        return got[1]
    if stored_only:
        return None
    f, fv = _feature_planes(st) if planes is None else planes
    pf = nlmeans_filter(f, f, fv, radius=5, patch=3, k=0.5)
    _PREFILTERED[st] = (stamp, pf, feature_slices(st))
    return pf


def seed_prefiltered(st: PixelStats, planes: np.ndarray, *, slices: dict | None = None) -> None:
    """Store ``planes`` as ``st``'s prefiltered features (:func:`prefiltered_features`): a crop of a buffer
    whose planes are computed takes the crop of them (the whole image's values, not a crop's edge effects).
    ``slices``: where each feature lies among them (:func:`feature_slices`; None: as ``st``'s features)."""
    _PREFILTERED[st] = (_stamp(st), planes, dict(feature_slices(st) if slices is None else slices))


def release_prefiltered(*buffers: PixelStats) -> None:
    """Forget the buffers' stored prefiltered planes (:func:`prefiltered_features`).

    auto's last readers of them are the regressions (OIDN's albedo and normal, :func:`~.blackbox.oidn_aux`,
    read them before); the halves themselves live on with the caller (the reader's inputs, an adaptive run's state), and the planes
    with them: 7 planes a half with albedo, normal and depth, 0.23 GB for both halves at 1920 x 1080,
    beside every candidate through the selection."""
    for st in buffers:
        _PREFILTERED.pop(st, None)


def feature_guided_half(name: str, half: PixelStats | _HalfPlanes, *, scale: float | None = None) -> np.ndarray | None:
    """A feature-guided filter of one half buffer from that half alone (its colour and its features).

    ``xbil``: :func:`~mcrecon.filters.cross_bilateral.cross_bilateral` (RDFC-style: feature distances
    normalised by the features' variance; window 11 x 11).  ``dnlm``: NL-means of the half's colour
    divided by its albedo, multiplied back (:func:`~mcrecon.filters.demodulation.demodulated_nlmeans`);
    None when the half has no ``albedo`` feature.  ``nfor_own``: NFOR's feature prefilter and
    collaborative first-order regression (:mod:`mcrecon.methods.nfor`; window 19 x 19, patch 3,
    k = 1) with the half's own NL-means weights and features (NFOR's crossed halves are the ``nfor``
    candidate, :func:`_regressions`).  Pixels without a sample take their nearest sampled neighbour's
    values.  ``scale``: dnlm's irradiance unit (:func:`~mcrecon.filters.demodulation.demodulation_scale`;
    None: the half's own; a tile's: its film's, :func:`dnlm_scale`).
    """
    from ...filters.cross_bilateral import cross_bilateral
    from ...filters.demodulation import demodulated_nlmeans

    p = half if isinstance(half, _HalfPlanes) else _HalfPlanes(half)
    y, v = p.colour, p.variance
    if name == "dnlm":
        alb = p.half.features.get("albedo")
        if alb is None:
            return None
        return demodulated_nlmeans(y, v, _filled(alb.mean, alb.count), scale=scale)
    if name == "xbil":
        # window 11^2, not RDFC's 21^2: the same choice on every scene measured (within 1.5 %) at
        # 0.28x the time (2.4 s a half at 1024^2 against 8.5 s)
        f, fv = p.features
        return cross_bilateral(y, v, f, fv, radius=5)
    if name == "nfor_own":
        return _regressions(p, None)[0]
    raise ValueError(f"feature_guided_half: {name!r}; valid: xbil, dnlm, nfor_own")


def dnlm_scale(half: PixelStats) -> float | None:
    """dnlm's irradiance unit of a half (:func:`~mcrecon.filters.demodulation.demodulation_scale` of its
    colour and albedo, as :func:`feature_guided_half` computes it); None without an albedo."""
    from ...filters.demodulation import demodulation_scale

    alb = half.features.get("albedo")
    return None if alb is None else demodulation_scale(_filled(half.mean, half.count), _filled(alb.mean, alb.count))


def _regressions(guide: _HalfPlanes, other: _HalfPlanes | None, *, own: bool = True, scales=None):
    """NFOR's collaborative regression (window 19 x 19, patch 3, k = 1) on one half's NL-means weights and
    prefiltered features, of that half's colour (``own``: the ``nfor_own`` image) and of the ``other``
    half's (NFOR's cross-buffer image of the other half, with its centre weight).

    The weights and the design, and so the normal equations and their factorisation, serve both colours:
    one pass instead of two.  ``scales``: the guide's prefiltered features' (mean, deviation) pairs
    (:func:`~mcrecon.filters.regression.feature_scale`; None: the planes' own), a tile's the film's.
    The cross-buffer image of half B is a linear function of B's colour whose
    weights and features come from half A alone, so Stein's estimate with the exact centre weight
    (:func:`~mcrecon.filters.regression.collaborative_regression`) is unbiased for its MSE; NFOR's own
    dual-buffer estimate of it is not (its filtered halves depend on both halves: 0.77x the true error
    on a textured Mitsuba wall).  Returns ``(own image or None, other's image or None, its centre
    weight or None)``.
    """
    from ...filters.regression import collaborative_regression

    parts = ([guide.colour] if own else []) + ([other.colour] if other is not None else [])
    c = guide.colour.shape[2]
    # the colours given apart: the regression writes them into its padded planes without their concatenation
    res = collaborative_regression(parts, guide.colour, guide.variance, guide.prefiltered, radius=9, patch=3, k=1.0,
                                   variance_scale=1.0, return_centre_weight=other is not None,
                                   feature_scales=scales)
    if other is None:
        return res, None, None
    out, cw = res
    return (out[..., :c] if own else None), out[..., -c:], cw


def _feature_bilateral(stats: PixelStats, y: np.ndarray, v: np.ndarray) -> "Candidate":
    """``fbil``: a joint bilateral filter of the pixel means with weights from the features alone.

    Linear in the colour (weights that do not look at it), so Stein's estimate applies as for the
    Gaussians, with the centre weight ``w_ii = 1 / sum_q w_iq`` (the centre's own weight is 1):
    the one feature-guided candidate that needs no halves, so pixel statistics (a pbrt-v4 GBuffer
    or Mitsuba AOV EXR) use their features too.  The features' own noise is correlated with the
    colour's (the same samples), so the estimate is exact only for noise-free features.
    """
    from ...filters.cross_bilateral import cross_bilateral

    f, fv = _feature_planes(stats)
    img, wsum = cross_bilateral(_filled(y, stats.count), v, f, fv, k_colour=None, return_weights=True)
    mse = sure(y, v, img, 1.0 / wsum)
    return Candidate("fbil", img, np.where((stats.count > 0)[..., None], mse, np.nan), feature=True)


def feature_candidates(names, ha: PixelStats, hb: PixelStats, *, variances=None, store=None,
                       scales=(None, None), units=(None, None)) -> list[Candidate]:
    """The feature-guided candidates ``names`` (of :data:`FEATURE_CANDIDATES`) on the two halves.

    ``nfor_own``, ``dnlm``, ``xbil`` and the ``mix`` of the first two filter each half with its own
    colour and features only (:func:`feature_guided_half`), so each result is independent of the
    other half and its cross-validation against it unbiased (as for the black boxes).  ``nfor``
    filters each half with the other's weights and features (:func:`_regressions`), so it is
    scored by Stein's estimate instead, exact for a filter linear in the half it filters.
    ``variances``: the halves' means' variances ``(v_A, v_B)`` the estimates read
    (:func:`~mcrecon.core.halves.mean_variances`; None: each half's ``s^2 / n``).  ``store``: applied to
    each candidate as soon as it is built (auto's float32 store), so its float64 image and estimate go
    at once and the candidates built before meet the next one's working arrays in the stored dtype
    (six candidates at 1920 x 1080: 0.3 GB, not 0.6 GB); None keeps them as built.  ``scales``: each
    half's prefiltered features' scales for the regressions (:func:`_regressions`; a tile's: the film's);
    ``units``: each half's dnlm unit (:func:`dnlm_scale`; a tile's: the film's).
    """
    from .estimates import sure

    keep = (lambda c: c) if store is None else store

    pa, pb = _HalfPlanes(ha), _HalfPlanes(hb)
    va, vb = (pa.variance, pb.variance) if variances is None else variances
    own = {}
    out = []
    want_own = "nfor_own" in names or ("mix" in names and "albedo" in ha.features)
    if "nfor" in names or want_own:
        # one regression per half serves that half's own image and the other half's crossed one
        own_a, cross_b, cw_b = _regressions(pa, pb if "nfor" in names else None, own=want_own, scales=scales[0])
        own_b, cross_a, cw_a = _regressions(pb, pa if "nfor" in names else None, own=want_own, scales=scales[1])
        if want_own:
            # compact copies: the regression's images are views of its whole (planes, H, W) output
            # (both colours and the weights, 8 planes a half with the crossed image), which the mixes
            # below would otherwise hold beside dnlm's working arrays
            own["nfor_own"] = (np.ascontiguousarray(own_a), np.ascontiguousarray(own_b))
        if "nfor" in names:
            out.append(keep(dual_candidate("nfor", cross_a, cross_b, sure(ha.mean, va, cross_a, cw_a),
                                           sure(hb.mean, vb, cross_b, cw_b), ha.count, hb.count, feature=True)))
        del own_a, own_b, cross_a, cross_b, cw_a, cw_b
    if "xbil" not in names:
        # the unfiltered feature planes and their variances (14 planes a half with albedo, normal and
        # depth) serve the prefilter and xbil only: not held beside the candidates built below
        pa.__dict__.pop("features", None)
        pb.__dict__.pop("features", None)
    for name in ("dnlm", "xbil"):
        if name in names or (name == "dnlm" and "mix" in names):
            a, b = feature_guided_half(name, pa, scale=units[0]), feature_guided_half(name, pb, scale=units[1])
            if a is not None and b is not None:   # None: a feature it needs is not in the samples
                own[name] = (a, b)
    mixes = "mix" in names and "dnlm" in own and "nfor_own" in own
    pairs = list(own.items()) + ([(f"mix{round(100 * w)}", w) for w in MIX_WEIGHTS] if mixes else [])
    # each candidate is built and its halves' images let go one after the other (each mix from the two
    # halves' images it averages, then those go too): at most one mix's halves beside the candidates
    for name, ab in pairs:
        if name.startswith("mix"):
            (ra, rb), (da, db), w = own["nfor_own"], own["dnlm"], ab
            a, b = w * ra + (1.0 - w) * da, w * rb + (1.0 - w) * db
        else:
            a, b = ab
        if name in names or name.startswith("mix"):
            out.append(keep(dual_candidate(name, a, b, cross_validation_mse(a, hb.mean, vb),
                                           cross_validation_mse(b, ha.mean, va), ha.count, hb.count,
                                           feature=True)))
        del a, b, ab
    return out

