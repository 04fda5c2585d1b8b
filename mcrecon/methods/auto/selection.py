"""auto's per-pixel selection: the floored relative estimates and the plain choice, the global prior, the
region guard, heavy tails (the passes over all candidates' maps: :mod:`.passes`).
"""

from __future__ import annotations


import dataclasses
import math

import numba
import numpy as np
from scipy.special import ndtr, ndtri

from ...filters.engine import parallel_rows

from .blend import blend_default
from .firefly import FIREFLY, HEAVY_TAIL, Z_FIREFLY, _firefly  # noqa: F401 (Z_FIREFLY: the tests read it here)
from .apart import HEAVY_PRIOR, _apart, left_out  # noqa: F401 (HEAVY_PRIOR, _apart: the tests read them here)
from .thinvote import THIN_VOTE, _could_vote, _thin_default
from .onesided import heavy_vote
from .rim import ONE_SAMPLE, _lifted, _lowered  # noqa: F401 (ONE_SAMPLE: the tests read it here)
from .passes import (_FirstLeast, _arrays, _c64, _channel_mean, _compress, _means, _nanmax,  # noqa: F401
                     _relative_choice)
from ...filters.masked import MaskedSmoothing, effective_counts
from ...filters.order import neighbour_median8, neighbour_medians8


#: Standard errors (the larger of the pixel's and its 3 x 3 neighbourhood's mean) beyond which the
#: global prior's candidate counts as biased at a pixel, which then keeps the per-pixel choice.  Above
#: the safeguard's 4: under pure noise a test at 4 fires on ~3 channels of a 128^2 RGB image, exactly
#: the pixels of largest error, where the clamped wide candidate beats any per-pixel choice.
Z_BIAS_PRIOR = 5.0
#: Standard errors by which a feature-guided candidate's summed estimate must undercut the best colour
#: candidate's to become the global default, and the tile (pixels) of the sums the error comes from.
#: 0.5, not 2: with albedo demodulation among the feature candidates, 2 kept NL-means the default of a
#: textured Mitsuba wall where the demodulated filter is 10 % better (sum -1.7, se 1.8); 0.5 still
#: keeps the colour default where a feature candidate's lower sum is noise (docs/methods/auto.md).
Z_GLOBAL = 0.5
BLOCK = 8
#: Whether the global prior's default is blended with its runner-up (:mod:`.blend`; ``_global_prior(blend=)``).
BLEND = True


def local_z(z: float, alternatives: int) -> float:
    """The standard errors each of ``alternatives`` local tests needs so that, under pure noise, the chance
    that any of them passes at a pixel is the one-sided tail of ``z`` (Sidak's correction:
    ``Phi(-z_m) = 1 - (1 - Phi(-z))^(1/m)``).  Every pixel runs one test per candidate other than the
    default: at ``z`` each, some candidate passes by chance about ``alternatives`` times as often, and where
    one does the pixel takes a candidate its neighbourhood's noise favoured (on a flat field, patches of
    NL-means carry a fifth of the error at 0.2 % of the pixels)."""
    if alternatives <= 1:
        return float(z)
    tail = -math.expm1(math.log1p(-float(ndtr(-z))) / alternatives)
    return float(-ndtri(tail))


def _significantly_lower(d: np.ndarray, z: float | None = None) -> bool:
    """Whether ``sum(d) < -z * se`` (z default :data:`Z_GLOBAL`), se from the spread of the sums over BLOCK x
    BLOCK tiles."""
    z = Z_GLOBAL if z is None else z
    total, se = _summed(d)
    return bool(np.isfinite(se)) and total < -z * se


