"""Progressive rendering (Suykens and Willems 2000, Eq. 8, Fig. 3): kernel widths, the running image, round schedules.

Every sample is spread with an Epanechnikov footprint (:mod:`.kernels`)
whose width grows with how "bad" the sample is compared with the current
estimate of the image (Eq. 8: :func:`kernel_width`, and its numba twin
used by the splatter) and shrinks as the number of samples grows.  The
images are built progressively (Fig. 3, :class:`ProgressiveSplatter`):
only the first batch is needed twice (for the pilot estimate,
:func:`pilot_width`, and the first variable-width estimate); every later
round scales the running image down and splats its samples with the
previous image as the width reference.  Rounds double
(:func:`doubling_schedule`).

Energy per sample
    A sample of round j in pixel p carries ``F / n_pj`` (F its value,
    ``n_pj`` the samples of p in that round), which is Eq. 3's
    ``G / N`` for stratified sampling with N_j samples per pixel; rounds
    are combined with the weights ``N_j / N_total`` of Fig. 3's scale-down.

Samples are validated, and NaN/Inf values handled, by the one path of
:mod:`mcrecon.core.samples` (:func:`~mcrecon.core.samples.check_samples`,
:func:`~mcrecon.core.samples.apply_nonfinite`).
"""

from __future__ import annotations

import math
import warnings
from typing import Callable, Iterable

import numba
import numpy as np

from ...errors import InputError, McreconWarning
from ...core.features import check_features, usable_layout
from ...core.samples import apply_nonfinite, check_policy, check_samples, one_float_dtype
from .kernels import BOUNDARY_MODES, _BOUNDARY_CODE, _deposit_own_pixel, _scatter, _splat_guided_loop
from ...filters.luminance import LUMINANCE_WEIGHTS
from .consistent import (FeatureSums, _split_and_radii, channel_sums, edge_radius, feature_moments, gate_k,
                         pixel_moments, round_sums, width_coefs)
from .kernels import _add_widths, _splat_gated_loop
from .gated import GATE_SIDE, _splat_gated_runs
from .bands import in_bands, in_ranges, rows_sorted
from .outliers import _box_sum, _count_and_moments, _norm_of, _outlier_thresholds, _split_and_deposit, _split_outliers

__all__ = ['NORMS', 'kernel_width', 'pilot_width', 'sample_norm', 'ProgressiveSplatter']

#: Scalar "value" G of a sample (and f of a pixel) used by Eq. 8 for
#: colour: ``luminance`` = Rec. 709 luminance of the absolute channel values
#: (1 channel: its absolute value), ``mean`` = mean absolute channel value,
#: ``max`` = largest absolute channel value.  Absolute values: a negative
#: sample is as "bad" as a positive one of the same magnitude, and G = 0
#: only for an all-zero sample.
NORMS = ("luminance", "mean", "max")
#: Which samples are splatted: ``all`` (the paper: every sample, Eq. 8
#: widths) or ``outliers`` (robust variant: only the excess of samples above
#: their neighbourhood's threshold, everything else stays in its pixel) or ``consistent`` (the
#: default: as ``outliers``, and the rest spreads too, gated by the pixels' statistics:
#: :mod:`.consistent`).
SPREADS = ("all", "outliers", "consistent")
#: Footprint weights of the spread part: ``none`` (plain Epanechnikov) or
#: ``local_mean`` (Epanechnikov times the pooled 3x3 mean of G at each
#: covered pixel: energy goes where the neighbourhoods' samples are bright).
GUIDES = ("none", "local_mean")
#: ``spread="consistent"``: whether the gate also compares the per-sample features the samples carry
#: (``auto``: when there are any) or the colour statistics only (``none``).
FEATURE_GATES = ("auto", "none")


# ----------------------------------------------------------------------------
# Eq. 8 (vectorised reference forms; the numba loops below are the fast path)
# ----------------------------------------------------------------------------

def _kernel_arrays(pos, val, consistent: bool):
    """Positions and values, C-contiguous, in the one dtype the splat kernels take them in.

    The gated spread's kernels read float32 as it comes (widened exactly where they compute), so a pair
    that is float32 on both sides stays so (half the memory of a log's round); any other pair is float64
    on both sides (exact, :func:`~mcrecon.core.samples.one_float_dtype`), as the outlier-only rule's fused
    pass takes every pair.  One pair of dtypes, not every mix of them, is what numba compiles each kernel for.
    """
    if consistent:
        return one_float_dtype(np.ascontiguousarray(pos), np.ascontiguousarray(val))
    return np.ascontiguousarray(pos, dtype=np.float64), np.ascontiguousarray(val, dtype=np.float64)


