"""``nfor``: the registered method (Bitterli et al. 2016) on half buffers with per-sample features."""

from __future__ import annotations

import copy
import dataclasses
import math
import warnings

import numpy as np

from ...core.fill import fill_empty_pixels, mean_variance_policy
from ...core.safeguard import (albedo_divisor, confidence_clamp, empty_pixels_kept, safeguard_variance,
                               sample_range_bounds)
from ...core.stats import PixelStats
from ...errors import InputError, McreconWarning
from ..base import Method, MethodInputs, Option, Requirements, RunState, variant_option
from .firefly import leave_out_isolated
from .pipeline import PAPER, denoise_planes, film_feature_scales
from ...filters.nlmeans import BAND
from ...filters.regression import MIN_COVER_WEIGHT, RIDGE

__all__ = ["NFORMethod", "NFORRun", "feature_planes", "feature_components", "channel_floor"]

_WHERE = "method nfor"
#: The pipeline's parameters that are no option: the paper's (nfor_denoise's defaults).
_FIXED = ("mse_radius", "mse_patch", "mse_k", "final_feature_radius", "final_feature_patch", "final_feature_k",
          "final_k")


@dataclasses.dataclass(eq=False)
class NFORRun(RunState):
    """Per-run state (``halves``: those of the committed samples with their features, :meth:`Method.observe`)."""


def _parse_bandwidths(text: str) -> tuple[float, ...]:
    try:
        ks = tuple(float(t) for t in str(text).split(",") if t.strip())
    except ValueError:
        ks = ()
    if len(ks) not in (1, 2) or not all(np.isfinite(k) and k > 0 for k in ks):
        raise InputError(_WHERE, "bandwidths", f"{text!r}, expected one or two positive numbers separated by a "
                         "comma (the paper: 0.5,1.0)")
    return ks


def _filled(half: PixelStats, other: PixelStats) -> np.ndarray:
    """A half's pixel means, a pixel without a sample in it taking its nearest sampled neighbour's value there.

    A half without any sample (one sampled pixel whose one sample went to
    the other half) has no neighbour to fill from: it takes the other
    half's filled means, so the regression sees two equal halves instead of
    a black one (which would halve the image).
    """
    if (half.count == 0).all() and (other.count > 0).any():
        half = other
    return fill_empty_pixels(half.mean.copy(), half.count, source=_WHERE)


