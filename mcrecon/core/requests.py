"""What a method asks a renderer for and what it gets back.

:class:`SampleRequest` (counts per pixel and/or film positions), :class:`SampleBatch`
(positions and values of the samples, optional per-sample features) and
:func:`jittered_positions`.  The renderer protocol itself is
:mod:`mcrecon.renderers.protocol`.
"""

from __future__ import annotations

import dataclasses
from typing import Mapping

import numpy as np

from ..errors import RendererError
# SAMPLERS and check_sampler are re-exported: a request's renderer and a reply declare the sampler
from .samples import SAMPLERS, check_sampler, check_samples, lazy_njit  # noqa: F401

__all__ = ['SampleRequest', 'SampleBatch', 'validate_reply', 'validate_reply_counted', 'jittered_positions', 'place_in_pixels',
           'sample_indices', 'SAMPLERS', 'check_sampler']

@dataclasses.dataclass(frozen=True, eq=False)
class SampleRequest:
    """A request for more samples.

    Attributes
    ----------
    width, height : int
        Film size in pixels.
    counts : ndarray of int64, shape (H, W), or None
        Number of samples the renderer places inside each pixel.
    positions : ndarray of float64, shape (M, 2), or None
        Film positions to evaluate exactly (x = column, y = row).
    round_index : int
        The adaptive round this request belongs to (0 = initial pass).
    seed : int
        Seed for the renderer's random numbers in this round; the same
        request with the same seed must give the same samples.
    first_index : ndarray of int64, shape (H, W), or None
        Per pixel, the index of the first new sample in that pixel's own
        sample sequence: the samples of the run already committed there
        plus those in flight (requested in a round not committed yet).  A
        renderer with a low-discrepancy sampler continues each pixel's
        sequence from it, so rounds of 8 + 8 + 8 + 8 samples give the
        points of one 32-sample render.  The new samples of pixel p take
        the indices ``first_index[p] + 0, 1, ...``: its counted samples
        first, then its explicit positions in request order
        (:func:`sample_indices`).  None: nothing rendered before (all
        zeros).  A renderer may ignore it (independent samples).
    """

    width: int
    height: int
    counts: np.ndarray | None = None
    positions: np.ndarray | None = None
    round_index: int = 0
    seed: int = 0
    first_index: np.ndarray | None = None

    def __post_init__(self):
        if self.counts is None and self.positions is None:
            raise ValueError("SampleRequest needs counts, positions or both")
        if self.counts is not None:
            counts = np.asarray(self.counts)
            if counts.shape != (self.height, self.width):
                raise ValueError(
                    f"SampleRequest.counts has shape {counts.shape}, "
                    f"expected (height, width) = {(self.height, self.width)}")
            if counts.size and (not np.issubdtype(counts.dtype, np.integer) or counts.min() < 0):
                raise ValueError("SampleRequest.counts must be non-negative integers")
            object.__setattr__(self, "counts", counts.astype(np.int64, copy=False))
        if self.positions is not None:
            pos = np.asarray(self.positions, dtype=np.float64)
            if pos.ndim != 2 or pos.shape[1] != 2:
                raise ValueError(f"SampleRequest.positions has shape {pos.shape}, expected (M, 2)")
            if pos.size and (not np.isfinite(pos).all() or pos[:, 0].min() < 0
                             or pos[:, 1].min() < 0 or pos[:, 0].max() >= self.width
                             or pos[:, 1].max() >= self.height):
                raise ValueError("SampleRequest.positions must lie on the film "
                                 f"[0, {self.width}) x [0, {self.height})")
            object.__setattr__(self, "positions", pos)
        if self.first_index is not None:
            first = np.asarray(self.first_index)
            if first.shape != (self.height, self.width):
                raise ValueError(f"SampleRequest.first_index has shape {first.shape}, "
                                 f"expected (height, width) = {(self.height, self.width)}")
            if first.size and (not np.issubdtype(first.dtype, np.integer) or first.min() < 0):
                raise ValueError("SampleRequest.first_index must be non-negative integers")
            object.__setattr__(self, "first_index", first.astype(np.int64, copy=False))

    @property
    def n_from_counts(self) -> int:
        return 0 if self.counts is None else int(self.counts.sum())

    @property
    def n_from_positions(self) -> int:
        return 0 if self.positions is None else int(self.positions.shape[0])

    @property
    def total(self) -> int:
        """Number of samples the reply must contain."""
        return self.n_from_counts + self.n_from_positions