def kernel_width(g, f, n, *, c: float = 4.0, alpha: float = 0.3, min_width: float = 1.0,
                 max_width: float = 32.0) -> np.ndarray:
    """Eq. 8: kernel diameter ``h = C N^-alpha (G / f)^(1/2)``, clamped to [min_width, max_width].

    Parameters
    ----------
    g : array_like
        Sample values G (any sign: the magnitude is used).
    f : array_like
        Reference estimate f at the samples' positions (magnitude used).
        ``f = 0`` (or non-finite) gives the maximum width: nothing is known
        there, so the sample is spread as far as allowed.
    n : array_like
        Samples per pixel N (>= 1).

    Returns
    -------
    ndarray of float64
        Diameters in pixels.  ``G = 0`` gives ``min_width`` (such samples
        carry no energy; :func:`splat` skips them).

    References
    ----------
    .. [1] Suykens and Willems 2000, Eq. 8 (after Abramson's square-root law, Eq. 5).
    """
    g = np.abs(np.asarray(g, dtype=np.float64))
    f = np.abs(np.asarray(f, dtype=np.float64))
    n = np.asarray(n, dtype=np.float64)
    ok = np.isfinite(f) & (f > 0)
    fs = np.where(ok, f, 1.0)
    # sqrt(g)/sqrt(f) rather than sqrt(g/f): no overflow for f ~ 1e-300.
    h = np.where(ok, c * n ** (-alpha) * np.sqrt(g) / np.sqrt(fs), np.inf)
    return np.clip(h, min_width, max_width)


def pilot_width(n, *, c_prime: float = 8.0, min_width: float = 1.0, max_width: float = 32.0) -> np.ndarray:
    """Fig. 3's pilot: fixed diameter ``h' = C' N0^(-1/2)``, clamped to [min_width, max_width]."""
    n = np.asarray(n, dtype=np.float64)
    return np.clip(c_prime * n ** -0.5, min_width, max_width)


def sample_norm(values, norm: str = "luminance") -> np.ndarray:
    """The scalar G of samples (N, C) or pixels (H, W, C) under ``norm`` (see :data:`NORMS`)."""
    v = np.abs(np.asarray(values, dtype=np.float64))
    c = v.shape[-1]
    if norm == "luminance":
        if c == 1:
            return v[..., 0]
        if c != 3:
            raise InputError("method splat", "norm", f"'luminance' needs 1 or 3 (R, G, B) channels, "
                             f"got {c}; use norm='mean' or 'max'")
        return v @ LUMINANCE_WEIGHTS
    if norm == "mean":
        return v.mean(axis=-1)
    if norm == "max":
        return v.max(axis=-1)
    raise InputError("method splat", "norm", f"{norm!r}; valid: {', '.join(NORMS)}")


@numba.njit(cache=True, nogil=True)
def _radii(pos, val, norm_code, weights, ref, nmap, pilot, c, alpha, c_prime, min_w, max_w, out):
    """Support radius (= diameter / 2) of every sample; -1 for G = 0 samples.

    pilot: fixed diameter C' N^-1/2; else Eq. 8 with ``ref`` (|f| of the
    sample's pixel under the same norm) and ``nmap`` (N of the sample's pixel).
    Returns the number of samples whose width hit ``max_w`` (capped).
    """
    h = nmap.shape[0]
    w = nmap.shape[1]
    n_capped = 0
    for k in range(pos.shape[0]):
        g = _norm_of(val, k, norm_code, weights)
        if g == 0.0:
            out[k] = -1.0
            continue
        px = min(max(int(math.floor(pos[k, 0])), 0), w - 1)
        py = min(max(int(math.floor(pos[k, 1])), 0), h - 1)
        n = nmap[py, px]
        if pilot:
            d = c_prime / math.sqrt(n)
        else:
            f = ref[py, px]
            if f > 0.0 and f < np.inf:
                d = c * n ** (-alpha) * (math.sqrt(g) / math.sqrt(f))
            else:
                d = np.inf  # nothing known here: spread as far as allowed
        if d >= max_w:
            if d > max_w:
                n_capped += 1
            d = max_w
        if d < min_w:
            d = min_w
        out[k] = 0.5 * d
    return n_capped