def _summed(d: np.ndarray) -> tuple:
    """``(sum(d), se)``: se from the spread of the sums over BLOCK x BLOCK tiles (neighbouring pixels'
    estimates are correlated); NaN with fewer than two tiles."""
    h, w = d.shape
    hb, wb = -(-h // BLOCK), -(-w // BLOCK)
    pad = np.zeros((hb * BLOCK, wb * BLOCK))
    pad[:h, :w] = d
    t = pad.reshape(hb, BLOCK, wb, BLOCK).sum(axis=(1, 3)).ravel()
    if t.size < 2:
        return float(t.sum()), np.nan
    return float(t.sum()), float(np.sqrt(t.size) * np.std(t, ddof=1))


def _nearer_the_neighbours(cands, g, choice, y, where, scale=None):
    """Per pixel of ``where``: candidate ``g``'s value no farther than the chosen candidate's from the median
    of the 8 neighbours' means (the sum over channels of the distances; edges repeated, empty neighbours'
    means 0); False elsewhere and where a neighbour's mean or a value is NaN.  With ``scale`` (H, W, C,
    positive: the albedo) the means and values are divided by it first, as in
    :func:`_no_push_in_heavy_tails`: on a texture the neighbours' colour is another square's."""
    out = np.zeros(y.shape[:2], bool)
    if where.any():
        yr = y if scale is None else y / scale
        sc = np.ones((0, 0, 0)) if scale is None else scale
        parallel_rows(_nearer_rows, (_c64(yr), _c64(sc), _arrays([c.image for c in cands]), int(g),
                                     np.ascontiguousarray(choice), np.ascontiguousarray(where), out), y.shape[0])
    return out


@numba.njit(cache=True, nogil=True)
def _nearer_rows(y, scale, images, g, choice, where, out, i0, i1):
    """``y``: the means, already divided by ``scale`` where ``scale`` is not empty (then each value is too)."""
    h, w, c = y.shape
    xg = images[g]
    scaled = scale.size > 0
    for i in range(i0, i1):
        for k in range(len(images)):
            xk = images[k]
            for j in range(w):
                if not where[i, j] or choice[i, j] != k:
                    continue
                dg = 0.0
                dc = 0.0
                for ch in range(c):
                    med = neighbour_median8(y, i, j, ch)
                    if scaled:
                        s = scale[i, j, ch]
                        dg += abs(xg[i, j, ch] / s - med)
                        dc += abs(xk[i, j, ch] / s - med)
                    else:
                        dg += abs(xg[i, j, ch] - med)
                        dc += abs(xk[i, j, ch] - med)
                out[i, j] = dg <= dc  # False when any is NaN


def summed_estimates(cands, y, v, count, hi, safeguard, within=None):
    """The global prior's statistic: ``(den_loo, cap, loo, apart, vote, sums)``.

    ``apart``: the pixels of rare huge samples or far brighter than their neighbourhood (:func:`_apart`);
    ``loo(k)``: candidate k's capped leave-one-out relative estimate, computed where it is read (three
    times a candidate) rather than every candidate's kept at once: K maps of H x W (0.3 GB at 1080p);
    ``vote``: the pixels (within ``within`` where given) that are not :func:`_apart` and where every
    candidate's estimate is finite; ``sums``: each candidate's ``np.sum(loo(k)[vote])``, None where no pixel
    votes.  ``hi``: the top of the pixels' sample range (:func:`~mcrecon.core.safeguard.sample_range_bounds`).
    """
    return _summed_with(cands, loo_estimates(cands, y, v, count, hi, safeguard), within)


def loo_estimates(cands, y, v, count, hi, safeguard):
    """``(den_loo, cap, loo, apart)`` of :func:`summed_estimates`: each a function of a pixel's 3 x 3
    neighbourhood, what a tile of the image computes of its own pixels."""
    # rare huge samples: the 3 x 3 maximum far above the pixel's mean and its neighbourhood's median
    # (so that one pixel whose mean fell near 0 by chance does not count; a median, not a mean,
    # which a bright emitter beside dim pixels would dominate); and pixels far brighter than their
    # neighbourhood (an emitter's edge): their relative estimates, divided by the neighbours' mu^2,
    # reach ~1e4 where the typical is ~1 (a Cornell box with a small bright light: two such pixels
    # made a 1.41 px Gaussian the whole image's default)
    den_loo, apart = left_out(y, v, count, hi, safeguard is not None)
    cap = None if safeguard is None else (safeguard + 1.0) ** 2

    def loo(k):
        return _means([cands[k].mse], den_loo, v, cap)[0]

    return den_loo, cap, loo, apart


def crossed_sum(cva, cvb, ha, hb, va, vb, den) -> float:
    """The crossed vote of a filter run on each half (its cross-validated estimates ``cva`` of half A's
    output against half B's means, ``cvb`` the other way; (H, W, C)): the sum of ``cva / den`` (channel
    mean) over the pixels half A's own samples let vote (not :func:`_apart` by half A's samples, means
    ``ha.mean``, variances ``va``), plus the same for B.  A pixel's voting is then chosen by the half the
    filter read, and the other half's means it is scored against are not selected by it: where most
    pixels have rare huge samples around, the whole vote's voters are selected by every sample, and
    their estimates charge a filter that restores a light those samples missed (docs/methods/auto.md,
    "A thin vote").  ``den``: the relative denominator (the same for every candidate of a frame)."""
    from ...core.safeguard import sample_range_bounds

    return crossed_total([crossed_terms(cv, h.mean, vh, h.count, sample_range_bounds(h)[1], den)
                          for cv, h, vh in ((cva, ha, va), (cvb, hb, vb))])


def crossed_terms(cv, mean, v, count, hi, den) -> tuple:
    """One half's terms of :func:`crossed_sum`: ``(r, votes)``, ``cv / den`` (channel mean, (H, W)) and the
    pixels whose finite ``r`` vote (the half's ``mean``, ``v``, ``count`` and sample range's top ``hi``).
    A pixel's terms read its 3 x 3 neighbourhood: a band of rows grown by one gives its rows'."""
    votes = ~left_out(mean, v, count, hi, True)[1]
    r = np.mean(np.asarray(cv, np.float64) / den, axis=2)
    return r, votes & np.isfinite(r)


def crossed_total(terms) -> float:
    """The crossed vote from each half's :func:`crossed_terms` of the film (arrays or memory maps), summed in
    the film's order."""
    total = 0.0
    for r, votes in terms:
        total += float(np.sum(r[votes]))
    return total


@dataclasses.dataclass(frozen=True)
class Default:
    """The global prior's whole-image decision (:func:`prior_default`): the default ``g`` (None: no pixel
    votes, the prior does not apply), whether the vote was thin, and the default's :class:`~.blend.Blend`
    (None: not blended).  What the tiles of an image are given, made once on the image's sums."""

    g: int | None
    thin: bool = False
    blend: object = None


def prior_default(cands, y, v, count, hi, safeguard, guarded=(), *, steady=(), blend=None, thin_vote=None,
                  local=None, heavy=None) -> Default:
    """The global prior's default over the image (:func:`_global_prior`, whose docstring states the
    rule): the candidate of least summed estimate, a thin vote's steady one, the guards' tests, the blend.
    ``local``: :func:`loo_estimates` of these arrays, if at hand.  ``heavy``: the pixels whose own samples
    have a one-sided tail (:func:`.onesided.one_sided`; None: not counted).  Reads each candidate's estimate and
    the default's and its partners' images (the film's, for tiles: memory-mapped ones serve)."""
    blend = BLEND if blend is None else blend
    thin_vote = THIN_VOTE if thin_vote is None else thin_vote
    den_loo, cap, loo, apart, vote, sums = summed_estimates(cands, y, v, count, hi, safeguard) if local is None \
        else _summed_with(cands, local)
    if sums is None:
        return Default(None)
    g = int(np.argmin(sums))
    zs = guarded if isinstance(guarded, dict) else {k: Z_GLOBAL for k in guarded}
    plain = [k for k in range(len(cands)) if k not in zs]
    # thin, or heavy: most pixels vote with rare huge samples of their own, and their capped sums lose their
    # positive tails (:mod:`.onesided`)
    thin = bool(steady) and (vote.sum() < thin_vote * _could_vote(v, count, safeguard)
                             or heavy_vote(vote, heavy, count))
    if thin:
        # a thin vote: the steady candidate (black box) of least sum, compared with its own kind only
        # (the voters' selection flatters the Stein-scored filters: THIN_VOTE)
        g = _thin_default(cands, steady, sums)
    loo_g = loo(g)
    if g in zs and plain and not thin:
        # a guarded candidate (feature-guided, or a black box scored by cross-validation) is the default
        # only where its lower sum is real: lower than the best plain candidate's by its z standard errors
        # of the summed difference, from sums over BLOCK x BLOCK tiles (neighbouring pixels' estimates
        # are correlated)
        c = plain[int(np.argmin([sums[k] for k in plain]))]
        if not _significantly_lower(np.where(vote, loo_g - loo(c), 0.0), zs[g]):
            g = c
            loo_g = loo(g)
    b = None
    if blend and not thin and not (g == 0 and cands[0].name == "box"):  # a thin vote's sums are what it
        # does not trust
        b = blend_default(cands, g, sums, vote, den_loo, zs,
                          lambda k: _summed(np.where(vote, loo(k) - loo_g, 0.0))[1], v, cap,
                          among=steady if g in steady else None, plan=True)[0]
    return Default(g, thin, b)


def _summed_with(cands, local, within=None):
    """:func:`summed_estimates` from its :func:`loo_estimates` ``local``."""
    den_loo, cap, loo, apart = local
    vote = ~apart  # and every candidate's estimate finite
    if within is not None:
        vote &= within
    for k in range(len(cands)):
        vote &= np.isfinite(loo(k))
    if not vote.any():
        return den_loo, cap, loo, apart, vote, None
    # np.sum(r[vote]) of each, the voters gathered into one buffer (numpy's pairwise sum of the same
    # contiguous values: the same bits)
    buf = np.empty(vote.size)
    sums = [float(np.sum(buf[:_compress(loo(k).ravel(), vote.ravel(), buf)])) for k in range(len(cands))]
    return den_loo, cap, loo, apart, vote, sums


def _global_prior(cands, smoothed, rel, choice, y, v, count, bounds, sigma, z, safeguard, guarded=(), scale=None,
                  steady=(), steady_var=None, blend=None, rare=None, info=None, thin_vote=None, fixed=None, heavy=None,
                  rim=None):
    """The per-pixel choice with the best single candidate over the image as the default.

    ``g`` = the candidate of least summed leave-one-out relative estimate
    (:func:`.estimates.relative_denominator_loo`) over the pixels that vote, each
    pixel's estimate capped at ``(safeguard + 1)^2 v``: after the clamp
    into ``y +- safeguard sd`` no candidate's squared error exceeds about
    that, so a candidate that is wild at a few pixels the safeguard repairs
    is not ruled out for them.  Over ~all pixels the sums are far less
    noisy than any per-pixel estimate.  A pixel takes ``g`` unless another
    candidate k's smoothed estimate is lower by more than ``z`` standard
    errors of the smoothed difference ``raw_k - raw_g`` (local spread over
    the smoothing's effective pixels, :func:`effective_counts`: ``4 pi
    sigma^2`` inside the image, about half along its edges); among ``g`` and such candidates
    the least smoothed estimate wins (``g``'s own unfloored: its bias is the
    next test's).  Pixels keep the plain per-pixel ``choice`` where ``g``
    departs from the pixel mean by more than :data:`Z_BIAS_PRIOR` standard
    errors (evidence of bias), where rare huge samples are around or the
    pixel is far brighter than its neighbours (:data:`HEAVY_PRIOR`; there
    every estimate is least reliable, and a relative one divided by the
    neighbours' mu^2 can be 10^4 times the typical) and where
    all samples agree (v = 0: the safeguard pins them whatever is chosen),
    unless ``g`` lies no farther than the plain choice from the median of
    the 8 neighbours' means (:func:`_nearer_the_neighbours`) and no other
    candidate passed the local test (then they take ``g``); none of these
    vote.  (Not all of them take ``g``: where ``g`` keeps a firefly that the
    plain choice removes, as nfor does behind glass, one pixel can rule an
    image's error.)  A pixel whose own mean is a firefly (:func:`_firefly`, with :data:`FIREFLY`) is
    judged as these, but votes.  When ``g`` is the pixel mean (candidate 0 named ``box``) the
    plain choice stands everywhere: the
    region guard already makes the mean the default of every region
    without evidence against it (a global box default costs the built-in
    caustic 15 %).  A ``guarded`` candidate (the feature-guided
    ones, and OIDN) is ``g`` only if its sum undercuts the best plain candidate's
    significantly (:func:`_significantly_lower`; ``guarded``: indices, each at
    :data:`Z_GLOBAL` standard errors, or a dict index -> z): the feature-guided
    estimates are the noisiest where they differ most, at texture edges, and a
    cross-validated black box's noise is independent of the Stein estimates'.  ``scale`` (the albedo)
    divides the means and values of the median test (:func:`_nearer_the_neighbours`:
    on a texture a neighbour's colour is another square's).  A ``steady`` candidate (indices: auto's
    OIDN candidates, which become ``g`` only through a significant whole-image test) stays ``g`` at the
    pixels with rare huge samples around too: there the plain per-pixel choice rests on the least
    reliable estimates of all, and a whole-image winner's sum is the better evidence (a spotlit
    texture: 85 % of its pixels have rare huge samples around), and its bias test reads ``steady_var``
    (default ``v``): the variance its pixels are clamped on.  Returns the new
    choice and the mask of pixels whose choice is ``g`` (all False when the
    prior does not apply).

    Where fewer than ``thin_vote`` (default :data:`THIN_VOTE`) of the pixels that could vote
    (:func:`_could_vote`: with samples and, with the safeguard, some variance) vote and there
    are ``steady`` candidates, ``g`` is the steady one of least sum, without its guard (``info["thin"]``:
    whether that applied): the voters are then the pixels whose neighbourhoods missed a rare light, a
    selection by their own samples that flatters the Stein-scored filters of those samples and charges
    the cross-validated black boxes, and the pixels left out would keep the plain per-pixel choice,
    which rests on the least reliable estimates of all, where a steady default takes them.  So too where
    more than :data:`.onesided.HEAVY_VOTE` of the pixels with samples vote with a one-sided tail of their own
    (``heavy``, :func:`.onesided.one_sided`; None: not counted): their capped sums lose their positive tails.

    With ``blend`` (default :data:`BLEND`) ``g`` is first blended with its runner-up
    (:func:`~.blend.blend_default`, partners among ``steady`` where ``g`` is one of them): ``cands[g]``
    is replaced by the blend, under ``g``'s name, so that every later reader sees it.

    ``rare`` (an index: auto's black box run on all the samples) takes every pixel the vote leaves out for
    rare huge samples or a bright emitter's edge (:func:`_apart`) whatever ``g`` is, where its estimate is
    defined (not every pixel whose 3 x 3 maximum exceeds :data:`HEAVY_TAIL` times its mean: at 8 spp a
    flat field's near-zero means pass that test): there every per-pixel estimate rests on
    the one sample that carries the light and the whole-image sums leave those pixels out, while a
    denoiser trained on such noise that sees every sample at once spreads that sample's light where it
    belongs (the average of it run on each half sees each rare sample at twice its weight).  Those pixels
    count as the default's (the returned mask): the region guard leaves them.  ``info`` (a dict), where
    given, receives ``"g"`` (the default's index, -1 where the prior does not apply) and ``"rare"`` (the
    mask of the pixels ``rare`` or ``rim`` took).

    ``rim`` (an index: auto's OIDN with the albedo and normal on the halves, on a frame where no colour-only
    OIDN on all the samples runs to be ``rare``) takes those of the same pixels whose mean one sample carries
    where it lowers them below their mean and the plain choice (:func:`_lowered`, :func:`_lifted`'s mirror), and
    counts them as the default's.  At an emitter's rim a pixel that caught one emitter sample has a mean
    that lies far above its truth as often as below, and the metric, relative, charges the first far more:
    a rim pixel with truth 0.56 and one emitter sample of 417 in 32 carries 0.90 of the pixel mean's error
    over the whole image.  Not every such pixel (``rare``'s rule): beside the emitter OIDN + albedo + normal
    spreads its light into dark pixels whose samples all agree (docs/methods/auto.md, "Rare huge samples").

    ``fixed``: the whole-image decision (:class:`Default`: ``g``, thin, the blend) made before on the
    image's sums (:func:`prior_default`); given, this is a tile's prior, the rest of the rule local.
    ``info["decision"]`` receives it.

    ``smoothed(k)``: candidate k's smoothed relative estimate (asked for
    ``g``'s only); ``rel``: the floored ones ``choice`` minimised, ``rel[k]`` an (H, W) map
    (:class:`_Floored`, or a (K, H, W) array; NaN: undefined, never the least).  Each other candidate's test runs on
    its own, one after the other (the difference maps of all of them at
    once cost more in fresh memory than their arithmetic).
    """
    if fixed is None:
        local = loo_estimates(cands, y, v, count, bounds[1], safeguard)
        fixed = prior_default(cands, y, v, count, bounds[1], safeguard, guarded, steady=steady, blend=blend,
                              thin_vote=thin_vote, local=local, heavy=heavy)
    else:   # the image's decision, made on its sums before (a tile of it)
        local = loo_estimates(cands, y, v, count, bounds[1], safeguard)
    den_loo, cap, loo, apart = local
    none = np.zeros(choice.shape, bool)
    if info is not None:
        info["decision"] = fixed
    if fixed.g is None:
        return choice, none
    g, thin = fixed.g, fixed.thin
    if info is not None:
        info["thin"] = thin
        info["g"] = g
    if g == 0 and cands[0].name == "box":
        return choice, none
    mixed = fixed.blend is not None
    if mixed:
        rel[g] = rel[g]  # the plain default's floored map, read below, before its candidate is replaced
        # the default blended with the runner-up where their summed estimates say a mix is better than
        # either (:mod:`.blend`): cands[g] is replaced, so every later reader (the local tests, the
        # region guard, the picked image) sees the blend
        cands[g] = fixed.blend.of(cands)
    loo_g = loo(g)
    smoothing = MaskedSmoothing(sigma)
    least = _FirstLeast(choice.shape)
    masks, n_eff = [], []
    z_each = local_z(z, len(cands) - 1)  # one test per other candidate, z for them all
    h = choice.shape[0]
    for k in range(len(cands)):
        if k == g:
            # g's own unfloored estimate: its bias is the test below; its floor at Z_BIAS (4.6 % of
            # pure-noise pixels) would hand the pixel to any alternative that passed the z test by chance
            sg = smoothed(g)
            sg = np.where(np.isfinite(sg), sg, rel[g])
            if mixed:  # the choice's estimate of a blended default is the blend's
                rel[g] = sg
            least.offer(g, sg)
            continue
        d, d2, mask = np.empty(choice.shape), np.empty(choice.shape), np.empty(choice.shape, bool)
        parallel_rows(_difference_rows, (loo(k), loo_g, d, d2, mask), h)
        m, q = smoothing([d, d2])
        # the smoothing's effective number of pixels, per pixel: about half of 4 pi sigma^2 along the
        # image's edges, a quarter in its corners (with 4 pi sigma^2 everywhere, 9 of the 16 regions of
        # flat exponential noise, 64^2 at 8 spp, 4 seeds, where a worse candidate passes the test lie
        # on the border).
        # The masks are mostly one: filtered once.
        a = next((a for a, mk in enumerate(masks) if np.array_equal(mk, mask)), None)
        if a is None:
            a = len(masks)
            masks.append(mask)
            n_eff += effective_counts([mask], sigma)
        # k's estimate where it passed its test (written over m), +inf elsewhere
        parallel_rows(_passed_rows, (m, q, n_eff[a], z_each, rel[k], m), h)
        least.offer(k, m)
    c2 = least.index
    # the test's standard error: the larger of the pixel's own and its 3 x 3 neighbourhood's mean
    # (a pixel's own sample variance is often far too small under skewed noise: with exponential
    # samples at 32 spp its own alone flagged 1.7 % of a flat field at 4 sd)
    biased = np.empty(choice.shape, bool)
    vb = steady_var if g in steady and steady_var is not None else v
    _biased(_c64(cands[g].image), _c64(y), _c64(vb), Z_BIAS_PRIOR, np.ascontiguousarray(count > 0), biased)
    # where the estimates are least reliable (rare huge samples around) g still stands, if no other
    # candidate passed the local test there, where it lies no farther than the plain choice from the
    # median of the 8 neighbours' means: a robust reference that a firefly kept by g (NFOR's
    # own-patch weights keep one) lies far from
    # At such a pixel that g would lift above both its own mean and the plain choice, the plain choice
    # stands (:func:`_lifted`): at an emitter's rim the median of the neighbours lies on the emitter.
    if g in steady:
        default = np.isfinite(rel[g]) & ~biased
        # nor does another candidate's local test override it there: at a pixel with rare huge samples
        # around, every local estimate is dominated by the one sample that carries them (a
        # cross-validated black box's most of all), and a local "pass" is that sample's noise
        c2 = np.where(apart | (bounds[1] > HEAVY_TAIL * np.abs(y)).any(axis=2), g, c2)
    else:
        # a pixel whose own mean is a firefly is judged as one the vote left out (:func:`_firefly`)
        loose = apart | _firefly(y, v, bounds[1], scale) if FIREFLY else apart
        at_g = loose & (c2 == g)
        at_g &= ~_lifted(cands, g, choice, y, v, at_g)
        default = np.isfinite(rel[g]) & ~biased & (~loose | _nearer_the_neighbours(cands, g, choice, y, at_g, scale))
    out = np.where(default, c2, choice)
    held = default & (c2 == g)
    if rare is not None and rare != g:
        # the black box on all the samples where rare huge samples are around (docstring: ``rare``)
        at = apart & np.isfinite(rel[rare]) & np.isfinite(cands[rare].image).all(axis=2)
        out = np.where(at, rare, out)
        held = np.where(at, True, held)
        if info is not None:
            info["rare"] = at
    if rim is not None and rim != g:
        # the one-sample pixels of the same set that the rim candidate lowers (docstring: ``rim``)
        at = apart & np.isfinite(rel[rim]) & np.isfinite(cands[rim].image).all(axis=2)
        at &= _lowered(cands, rim, choice, y, v, at)
        out = np.where(at, rim, out)
        held = np.where(at, True, held)
        if info is not None:
            info["rare"] = at | info["rare"] if "rare" in info else at
    return out, held


@numba.njit(cache=True, nogil=True)
def _difference_rows(lk, lg, d, d2, mask, i0, i1):
    # d = lk - lg, NaN where either is NaN or lg is infinite; d2 = d * d; mask = d finite
    for i in range(i0, i1):
        for j in range(lk.shape[1]):
            a, b = lk[i, j], lg[i, j]
            x = np.nan if (a != a or b != b or np.isinf(b)) else a - b
            d[i, j] = x
            d2[i, j] = x * x
            mask[i, j] = np.isfinite(x)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _passed_rows(m, q, n, z, rel, out, i0, i1):
    # out = rel where m < -z se, se = sqrt(max(q - m^2, 0) / n) (m finite), else +inf
    for i in range(i0, i1):
        for j in range(m.shape[1]):
            mm = m[i, j]
            se = np.sqrt(_nanmax(q[i, j] - mm * mm, 0.0) / n[i, j])
            out[i, j] = rel[i, j] if np.isfinite(mm) & (mm < (-z) * se) else np.inf


@numba.njit(cache=True, nogil=True, inline="always")
def _neighbourhood_mean_row(x, i, c, t, r, out_row):
    # row i of _neighbourhood_mean of x (H, W * C), rows in order: t, the running sums along axis 0,
    # advanced from row i - 1 to row i; r a row buffer
    h, n = x.shape
    w = n // c
    if i == 0:
        for q in range(n):
            t[q] = ((0.0 + _finite0(x[0, q])) + _finite0(x[0, q])) + _finite0(x[min(1, h - 1), q])
    else:
        a, b = x[min(i + 1, h - 1)], x[max(i - 2, 0)]
        for q in range(n):
            t[q] += _finite0(a[q]) - _finite0(b[q])
    for q in range(n):
        r[q] = t[q] / 3.0
    for ch in range(c):
        s = ((0.0 + r[ch]) + r[ch]) + r[min(1, w - 1) * c + ch]
        out_row[ch] = s / 3.0
        for j in range(1, w):
            s += r[min(j + 1, w - 1) * c + ch] - r[max(j - 2, 0) * c + ch]
            out_row[j * c + ch] = s / 3.0


@numba.njit(cache=True, nogil=True)
def _neighbourhood_mean(v, out):
    """``scipy.ndimage.uniform_filter(where(isfinite(v), v, 0), size=(3, 3, 1), mode="nearest")`` of
    ``v`` (H, W, C), term for term as scipy computes it (so bit-identical, tested): along axis 0, then
    axis 1, a running sum ``t`` of the 3 values under the window (edges repeated; first ``((0 + x_0) +
    x_0) + x_1``, then ``t += x_new - x_old``), each output ``t / 3``, the first pass stored as float64."""
    h, w, c = v.shape
    n = w * c
    t, r = np.empty(n), np.empty(n)
    for i in range(h):
        _neighbourhood_mean_row(v.reshape(h, n), i, c, t, r, out[i].reshape(n))


@numba.njit(cache=True, nogil=True, inline="always")
def _finite0(x):
    return x if np.isfinite(x) else 0.0


@numba.njit(cache=True, nogil=True)
def _biased(x, y, v, zb, has, out):
    """Per pixel with samples: any channel with ``|x - y| > zb sqrt(max(v, v_nb))`` (NaN as np.maximum),
    ``v_nb`` the :func:`_neighbourhood_mean` of ``v``, row by row (no image of it)."""
    h, w, c = x.shape
    n = w * c
    t, r, nb = np.empty(n), np.empty(n), np.empty(n)
    for i in range(h):
        _neighbourhood_mean_row(v.reshape(h, n), i, c, t, r, nb)
        for j in range(w):
            b = False
            for ch in range(c):
                if abs(x[i, j, ch] - y[i, j, ch]) > zb * np.sqrt(_nanmax(v[i, j, ch], nb[j * c + ch])):
                    b = True
            out[i, j] = b and has[i, j]


def _region_guard(cands, den, choice, keep, sigma):
    """``choice`` with the pixel mean (0) where the chosen candidates' relative estimates minus the mean's,
    smoothed (``sigma``), exceed 0, except at ``keep``; the estimates unsmoothed and unfloored, each only
    where it is chosen."""
    diff = np.empty(choice.shape)
    parallel_rows(_guard_rows, (_arrays([c.mse for c in cands]), _c64(den), np.ascontiguousarray(choice), diff),
                  diff.shape[0])
    diff = MaskedSmoothing(sigma)([diff])[0]
    return np.where(np.isfinite(diff) & (diff > 0) & ~keep, 0, choice)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _guard_rows(mses, den, choice, out, i0, i1):
    # out = the chosen candidate's relative estimate minus the first's (the channel means of mse / den),
    # each non-finite one read as NaN
    h, w, c = den.shape
    a = np.empty(w * c)
    b = np.empty(w * c)
    for i in range(i0, i1):
        m0 = mses[0]
        for k in range(len(mses)):
            mk = mses[k]
            for j in range(w):
                if choice[i, j] != k:
                    continue
                o = j * c
                for ch in range(c):
                    a[o + ch] = mk[i, j, ch] / den[i, j, ch]
                    b[o + ch] = m0[i, j, ch] / den[i, j, ch]
                x, y0 = _channel_mean(a, o, c), _channel_mean(b, o, c)
                out[i, j] = (x if np.isfinite(x) else np.nan) - (y0 if np.isfinite(y0) else np.nan)


def _no_push_in_heavy_tails(img: np.ndarray, y: np.ndarray, hi: np.ndarray, out: np.ndarray | None = None, *,
                            scale: np.ndarray | None = None) -> np.ndarray:
    """Where the samples around a pixel are heavy-tailed, a candidate may pull it towards its neighbours, not away.

    A pixel is heavy-tailed when the largest sample of its 3 x 3
    neighbourhood (``hi``, from :func:`sample_range_bounds`) exceeds
    :data:`HEAVY_TAIL` times its mean ``y``: rare huge samples (caustics,
    small lights) are around.  There the error estimates that chose a
    candidate are least reliable, and a candidate that moves the pixel
    *further* from the median of its 8 neighbours' means than its own mean
    is (above it when the mean is above the median, or below) carries a
    neighbour's rare sample into it; the pixel keeps its own mean.  Per
    channel; at the film's border the missing neighbours repeat the edge
    (the pixel itself may count up to three times), an empty neighbour's
    mean is 0.  From pixel statistics without a sample range (a half-buffer
    pair, an EXR) ``hi`` is the 3 x 3 maximum of the pixel means, so the
    rule then fires at any edge of more than 10x contrast.  It protects the
    built-in caustic and hdr's rim pixels; elsewhere it costs little
    (docs/methods/auto.md, "Selection rule").
    Written into ``out`` (default a new array; ``img`` itself may be given:
    each value reads only its own pixel of ``img``).

    ``scale`` (H, W, C), positive: the median and the pixel's side of it are taken of ``y / scale``
    (auto passes the albedo: the light, not the texture, is what a rare sample carries).  On a
    texture the neighbours' median of the colour is another square's colour, and the rule reverted
    every candidate that moved a dark pixel beside light ones further down, towards its truth
    (a textured Mitsuba corridor: dnlm alone 0.075 of the mean's error, through the rule 0.099).
    """
    # one compiled pass (the numpy formulation, kept in the tests as the reference, was 1.2 s of
    # auto's 8 s at 1024^2)
    img = np.ascontiguousarray(img, dtype=np.float64)
    out = img.copy() if out is None else out
    y = np.ascontiguousarray(y, dtype=np.float64)
    hi = np.ascontiguousarray(hi, dtype=np.float64)
    ref = y if scale is None else np.ascontiguousarray(y / scale, dtype=np.float64)
    # row blocks on the filters' thread pool (a parallel=True kernel cost 1.5 s of compilation on a first run)
    parallel_rows(_no_push_rows, (img, y, ref, hi, HEAVY_TAIL, out), y.shape[0])
    return out


@numba.njit(cache=True, nogil=True)
def _no_push_rows(img, y, ref, hi, heavy_tail, out, i0, i1):
    """:func:`_no_push_in_heavy_tails` per pixel and channel in rows [i0, i1) (``out`` starts as a copy of ``img``).

    The median of the 8 neighbours' ``ref`` (``y``, or ``y / scale``; edge-repeated; an empty neighbour's mean
    counts) is :func:`~mcrecon.filters.order.neighbour_median8`, as
    :func:`numpy.median` computes it; NaN anywhere among them makes it NaN,
    and a NaN median never reverts.  Computed for whole rows
    (:func:`~mcrecon.filters.order.neighbour_medians8`): the rule fires at
    half the values of a film with rare huge samples.
    """
    h, w, c = y.shape
    n = w * c
    med = np.empty(n)
    for i in range(i0, i1):
        neighbour_medians8(ref, i, med[c:n - c] if w > 1 else med[:0])
        for j in (0, w - 1):
            for ch in range(c):
                med[j * c + ch] = neighbour_median8(ref, i, j, ch)
        yr, rr, ir, hr, orow = y[i].reshape(n), ref[i].reshape(n), img[i].reshape(n), hi[i].reshape(n), out[i].reshape(n)
        for q in range(n):
            yc, rc, oc, md = yr[q], rr[q], ir[q], med[q]
            if hr[q] > heavy_tail * abs(yc) and oc != yc and ((rc > md and oc > yc) or (rc < md and oc < yc)):
                orow[q] = yc


def _largest_remainder(pri: np.ndarray, total: int) -> np.ndarray:
    """Integer counts summing to ``total`` in proportion to ``pri`` (inf: served first, evenly)."""
    h, w = pri.shape
    flat = pri.ravel()
    counts = np.zeros(flat.size, np.int64)
    inf = np.isposinf(flat)
    if inf.any():
        idx = np.flatnonzero(inf)
        k = min(total, idx.size)
        counts[idx[:k]] += 1
        total -= k
        flat = np.where(inf, 0.0, flat)
    s = float(flat.sum())
    if total > 0:
        if not s > 0:
            flat = np.ones(flat.size)
            s = float(flat.size)
        share = flat * (total / s)
        base = np.floor(share).astype(np.int64)
        rest = total - int(base.sum())
        if rest > 0:
            order = np.argsort(-(share - base), kind="stable")[:rest]
            base[order] += 1
        counts += base
    return counts.reshape(h, w)