def feature_planes(a: PixelStats, b: PixelStats, stats: PixelStats) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every feature component of the halves as (H, W, D) means, and the variance of the full mean.

    Pixels without a sample in a half take their nearest sampled
    neighbour's value there (:func:`_filled`); the variance follows the one
    fill-in policy for pixels with fewer than two samples
    (:func:`mcrecon.core.fill.mean_variance_policy`).
    """
    fa, fb, fv = [], [], []
    for name in a.feature_names:
        ha, hb = a.features[name], b.features[name]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", McreconWarning)  # the colour's fill warns once for the pixel
            fa.append(_filled(ha, hb))
            fb.append(_filled(hb, ha))
        fv.append(mean_variance_policy(stats.features[name]))
    h, w = a.count.shape
    if not fa:
        z = np.zeros((h, w, 0))
        return z, z, z
    return np.concatenate(fa, axis=2), np.concatenate(fb, axis=2), np.concatenate(fv, axis=2)


def feature_components(a: PixelStats, b: PixelStats):
    """:func:`feature_planes` one component at a time: ``(feat_a, feat_b, feat_variance)`` (H, W) each, in the
    order of :func:`feature_planes`' planes and bit-identical to them, with one feature's merge at a time
    (the film's merged features are never held whole)."""
    for name in a.feature_names:
        ha, hb = a.features[name], b.features[name]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", McreconWarning)
            fa, fb = _filled(ha, hb), _filled(hb, ha)
        fv = mean_variance_policy(ha.merged(hb))
        for m in range(fa.shape[2]):
            yield fa[..., m], fb[..., m], fv[..., m]


def channel_floor(var: np.ndarray, divisor: np.ndarray | None = None) -> np.ndarray:
    """Each pixel's variance of its mean, per channel, floored by its largest channel's (in albedo units).

    A pixel's channels share its samples' paths: where one channel's
    samples vary and another's are all zero (a red path among empty ones
    in a caustic's shadow), the zero channel drew none of what the other
    drew, and its own variance (0) would pin a clamp onto its mean (0):
    the pixel came out (0.19, 0, 0) where the truth is grey.  The floor
    ``max_c v_c / d_c^2 * d_c^2`` (``d``: the albedo divisor) gives every
    channel the interval its noisiest channel needs, measured in units of
    the pixel's reflectance so that a coloured albedo does not widen the
    dark channels beyond their own scale.  (H, W, C) in and out.
    """
    v = np.asarray(var, dtype=np.float64)
    if divisor is None:
        return np.maximum(v, v.max(axis=2, keepdims=True))
    d2 = np.asarray(divisor, dtype=np.float64) ** 2
    return np.maximum(v, (v / d2).max(axis=2, keepdims=True) * d2)


class NFORMethod(Method):
    """Feature-guided first-order regression on half buffers (NFOR, Bitterli et al. 2016); needs features.

    Bitterli, Rousselle, Moon, Iglesias-Guitian, Adler, Mitchell, Jarosz,
    Novak 2016, "Nonlinearly weighted first-order regression for denoising
    Monte Carlo renderings", CGF 35(4).

    Needs the samples (split into two halves by the dispatcher) or a half-buffer pair,
    and features (albedo, normal, depth or any other); refuses sources
    without features.  Uniform sampling in doubling rounds when run
    adaptively.

    ``variant='robust'`` (the default) departs from the paper in one step:
    the result is clamped into each pixel's confidence interval of its
    mean, ``mean +- safeguard`` standard errors (the variance floored by its
    neighbourhood's in units of the albedo,
    :func:`~mcrecon.core.safeguard.safeguard_variance`) and the range of
    the samples around it (:func:`~mcrecon.core.safeguard.confidence_clamp`,
    auto's and awr's safeguard), then into the interval the pixel's samples
    give without their largest (smallest) one unless a neighbour's sample
    was as far out, where the result keeps more than half of the pixel's
    own excess beyond it (:func:`~mcrecon.methods.nfor.firefly.leave_out_isolated`:
    a lone firefly finds no matching patch, so the regression keeps it).  The regression's weights come from the
    colour, and under rare huge samples (a caustic, an emitter's rim) they
    spread one pixel's light over exact dim neighbours: the paper's
    algorithm gave 12x the pixel mean's error on the built-in caustic and
    2.3x on hdr, the clamp 0.69 and 0.66, textured scenes within 0.1 %
    or better at 32 spp (docs/methods/nfor.md).  Pixels without a sample
    keep the value filled in from their neighbours.  ``variant='paper'`` is the paper's
    algorithm alone (``safeguard=None``).
    """

    name = "nfor"
    variants = {"robust": {"safeguard": 4.0}, "paper": {"safeguard": None}}
    options = (
        variant_option(variants),
        Option("bandwidths", str, "0.5,1.0", "NL-means bandwidths k of the regression's candidates (one or two, "
               "comma separated; the paper: 0.5,1.0)"),
        Option("radius", int, PAPER["radius"], "regression window radius (the window is (2r+1)^2; paper: 9)",
               min=1, max=30),
        Option("patch", int, PAPER["patch"], "NL-means patch radius of the regression weights (paper: 3)",
               min=0, max=10),
        Option("feature_radius", int, PAPER["feature_radius"], "search radius of the feature prefilter (paper: 5)",
               min=0, max=30),
        Option("feature_patch", int, PAPER["feature_patch"], "patch radius of the feature prefilter (paper: 3)",
               min=0, max=10),
        Option("feature_k", float, PAPER["feature_k"], "bandwidth of the feature prefilter (paper: 0.5)",
               min=0.0, min_open=True),
        Option("stride", int, 1, "fit a regression window at every stride-th pixel and row only, and at the "
               "pixels those windows leave (nearly) unweighted; each pixel averages the windows covering it "
               "(1: every pixel, the paper)", min=1, max=10),
        Option("second_pass", bool, PAPER["second_pass"], "Sec. 5.4's second regression of the averaged halves"),
        Option("ridge", float, RIDGE, "ridge on the regression's non-constant columns (standardised features), "
               "times the window's total weight: makes flat or collinear features solvable", min=0.0, max=1.0),
        Option("safeguard", float, 4.0, nullable=True, help="clamp each pixel into mean +- k standard errors of its "
               "mean (the variance floored by its neighbourhood's, in albedo units) and into the range of the samples "
               "around it (k; None: no clamp, the paper)", min=0.0),
        Option("threads", int, None, "worker threads (default: $MCRECON_THREADS, else the usable cores)", min=1),
    )
    requires = Requirements(samples=True, half_buffers=True, features="required")
    run_type = NFORRun
    #: The film's feature scales a tile standardises by (:meth:`for_tiles`); None: the image's own.
    _film_scales = None
    initial_spp = 4  # two samples in each half: a pixel's half needs one, its variance two in all
    pipeline = True  # uniform rounds: the plan reads only the sample count

    def _configure(self, params: dict) -> None:
        object.__setattr__(self, "_bandwidths", _parse_bandwidths(params["bandwidths"]))
        if params["stride"] > params["radius"] + 1:
            raise InputError(_WHERE, "stride", f"{params['stride']} leaves pixels outside every fitted window of "
                             f"radius {params['radius']}: use a stride of at most radius + 1 = {params['radius'] + 1}")

    def halo(self, width, height):
        # The reach of each stage, composed (a window of radius r with patches of radius f reads the
        # guide up to r + f away; a regression's result at q averages the fits of the windows centred
        # within r of q, each fitted on its whole window: 2r from the colour and features, 2r + f from
        # its guide):
        p = self.params
        r, f = p["radius"], p["patch"]
        # the prefiltered features: the other half's features as the guide of a (feature_radius,
        # feature_patch) NL-means
        pf = p["feature_radius"] + p["feature_patch"]
        # each half's candidates: the other half's colour as the guide, the prefiltered features
        first = max(2 * r + f, 2 * r + pf)
        # the MSE estimates: the candidates' squared errors (pointwise) NL-means filtered, guided by the
        # halves' mean (statistics: its own reach mse_radius + mse_patch)
        rm, fm = PAPER["mse_radius"], PAPER["mse_patch"]
        mse = max(first + rm, rm + fm)
        # the selection: the binary map of the estimates, filtered the same way (one bandwidth: none)
        sel = max(mse + rm, rm + fm) if len(self._bandwidths) == 2 else first
        image = sel
        if p["second_pass"]:
            # the averaged features filtered again, then one regression guided by the first pass's result
            final_feature = pf + PAPER["final_feature_radius"] + PAPER["final_feature_patch"]
            image = max(2 * r + f + sel, 2 * r + final_feature)
        # the clamp: the 3 x 3 sample range and pooled variance, the firefly rule's 8 neighbours (of the
        # statistics); the diagnostics: the selection map and the MSE estimate
        return int(max(image, mse, 1 if p["safeguard"] is not None else 0))

    def tile_grid(self) -> tuple[int, int]:
        """Rows and columns a grown tile's first pixel is a multiple of (:func:`~mcrecon.offline.tiles.tile_windows`).

        The NL-means and regression kernels work in bands of :data:`~mcrecon.filters.nlmeans.BAND` rows
        from the array's first row (a patch's running sums restart at each band, a pixel's collaborative
        sums add up band by band), and a stride fits windows on a grid from the array's first pixel: a
        tile anchored on the film's bands and grid makes every sum in the same order as the film's."""
        s = self.params["stride"]
        return BAND * s // math.gcd(BAND, s), s

    def for_tiles(self, inputs: MethodInputs, each_tile=None) -> "NFORMethod":
        """This method for the tiles of the film ``inputs`` (its half buffers with features): a copy that
        standardises every tile's features by the film's means and deviations
        (:func:`~mcrecon.methods.nfor.pipeline.film_feature_scales`), the one whole-image decision of the
        pipeline (the ridge's scale), made here once.  A film read band by band
        (:class:`~mcrecon.offline.tiles.FilmReader`) gives each feature component's planes through
        temporary files (``planes``): one pass over the samples more, a few planes of the film held."""
        p = self.params
        if isinstance(inputs, MethodInputs):
            components = feature_components(*inputs.halves)
        else:   # a film read a band at a time (mcrecon.offline.tiles.FilmReader): its planes assembled on disk
            components = inputs.planes(lambda sub: feature_components(*sub.halves))
        scales = film_feature_scales(components, feature_radius=p["feature_radius"],
                                     feature_patch=p["feature_patch"], feature_k=p["feature_k"],
                                     final_feature_radius=PAPER["final_feature_radius"],
                                     final_feature_patch=PAPER["final_feature_patch"],
                                     final_feature_k=PAPER["final_feature_k"], second_pass=p["second_pass"],
                                     threads=p["threads"])
        tiled = copy.copy(self)
        object.__setattr__(tiled, "_film_scales", scales)
        return tiled

    def reconstruct_run(self, run: NFORRun, inputs: MethodInputs) -> np.ndarray:
        """The NFOR image (H, W, C) float64 (:func:`mcrecon.methods.nfor.pipeline.nfor_denoise`) of ``inputs.halves``.

        The halves come split from the samples by the dispatcher, as a pair
        a renderer wrote, or from an adaptive run (:meth:`Method.run_inputs`);
        what the inputs cannot supply (no halves, no features, no sample) is
        refused before (:func:`mcrecon.methods.supply.check_supply`).
        """
        a, b = inputs.halves
        stats = inputs.stats if inputs.stats is not None else inputs.halves.merged()
        ya = _filled(a, b)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", McreconWarning)  # one warning for the empty pixels is enough
            yb = _filled(b, a)
        var = mean_variance_policy(stats)
        # the planes go in a list the pipeline empties (denoise_planes): none is held here past its stage
        planes = [ya, yb, var, *feature_planes(a, b, stats)]
        del ya, yb
        p = self.params
        diag: dict = {}
        img = denoise_planes(planes, bandwidths=self._bandwidths, radius=p["radius"], patch=p["patch"],
                             feature_radius=p["feature_radius"], feature_patch=p["feature_patch"],
                             feature_k=p["feature_k"], second_pass=p["second_pass"], ridge=p["ridge"],
                             threads=p["threads"], stride=p["stride"], diagnostics=diag,
                             min_weight=MIN_COVER_WEIGHT, feature_scales=self._film_scales,
                             **{k: PAPER[k] for k in _FIXED})
        img = np.asarray(img, dtype=np.float64)
        if p["safeguard"] is not None:
            img = np.ascontiguousarray(img)
            lo, hi = sample_range_bounds(stats)
            divisor = albedo_divisor(stats)
            with empty_pixels_kept(img, stats.count):  # no interval without a sample: the fill-in stands
                confidence_clamp(img, stats.mean, safeguard_variance(channel_floor(var, divisor), stats.count,
                                                                     divisor),
                                 p["safeguard"], lo, hi, out=img)
                # a brightness that rests on one sample no neighbour's sample confirms, kept where the
                # NL-means weights find no patch like it, is left out
                leave_out_isolated(img, stats, p["safeguard"])
        run.diagnostics = {"selection": diag["selection"], "estimated_mse": np.maximum(diag["estimated_mse"], 0.0),
                           "sample_density": stats.count.astype(np.float64)}
        return img