# ----------------------------------------------------------------------------
# The progressive algorithm (Fig. 3)
# ----------------------------------------------------------------------------

class ProgressiveSplatter:
    """Fig. 3 of Suykens and Willems (2000): the running image and its update rounds.

    Parameters
    ----------
    width, height, n_channels : int
        Film size and channels.
    c, alpha, c_prime, min_width, max_width, boundary, norm
        See :class:`SplatMethod`.
    spread, outlier_k, guide
        See :class:`SplatMethod`.  The defaults here (``spread="all"``,
        ``guide="none"``, ``c=4``) are the paper's Fig. 3; the method's
        default variant passes the robust ones.

    Attributes
    ----------
    image : ndarray (H, W, C) float64
        The current estimate f_j (after the last round).
    pilot : ndarray or None
        f'_0, the fixed-width pilot estimate of the first round.
    spp_total : float
        N_total in samples per pixel (mean over the film).
    cum_counts : ndarray (H, W) int64
        Samples per pixel over all rounds (the N of Eq. 8 per pixel).
    rounds : list of dict
        Per round: spp, samples, capped (width hit max_width), fallback
        (no centre covered), empty_pixels; with ``spread="outliers"`` also
        outliers (samples whose excess was spread).
    n_nonfinite : int
        Samples with a NaN or Inf value met so far (dropped or set to 0
        under the ``nonfinite`` policy), each counted once.

    Notes
    -----
    Rounds are added with :meth:`add_round` (samples in memory) or
    :meth:`add_round_stream` (two passes over re-iterable chunks: counts,
    then splats).  Adding the same rounds in the same order gives the
    same image bit for bit, whatever the number of threads (the paper's
    scatter is sequential, or two fixed blocks summed in order; the
    default's passes run in bands of rows that give one thread's bits:
    :mod:`.bands`).  Every
    chunk is checked by :func:`mcrecon.core.samples.check_samples` and its
    NaN/Inf values handled by :func:`mcrecon.core.samples.apply_nonfinite`
    under ``nonfinite``, without a warning here: callers report
    :attr:`n_nonfinite` (:meth:`SplatMethod.reconstruct_run` warns).
    """

    #: Robust variant: half-size of the window whose samples set a pixel's outlier threshold (3 x 3).
    POOL_RADIUS = 1
    #: Robust variant: fewest samples in a pixel's window for its outlier test (fewer: nothing is
    #: spread).  mean + k std of a rare-event pool means nothing until it holds a few events: with
    #: 32 (4 spp in 3x3), the caustic at 64^2, 4 spp lost to box by up to 14 % (one seed of three).
    MIN_POOL = 64

    def __init__(self, width: int, height: int, n_channels: int, *, c: float = 4.0, alpha: float = 0.3,
                 c_prime: float = 8.0, min_width: float = 1.0, max_width: float = 32.0,
                 boundary: str = "mirror", norm: str = "luminance", spread: str = "all",
                 outlier_k: float = 2.0, guide: str = "none", false_rejection: float = 0.05,
                 spread_c: float = 8.0, spread_alpha: float = 0.3, feature_gate: str = "auto"):
        self.width, self.height, self.n_channels = int(width), int(height), int(n_channels)
        if spread not in SPREADS:
            raise InputError("method splat", "spread", f"{spread!r}; valid: {', '.join(SPREADS)}")
        if guide not in GUIDES:
            raise InputError("method splat", "guide", f"{guide!r}; valid: {', '.join(GUIDES)}")
        self.spread, self.outlier_k, self.guide = spread, float(outlier_k), guide
        if not 0.0 < false_rejection < 1.0:
            raise InputError("method splat", "false_rejection", f"{false_rejection!r}, expected 0 < rate < 1")
        self.false_rejection = float(false_rejection)
        self.spread_c, self.spread_alpha = float(spread_c), float(spread_alpha)
        if feature_gate not in FEATURE_GATES:
            raise InputError("method splat", "feature_gate", f"{feature_gate!r}; valid: {', '.join(FEATURE_GATES)}")
        self.feature_gate = feature_gate
        self._gate_k = gate_k(self.false_rejection, self.n_channels)
        self.c, self.alpha, self.c_prime = float(c), float(alpha), float(c_prime)
        self.min_width, self.max_width = float(min_width), float(max_width)
        if boundary not in _BOUNDARY_CODE:
            raise InputError("method splat", "boundary", f"{boundary!r}; valid: {', '.join(BOUNDARY_MODES)}")
        self.boundary = boundary
        self.norm = norm
        if norm == "luminance":
            if self.n_channels == 1:
                weights = np.ones(1)
            elif self.n_channels == 3:
                weights = LUMINANCE_WEIGHTS.copy()
            else:
                raise InputError("method splat", "norm", f"'luminance' needs 1 or 3 (R, G, B) channels, got "
                                 f"{self.n_channels}; use norm='mean' or 'max'")
            self._norm_code = 0
        elif norm == "mean":
            weights = np.full(self.n_channels, 1.0 / self.n_channels)
            self._norm_code = 0
        elif norm == "max":
            weights = np.ones(self.n_channels)
            self._norm_code = 1
        else:
            raise InputError("method splat", "norm", f"{norm!r}; valid: {', '.join(NORMS)}")
        self._weights = weights
        self.image = np.zeros((self.height, self.width, self.n_channels))
        self.pilot = None
        self.spp_total = 0.0
        self.cum_counts = np.zeros((self.height, self.width), np.int64)
        self.rounds: list[dict] = []
        self.n_nonfinite = 0
        self.n_feature_zeroed = 0  # samples whose NaN, Inf or sentinel feature entries were set to 0
        self.last_widths = np.zeros((self.height, self.width))
        # robust variant: cumulative per-pixel sums of G and G^2
        self._s1 = np.zeros((self.height, self.width))
        self._s2 = np.zeros((self.height, self.width))
        # spread="consistent": cumulative per-pixel, per-channel sums of the values and their squares
        self._cs1 = np.zeros((self.height, self.width, self.n_channels))
        self._cs2 = np.zeros((self.height, self.width, self.n_channels))
        # ... and of every feature component the samples carry (the gate's feature test), if any
        self._fsum = FeatureSums(self.width, self.height) \
            if spread == "consistent" and feature_gate == "auto" else None

    # ------------------------------------------------------------ helpers
    def _pixel_of(self, pos) -> tuple[np.ndarray, np.ndarray]:
        """(row, column) of each sample's pixel, positions on the border clipped to the film."""
        return (np.clip(np.floor(pos[:, 1]).astype(np.int64), 0, self.height - 1),
                np.clip(np.floor(pos[:, 0]).astype(np.int64), 0, self.width - 1))

    def _pixel_counts(self, pos) -> np.ndarray:
        w, h = self.width, self.height
        iy, ix = self._pixel_of(pos)
        return np.bincount(iy * w + ix, minlength=w * h).reshape(h, w)

    def _validated(self, positions, values, nonfinite, where):
        """A chunk checked (shapes, positions on the film) and its NaN/Inf values handled under ``nonfinite``.

        Returns ``(positions, values, n_nonfinite)``, contiguous, in the
        precision given (see :func:`~mcrecon.core.samples.check_samples`).
        """
        pos, val, n_bad = check_samples(positions, values, width=self.width, height=self.height,
                                        n_channels=self.n_channels, where=where)
        pos, val = apply_nonfinite(pos, val, n_bad, nonfinite, where=where)
        return pos, val, n_bad

    def _ref_norm(self, img) -> np.ndarray:
        """|f| of every pixel under the norm (the reference of Eq. 8)."""
        return np.ascontiguousarray(sample_norm(img, self.norm))

    def _radii(self, pos, val, ref, pilot) -> tuple[np.ndarray, int]:
        out = np.empty(pos.shape[0])
        nmap = np.maximum(self.cum_counts, 1).astype(np.float64)
        capped = _radii(pos, val, self._norm_code, self._weights, ref, nmap, pilot, self.c, self.alpha,
                        self.c_prime, self.min_width, self.max_width, out)
        return out, int(capped)

    def _deposit(self, pos, val, scale, radius, out) -> int:
        return _scatter(pos, val, scale, radius, _BOUNDARY_CODE[self.boundary], out)

    def _record_widths(self, pos, radius):
        """Mean kernel diameter of the samples of each pixel (diagnostic), 0 where none splatted."""
        keep = radius > 0
        w, h = self.width, self.height
        iy, ix = self._pixel_of(pos[keep])
        idx = iy * w + ix
        s = np.bincount(idx, weights=2.0 * radius[keep], minlength=w * h)
        n = np.bincount(idx, minlength=w * h)
        self._width_sum += s
        self._width_n += n

    # ------------------------------------------------------------- rounds
    def add_round(self, positions, values, *, features=None, nonfinite: str = "drop", where: str = "samples",
                  checked: bool = False) -> None:
        """Add one round held in memory (Fig. 3: the first round, or one loop iteration).

        The robust variant takes it in two fused passes (counts and G moments,
        then split, own-pixel deposit and widths) with the outlier thresholds
        computed once per pixel: the image, widths and round records are bit
        for bit those of :meth:`add_round_stream` on the same arrays (tested),
        at a fraction of the cost.  ``checked=True``: the arrays were already
        checked by :func:`~mcrecon.core.samples.check_samples` and hold no NaN/Inf
        value (the adaptive driver's committed rounds, after its policy):
        they are not checked again.  ``features`` (``{name: (N, k)}``, rows of the samples, as
        :func:`mcrecon.core.features.check_features` returns them): read by the default's gate
        (``spread="consistent"``), ignored otherwise.
        """
        if self.spread == "all" or (self.spread == "consistent" and not checked):
            # the paper's rounds, and a gated round not yet checked (its features follow the rows that
            # the NaN/Inf policy keeps), go through the streamed path
            item = (positions, values, features) if features else (positions, values)
            self.add_round_stream(lambda: iter([item]), nonfinite=nonfinite, where=where)
            return
        check_policy(nonfinite, where)
        if checked:
            pos, val = positions, values
        else:
            pos, val, n_bad = self._validated(positions, values, nonfinite, where)
            self.n_nonfinite += n_bad
        pos, val = _kernel_arrays(pos, val, self.spread == "consistent")
        srt = rows_sorted(pos, self.height)
        if self.spread == "consistent":  # the passes of add_round_stream in one, on the arrays as given
            counts, s1, s2, c1, c2 = round_sums(pos, val, self.width, self.height, self._norm_code, self._weights,
                                                self._fsum, features or {}, where, srt)
            self._cs1 += c1
            self._cs2 += c2
        else:
            counts = np.zeros((self.height, self.width), np.int64)
            s1 = np.zeros((self.height, self.width))
            s2 = np.zeros((self.height, self.width))
            in_bands(_count_and_moments, (pos, val, self._norm_code, self._weights, counts, s1, s2), pos,
                     self.height, sorted_rows=srt)
        if int(counts.sum()) == 0:
            return
        self._add_round_robust(None, counts, s1, s2, self.spp_total == 0.0, nonfinite, where, arrays=(pos, val, srt))

    def add_round_stream(self, chunks: Callable[[], Iterable], *, nonfinite: str = "drop",
                         where: str = "samples") -> None:
        """Add one round given as re-iterable chunks: ``chunks()`` yields (positions, values) or
        (positions, values, features), features ``{name: (N, k)}`` or None (read by the default's gate).

        The paper's first round is materialised (Fig. 3 stores the first
        batch: it is splatted twice); every other round (and every round of
        the robust variant) is streamed twice (counts and G moments per
        pixel, then the splat), so memory stays bounded by the image.
        """
        check_policy(nonfinite, where)
        first = self.spp_total == 0.0
        robust = self.spread != "all"
        s1 = np.zeros((self.height, self.width))
        s2 = np.zeros((self.height, self.width))
        if first and not robust:
            # Fig. 3 stores the first batch: it is splatted twice (pilot, then Eq. 8)
            parts = []
            for p, v, *_ in chunks():
                p, v, n_bad = self._validated(p, v, nonfinite, where)
                self.n_nonfinite += n_bad
                parts.append(_kernel_arrays(p, v, False))
            if parts:
                pos = np.ascontiguousarray(np.concatenate([p for p, _ in parts]))
                val = np.ascontiguousarray(np.concatenate([v for _, v in parts]))
            else:
                pos, val = np.zeros((0, 2)), np.zeros((0, self.n_channels))
            counts = self._pixel_counts(pos)
        else:
            counts = np.zeros((self.height, self.width), np.int64)
            for p, v, *f in chunks():  # first pass: counts per pixel (and the one count of NaN/Inf samples)
                feats = f[0] if f else None
                if feats and self._fsum is not None and nonfinite == "drop":
                    keep = np.isfinite(np.asarray(v)).all(axis=1)  # the rows apply_nonfinite keeps
                    feats = feats if keep.all() else {k: np.asarray(a)[keep] for k, a in feats.items()}
                p, v, n_bad = self._validated(p, v, nonfinite, where)
                self.n_nonfinite += n_bad
                srt = rows_sorted(p, self.height) if robust else False
                if self._fsum is not None:  # every round carries the same features, or none
                    # as read from a file or given: through the one feature check (native floats, NaN, Inf
                    # and "no hit" sentinels zeroed); what a method cannot use (an (N, 2, 2) array) is left
                    # out, as the other methods leave it
                    feats = {k: feats[k] for k in usable_layout(feats)} if feats else {}
                    feats, n_fz = check_features(feats, p.shape[0], where=where)
                    self.n_feature_zeroed += n_fz
                    self._fsum.add(p, feats, where, srt)
                if robust:  # ... and the sums of G, G^2 per pixel
                    # G widens each value exactly (outliers._norm_of): a float32 round is read as it comes
                    args = one_float_dtype(p, v) + (self._norm_code, self._weights, counts, s1, s2)
                    in_bands(_count_and_moments, args, p, self.height, sorted_rows=srt)
                    if self.spread == "consistent":  # ... and of every channel's values and squares
                        c1, c2 = channel_sums(p, v, self.width, self.height, srt)
                        self._cs1 += c1
                        self._cs2 += c2
                else:
                    counts += self._pixel_counts(p)
        n_round = int(counts.sum())
        if n_round == 0:
            return
        if robust:
            self._add_round_robust(chunks, counts, s1, s2, first, nonfinite, where)
            return
        p_film = self.width * self.height
        n_j = n_round / p_film  # N_j: mean samples per pixel of this round
        self.cum_counts += counts
        # Energy per sample: F / n_pj, so that the round's image is the splat
        # of its pixel means (Eq. 3 with G / N for stratified sampling).
        inv_counts = np.where(counts > 0, 1.0 / np.maximum(counts, 1), 0.0)
        empty = counts == 0
        self._width_sum = np.zeros(p_film)
        self._width_n = np.zeros(p_film, np.int64)
        capped = fallback = 0
        if first:
            # f'_0: fixed-width density estimate of the stored first batch (C' N0^-1/2) ...
            scale = inv_counts[self._pixel_of(pos)]
            rad, _ = self._radii(pos, val, np.zeros((self.height, self.width)), True)
            pilot = np.zeros_like(self.image)
            self._deposit(pos, val, scale, rad, pilot)
            self.pilot = pilot
            # ... then f_0: Eq. 8 widths with f'_0 as the reference, same samples.
            rad, capped = self._radii(pos, val, self._ref_norm(pilot), False)
            img = np.zeros_like(self.image)
            fallback = self._deposit(pos, val, scale, rad, img)
            self._record_widths(pos, rad)
            self.image = img
            self.spp_total = n_j
        else:
            ref_img = self.image  # f_{j-1}: the reference for this round's widths
            ref = self._ref_norm(ref_img)
            total = self.spp_total + n_j
            # Scale down: f_j = (N_total - N_j) / N_total * f_{j-1}
            img = ref_img * (self.spp_total / total)
            w_round = n_j / total
            for p, v, *_ in chunks():  # second pass: the splat
                p, v = _kernel_arrays(*self._validated(p, v, nonfinite, where)[:2], False)
                scale = w_round * inv_counts[self._pixel_of(p)]
                rad, cap = self._radii(p, v, ref, False)
                capped += cap
                fallback += self._deposit(p, v, scale, rad, img)
                self._record_widths(p, rad)
            if empty.any():
                # A pixel this round did not sample keeps its previous estimate
                # for the round's share (not energy from samples: documented).
                img[empty] += w_round * ref_img[empty]
            self.image = img
            self.spp_total = total
        self._finish_round(n_j, n_round, capped, fallback, empty, first, where)

    def _finish_round(self, n_j, n_round, capped, fallback, empty, first, where, **extra):
        """Record the round: the mean kernel diameter per pixel, the round's counts, a warning for unsampled pixels."""
        with np.errstate(invalid="ignore", divide="ignore"):
            self.last_widths = np.where(self._width_n > 0, self._width_sum / np.maximum(self._width_n, 1),
                                        0.0).reshape(self.height, self.width)
        n_empty = int(empty.sum())
        self.rounds.append({"spp": n_j, "samples": n_round, "capped": capped, "fallback": fallback,
                            "empty_pixels": n_empty, **extra})
        if n_empty:
            warnings.warn(f"{where}: splat round {len(self.rounds) - 1}: {n_empty} pixel(s) without samples in "
                          "this round" + (" keep their previous estimate for its share (Eq. 3 assumes every "
                                          "round samples every pixel)" if not first else
                                          " get only their neighbours' splats in the first round"),
                          McreconWarning, stacklevel=4)

    # ------------------------------------------------------- robust variant
    def window_stats(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Robust variant: per pixel the count, sum of G and sum of G^2 of the samples so far in the
        (2r+1)^2 window around it (r = :attr:`POOL_RADIUS`, clipped to the film), and their mean G.

        Pooling a few neighbours gives the outlier test (:func:`_split_outliers`)
        enough samples at a few spp; the mean is the reference of the excess
        width and the guide of its footprint.
        """
        r = self.POOL_RADIUS
        n = _box_sum(self.cum_counts.astype(np.float64), r)
        s1 = _box_sum(self._s1, r)
        s2 = _box_sum(self._s2, r)
        mean = np.where(n > 0, s1 / np.maximum(n, 1), 0.0)
        return n, s1, s2, np.ascontiguousarray(mean)

    def _add_round_robust(self, chunks, counts, s1, s2, first, nonfinite, where, arrays=None):
        """One round of the robust variant (``docs/methods/splat.md``, "Default vs paper").

        Every sample stays in its pixel (the one-pixel footprint, i.e. the
        pixel mean) except the *excess* of outliers above their
        neighbourhood's threshold (:func:`_split_outliers`), which is splatted
        with Eq. 8's width (``G - tau`` against the pooled mean) and, with
        ``guide="local_mean"``, Epanechnikov weights times the pooled mean
        of G at each covered pixel (:func:`.kernels._splat_guided_loop`):
        the excess goes where the neighbourhood's samples say the image is
        bright, never into pixels whose 3x3 window saw only zeros.  Energy:
        each sample deposits ``(1 - frac) + frac`` of ``F / n_pj`` times the
        round weight, as in the paper's path (Fig. 3's scale-down included).
        """
        p_film = self.width * self.height
        n_round = int(counts.sum())
        n_j = n_round / p_film
        self.cum_counts += counts
        self._s1 += s1
        self._s2 += s2
        inv_counts = np.where(counts > 0, 1.0 / np.maximum(counts, 1), 0.0)
        empty = counts == 0
        wn, ws1, ws2, fref = self.window_stats()
        nmap = np.maximum(self.cum_counts, 1).astype(np.float64)
        # guide of the excess: the window mean of G (local_mean), or 1.  (Measured and rejected: the
        # window mean without the sample itself, which concentrates a spike's excess on the
        # neighbourhoods of other spikes: caustic at 64^2, 8 spp, up to 5.7x box.)
        guide = fref if self.guide == "local_mean" else np.ones((self.height, self.width))
        prev = self.image
        if first:
            total, w_round = n_j, 1.0
            img = np.zeros_like(self.image)
        else:
            total = self.spp_total + n_j
            w_round = n_j / total
            img = prev * (self.spp_total / total)
        self._width_sum = np.zeros(p_film)
        self._width_n = np.zeros(p_film, np.int64)
        mode = _BOUNDARY_CODE[self.boundary]
        outliers = capped = fallback = 0
        tau = np.empty((self.height, self.width))
        consistent = self.spread == "consistent"
        # consistent: a sample is spread only once the outlier test judged it, so the test must run
        # wherever it can, also at the film border (over the full windows there)
        _outlier_thresholds(wn, ws1, ws2, self.POOL_RADIUS, self.outlier_k, float(self.MIN_POOL), tau, consistent)
        if consistent:  # the gate's pixel statistics and the gradient bound, all samples so far
            row_work = counts.sum(axis=1)  # the gated splat's bands of rows: about equal samples each
            gstats = pixel_moments(self.cum_counts, self._cs1, self._cs2)
            r_edge = edge_radius(gstats, self._gate_k)
            fstats = feature_moments(self._fsum)  # (1, 1, 0, 2) without features: the gate tests none
            # Eq. 8's per-pixel factors of the outliers' and the consistent samples' widths, once per pixel
            coef, sqrt_f = width_coefs(fref, nmap, self.c, self.alpha)
            spread_coef, _ = width_coefs(fref, nmap, self.spread_c, self.spread_alpha)
        if arrays is not None and not consistent:  # a round in memory (add_round): the fused pass
            p, v, _ = arrays
            idx = np.empty(p.shape[0], np.int64)
            oscale = np.empty(p.shape[0])
            orad = np.empty(p.shape[0])
            outliers, capped = _split_and_deposit(p, v, self._norm_code, self._weights, tau, fref, nmap, self.c,
                                                  self.alpha, self.min_width, self.max_width, w_round, inv_counts,
                                                  img, self._width_sum, self._width_n, idx, oscale, orad)
            if outliers:
                idx = idx[:outliers]
                fallback = _splat_guided_loop(np.ascontiguousarray(p[idx]), np.ascontiguousarray(v[idx]),
                                              oscale[:outliers], orad[:outliers], guide, mode, img)
        if arrays is None:  # (positions, values, whether their rows are sorted: not known yet)
            rounds = ((*self._validated(p, v, nonfinite, where)[:2], None) for p, v, *_ in chunks())
        else:  # a round in memory, checked and converted once (add_round); the outlier-only rule is done above
            rounds = [arrays] if consistent else []
        w2 = self._width_sum.reshape(self.height, self.width)
        n2 = self._width_n.reshape(self.height, self.width)
        gate_memo = None
        for p, v, srt in rounds:  # second pass: split and deposit
            p, v = _kernel_arrays(p, v, consistent)
            if srt is None:
                srt = rows_sorted(p, self.height)
            frac = np.empty(p.shape[0])
            rad = np.empty(p.shape[0])
            krad = np.empty(p.shape[0]) if consistent else rad
            if consistent:  # the split and the consistent samples' radii in one pass
                split = in_ranges(_split_and_radii, (p, v, self._norm_code, self._weights, tau, coef, spread_coef,
                                                     sqrt_f, self.min_width, self.max_width, r_edge, frac, rad,
                                                     krad), p.shape[0])
            else:
                split = in_ranges(_split_outliers, (p, v, self._norm_code, self._weights, tau, fref, nmap, self.c,
                                                    self.alpha, self.min_width, self.max_width, frac, rad), p.shape[0])
            for n_out, n_cap in split:
                outliers += n_out
                capped += n_cap
            # the kernel diameters of the samples: a chunk's sums are added as a whole, as a round's were
            # (the same sums)
            cw, cn = (np.zeros_like(w2), np.zeros_like(n2)) if arrays is None else (w2, n2)
            widths = True  # still to add (the gated runs add them in their pass)
            if consistent:
                # in bands of rows of about equal samples, one per thread; a sample near a band's edge
                # costs both threads its footprint (reach: a radius is at most max_width / 2)
                if mode == 1:  # renormalise: each footprint clipped to the film, a sum per sample
                    gated, tail = _splat_gated_loop, ()
                else:  # the gate's answers, kept for the round (its statistics hold for the round)
                    if gate_memo is None:
                        gate_memo = np.zeros((p_film, GATE_SIDE * GATE_SIDE), np.int8)
                    gated, tail = _splat_gated_runs, (gate_memo, rad, 0.5 * self.min_width, cw, cn)
                    widths = False
                fallback += sum(in_bands(gated, (p, v, w_round, inv_counts, frac, krad, r_edge, gstats,
                                                 fstats, self._gate_k ** 2, mode, img) + tail,
                                         p, self.height, row_work=row_work, sorted_rows=srt,
                                         reach=int(math.ceil(0.5 * self.max_width)) + 1))
            else:
                _deposit_own_pixel(p, v, w_round * inv_counts[self._pixel_of(p)] * (1.0 - frac), img)
            sel = np.flatnonzero(rad > 0)
            if sel.size:
                ps = np.ascontiguousarray(p[sel])
                fallback += _splat_guided_loop(ps.astype(np.float64, copy=False),
                                               np.ascontiguousarray(v[sel], dtype=np.float64),
                                               w_round * inv_counts[self._pixel_of(ps)] * frac[sel],
                                               np.ascontiguousarray(rad[sel]), guide, mode, img)
            if widths:
                in_bands(_add_widths, (p, rad, krad, 0.5 * self.min_width, cw, cn), p, self.height, sorted_rows=srt)
            if arrays is None:
                w2 += cw
                n2 += cn
        if empty.any() and not first:
            img[empty] += w_round * prev[empty]
        self.image = img
        self.spp_total = total
        self._finish_round(n_j, n_round, capped, int(fallback), empty, first, where, outliers=outliers)