@dataclasses.dataclass(eq=False)
class SampleBatch:
    """Samples: film positions (N, 2) and values (N, C), plus named features.

    A renderer's reply lists the samples for ``request.counts`` first (in
    any order) and then one sample per requested position, in request
    order.
    """

    positions: np.ndarray
    values: np.ndarray
    features: Mapping[str, np.ndarray] = dataclasses.field(default_factory=dict)

    def __len__(self) -> int:
        return int(np.shape(self.positions)[0])


@lazy_njit(cache=True, nogil=True)
def _pixel_counts(pos, width, height):
    """Samples per pixel (H*W,) and the number of positions off the film, in one pass."""
    counts = np.zeros(width * height, np.int64)
    off = 0
    for k in range(pos.shape[0]):
        x = pos[k, 0]
        y = pos[k, 1]
        if x >= 0.0 and x < width and y >= 0.0 and y < height:
            counts[int(y) * width + int(x)] += 1
        else:
            off += 1
    return counts, off


@lazy_njit(cache=True, nogil=True)
def place_in_pixels(u, counts, width):
    """Shift uniform [0, 1)^2 numbers into their pixels, in row-major pixel order (in place)."""
    k = 0
    for p in range(counts.shape[0]):
        x0 = float(p % width)
        y0 = float(p // width)
        for _ in range(counts[p]):
            x = x0 + u[k, 0]
            y = y0 + u[k, 1]
            # x0 + u can round up to x0 + 1 for large films; keep it inside the pixel.
            u[k, 0] = x if x < x0 + 1.0 else np.nextafter(x0 + 1.0, 0.0)
            u[k, 1] = y if y < y0 + 1.0 else np.nextafter(y0 + 1.0, 0.0)
            k += 1
    return u


@lazy_njit(cache=True, nogil=True)
def _max_abs_diff(a, b):
    m = 0.0
    for k in range(a.shape[0]):
        for j in range(a.shape[1]):
            d = abs(a[k, j] - b[k, j])
            if d > m:  # positions were checked finite before
                m = d
    return m


def jittered_positions(counts: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Uniform random positions, ``counts[j, i]`` of them inside pixel (i, j).

    Pixels are visited in row-major order, so the result is sorted by pixel
    (which keeps later scatter loops cache friendly).
    """
    counts = np.ascontiguousarray(counts, dtype=np.int64)
    u = rng.random((int(counts.sum()), 2))
    return place_in_pixels(u, counts.ravel(), counts.shape[1])


@lazy_njit(cache=True, nogil=True)
def _indices(counts, first, pix):
    n_c = 0
    for p in range(counts.shape[0]):
        n_c += counts[p]
    out = np.empty(n_c + pix.shape[0], np.int64)
    nxt = first.copy()
    k = 0
    for p in range(counts.shape[0]):  # counted samples, row-major pixel order
        for _ in range(counts[p]):
            out[k] = nxt[p]
            nxt[p] += 1
            k += 1
    for m in range(pix.shape[0]):  # explicit positions, request order
        out[k] = nxt[pix[m]]
        nxt[pix[m]] += 1
        k += 1
    return out


def sample_indices(request: SampleRequest) -> np.ndarray:
    """Each reply row's index in its pixel's sample sequence, (N,) int64.

    Rows as a renderer that places counted samples pixel by pixel in
    row-major order lists them (as :func:`jittered_positions` does), then
    the explicit positions in request order: pixel p's counted samples
    take ``first_index[p] + 0 .. counts[p] - 1``, its explicit positions
    the indices after them, in request order.
    """
    w, h = request.width, request.height
    counts = (np.zeros(w * h, np.int64) if request.counts is None
              else np.ascontiguousarray(request.counts, np.int64).ravel())
    first = (np.zeros(w * h, np.int64) if request.first_index is None
             else np.ascontiguousarray(request.first_index, np.int64).ravel())
    if request.positions is None:
        pix = np.zeros(0, np.int64)
    else:
        pos = request.positions
        pix = np.ascontiguousarray(pos[:, 1].astype(np.int64) * w + pos[:, 0].astype(np.int64))
    return _indices(counts, first, pix)


def validate_reply(request: SampleRequest, batch, *, n_channels: int,
                   renderer: str = "renderer", position_tolerance: float = 1e-4) -> SampleBatch:
    """Check a renderer's reply against its request.

    Raises :class:`~mcrecon.errors.RendererError` naming the renderer,
    the field and what was expected when the reply has the wrong type,
    length, shape or dtype, non-finite positions, samples outside the
    requested pixels, or positions that differ from the requested ones.
    Non-finite *values* are allowed here; the sample log's ingestion
    policy (``nonfinite=``) decides what happens to them.
    """
    return validate_reply_counted(request, batch, n_channels=n_channels, renderer=renderer,
                                  position_tolerance=position_tolerance)[0]


def validate_reply_counted(request: SampleRequest, batch, *, n_channels: int, renderer: str = "renderer",
                           position_tolerance: float = 1e-4, keep_float32: bool = False,
                           warned: set | None = None):
    """:func:`validate_reply` and the number of rows with a NaN or Inf value, counted in the same
    pass over the reply (:func:`~mcrecon.core.samples.check_samples`).

    ``warned``: the warnings already given for this renderer (the driver keeps one set per run); the
    warning for zeroed feature entries is given once per renderer, not once per reply.

    ``keep_float32``: float32 positions of a reply without explicit positions stay float32 (the driver
    storing a log casts them to the log's dtype next: float32 -> float64 -> float32 is exact, so the
    round trip only cost two copies, 0.015 CPU s per million samples)."""
    if isinstance(batch, tuple) and len(batch) in (2, 3):
        batch = SampleBatch(*batch)
    if not isinstance(batch, SampleBatch):
        raise RendererError(renderer, "reply",
                            f"expected a SampleBatch or a (positions, values) tuple, got {type(batch).__name__}")
    try:
        pos = np.asarray(batch.positions)
        val = np.asarray(batch.values)
    except Exception as exc:  # ragged lists and the like
        raise RendererError(renderer, "reply", f"cannot convert to arrays: {exc}") from None
    n = request.total
    w, h = request.width, request.height
    # The shared sample checks (shapes, real dtypes, positions finite and on the film) ...
    pos, val, n_nonfinite = check_samples(pos, val, width=w, height=h, n_channels=n_channels, where=renderer,
                                          error=RendererError)
    # ... then what only a reply must satisfy: its request.
    if pos.shape[0] != n:
        raise RendererError(renderer, "reply length", f"{pos.shape[0]} samples, requested {n}")
    nc = request.n_from_counts
    if nc:
        got, off = _pixel_counts(pos[:nc], w, h)
        if off:
            raise RendererError(renderer, "positions",
                                f"{off} of the counted samples lie off the film [0, {w}) x [0, {h})")
        if not np.array_equal(got, request.counts.ravel()):
            bad = int(np.count_nonzero(got != request.counts.ravel()))
            raise RendererError(renderer, "positions",
                                f"per-pixel sample counts differ from the request in {bad} pixel(s): "
                                "samples must lie inside the requested pixels")
    if request.n_from_positions:
        tol = position_tolerance
        if pos.dtype == np.float32:
            # float32 cannot hold the requested float64 positions exactly: allow its rounding.
            tol = max(tol, 2.0 * float(np.spacing(np.float32(max(w, h)))))
        pp = np.ascontiguousarray(pos[nc:], np.float64)
        dev = _max_abs_diff(pp, request.positions)
        if not dev <= tol:
            raise RendererError(renderer, "positions",
                                f"differ from the requested positions by up to {dev:.3g} "
                                f"(tolerance {tol:.3g}); answer them in request order")
        pos = pos.astype(np.float64)  # a copy
        pos[nc:] = request.positions  # keep the exact requested positions
    elif not (keep_float32 and pos.dtype == np.float32):
        pos = pos.astype(np.float64, copy=False)
    feats = {}
    if batch.features:
        # the one validation path of features (mcrecon.core.features): (N,) or (N, k), a real numeric
        # dtype; NaN/Inf entries set to 0 and counted (a feature guides, it is not radiance)
        from .features import check_features, warn_feature_zeroed, within_feature_limit

        if not hasattr(batch.features, "items"):
            raise RendererError(renderer, "features", f"got {type(batch.features).__name__}, expected a mapping "
                                "name -> (N,) or (N, k) array")
        checked, n_fz = check_features(batch.features, n, where=renderer, error=RendererError)
        # as sent (shape (N,) or (N, k), dtype), unless an entry had to be set to 0 (NaN, Inf, a sentinel
        # beyond the limit: the log stores the zeroed copy, and the commit does not zero and warn again)
        feats = {}
        for name, arr in batch.features.items():
            given = np.asarray(arr)
            fixed = checked[str(name)]
            zeroed = n_fz and not within_feature_limit(np.asarray(given, dtype=fixed.dtype)).all()
            feats[str(name)] = (fixed[:, 0] if given.ndim == 1 else fixed) if zeroed else given
        if n_fz and (warned is None or "zeroed features" not in warned):
            warn_feature_zeroed(renderer, n_fz, stacklevel=3)
            if warned is not None:
                warned.add("zeroed features")
    return SampleBatch(pos, val, feats), int(n_nonfinite)
