"""Samples cleaned before any filter: fireflies found among the samples, their energy moved, not lost.

A firefly is a *rare* bright sample: far brighter than the samples around
it, with too few like it nearby for any filter to average it out.  A
filter given the raw pixel means either keeps it (a bright dot) or smears
it into a blob; a denoiser trained on clean renders (OIDN) does both.
:func:`clean_samples` finds them from the individual samples and hands
every filter the same samples with the rare bright parts moved:

* **Which samples**: the luminance cascades of
  :func:`mcrecon.filters.fireflies.split_fireflies` (Zirr, Hanika and
  Dachsbacher 2018): a sample is an outlier where its luminance lies above
  the highest level that its pixel's 3 x 3 neighbourhood holds densely
  (at least ``min(k_min, frac * n)`` samples above it).  A small
  highlight that many samples see is dense there and stays; a lone bright
  sample among dim ones is not.
* **Where its energy goes**: its part above the threshold is spread with
  a density-adaptive kernel over the pixels that saw samples that bright
  (and their neighbours), only pixels that hold a sample.  Each pixel's
  share is added to every one of its samples, so the cleaned samples'
  pixel means are the base's plus the spread excess, and their sum over
  the image is the raw pixel means' sum to round-off.
* **Halves**: each half is cleaned on its own samples
  (:meth:`CleanedSamples.halves`), dealt as
  :func:`mcrecon.core.halves.split_halves` deals the raw ones: a firefly of
  half A moves within half A, so the halves stay independent (the
  dual-buffer error estimates of nfor and auto rely on it) and each keeps
  its own energy.  Cleaning all the samples together would add a half-A
  firefly's energy to half B's samples.

Nothing is clipped: the base keeps every sample below the threshold as it
is, and nothing moves where the samples hold no firefly (the cleaned
samples are then the input's, bit for bit).  Non-finite samples get the
``nonfinite`` policy first.  Every sample is held in memory (positions,
values and features).

References
----------
.. [1] T. Zirr, J. Hanika and C. Dachsbacher, "Re-weighting firefly
   samples for improved finite-sample Monte Carlo estimates", Computer
   Graphics Forum 37(6), 2018.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..errors import InputError
from ..filters.fireflies import split_fireflies
from .features import source_name
from .samples import SampleSet, apply_nonfinite, check_policy

__all__ = ["CleanedSamples", "clean_samples"]

_WHERE = "cleaning"


@dataclasses.dataclass(eq=False)
class CleanedSamples:
    """Samples with their fireflies' energy moved (:func:`clean_samples`).

    Attributes
    ----------
    samples : SampleSet
        The cleaned samples: the input's positions, order and features;
        each value its base part plus its pixel's share of the moved
        energy.  Any method reads it as it reads the raw samples.
    mean : ndarray (H, W, C) float64
        The cleaned per-pixel estimate: the pixel means of ``samples``
        (0 in pixels without a sample).
    raw_mean : ndarray (H, W, C) float64
        The pixel means of the input samples (after the ``nonfinite`` policy).
    count : ndarray (H, W) int64
        Samples per pixel.
    outliers : ndarray (N,) bool
        The samples a part of which moved (luminance above their pixel's
        threshold), in the order of ``samples``.
    excess : ndarray (H, W, C) float64
        The moved energy where it landed, as a contribution to the pixel means.
    threshold : ndarray (H, W) float64
        Luminance above which a pixel's samples lose their part (``inf``:
        none moves).
    moved_fraction : float
        Share of the samples' luminance (per pixel mean) that moved.
    """

    samples: SampleSet
    mean: np.ndarray
    raw_mean: np.ndarray
    count: np.ndarray
    outliers: np.ndarray
    excess: np.ndarray
    threshold: np.ndarray
    moved_fraction: float

    #: The options of the cleaning (``k_min``, ``neighbour_weight``, ``frac``, ``max_radius``), for :meth:`halves`.
    options: dict = dataclasses.field(default_factory=dict)
    #: The input samples after the ``nonfinite`` policy (values), for :meth:`halves`.
    raw_values: np.ndarray | None = None

    def halves(self, *, features=()):
        """Two independent cleaned halves (:class:`~mcrecon.core.halves.Halves`), each cleaned on its own.

        The samples are dealt into halves as
        :func:`mcrecon.core.halves.split_halves` deals the raw ones
        (:func:`~mcrecon.core.halves.split_labels`, in stream order); each
        half's samples are cleaned with this cleaning's options, so its
        energy stays in it and no firefly of one half reaches the other.
        ``features``: names of the samples' features to keep, or ``"all"``.
        """
        from .halves import split_halves, split_labels
        src = self.samples
        w, h = src.width, src.height
        labels = split_labels(src.positions, w, h, np.zeros(w * h, np.int64))
        values = self.raw_values.copy()
        for half in (0, 1):
            sel = labels == half
            if sel.any():
                values[sel] = _cleaned_values(src.positions[sel], self.raw_values[sel], w, h, self.options)[0]
        halves = SampleSet(src.positions, values, width=w, height=h, channels=src.channels,
                           features=src.features or None, name=src.name)
        return split_halves(halves, features=features)


def _pixel_means(pix: np.ndarray, values: np.ndarray, count: np.ndarray, shape) -> np.ndarray:
    h, w = shape
    sums = np.stack([np.bincount(pix, weights=values[:, c], minlength=h * w) for c in range(values.shape[1])],
                    axis=1) if values.shape[1] else np.zeros((h * w, 0))
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(count.ravel()[:, None] > 0, sums / np.maximum(count.ravel(), 1)[:, None], 0.0)
    return mean.reshape(h, w, values.shape[1])


def _read_all(source, nonfinite: str):
    """Every sample of ``source`` (SampleSet or sample log): positions, values and features, policy applied."""
    names = tuple(getattr(source, "feature_names", ()) or ())
    pos, val, feats = [], [], {n: [] for n in names}
    for ch in source.iter_chunks(with_round=False, features=names):
        pos.append(np.asarray(ch.positions, dtype=np.float64))
        val.append(np.asarray(ch.values, dtype=np.float64))
        for n in names:
            feats[n].append(np.asarray(ch.features[n]))
    n_ch = len(source.channels)
    pos = np.concatenate(pos) if pos else np.zeros((0, 2))
    val = np.concatenate(val) if val else np.zeros((0, n_ch))
    if val.ndim == 1:
        val = val[:, None]
    feats = {n: np.concatenate(a) for n, a in feats.items() if a}
    bad = ~np.isfinite(val).all(axis=1)
    n_bad = int(bad.sum())
    if n_bad:
        rows, val = apply_nonfinite(np.arange(pos.shape[0]), val, n_bad, nonfinite, where=source_name(source))
        pos = pos[rows]
        feats = {n: a[rows] for n, a in feats.items()}
    return pos, val, feats


def clean_samples(source, *, k_min: int = 4, neighbour_weight: float = 0.2, frac: float = 0.25,
                  max_radius: int = 32, nonfinite: str = "drop") -> CleanedSamples:
    """Find the fireflies among a source's samples and move their energy: samples for any filter.

    Parameters
    ----------
    source : SampleSet or sample log
        The individual samples (a pixel's range, its halves and its
        neighbours' densities are read from them).
    k_min : int >= 1
        Samples above a luminance level that a pixel's 3 x 3 neighbourhood
        needs for the level to stay; fewer, and the part above moves (also
        the count a spread kernel gathers).  Larger: more is moved, further.
    neighbour_weight : float >= 0
        Weight of a pixel's 3 x 3 neighbours' bright samples in where the
        moved energy lands (0: only pixels that saw samples that bright).
    frac : float in (0, 1]
        A level is also dense where this share of the neighbourhood's
        samples is above it (keeps an emitter's rim in place at low counts).
    max_radius : int >= 2
        Largest spread radius in pixels.
    nonfinite : {"drop", "zero", "raise"}
        What happens to samples with NaN or Inf values first.

    Returns
    -------
    CleanedSamples
        ``mean`` is the cleaned per-pixel estimate to give a filter or a
        denoiser in place of the pixel means; ``samples`` the same for
        methods that read samples, :meth:`CleanedSamples.halves` for methods
        that read two independent half buffers.

    Notes
    -----
    Energy: ``(mean * [count > 0]).sum() == (raw_mean * [count > 0]).sum()``
    to round-off (the excess lands only in pixels with samples).  Without a
    firefly (every level dense wherever it occurs) the cleaned samples are
    the input's exactly.  ``k_min = 4`` moves only samples with fewer than
    four like them within one pixel: larger values move the rare but
    legitimate samples of a caustic too (measured with OIDN on them,
    ``docs/fireflies.md``).

    Examples
    --------
    >>> import numpy as np, mcrecon
    >>> rng = np.random.default_rng(0)
    >>> pos = rng.random((32 * 32 * 16, 2)) * 32
    >>> val = np.full((pos.shape[0], 3), 0.1)
    >>> val[::700] = 100.0                      # rare fireflies
    >>> c = clean_samples(mcrecon.SampleSet(pos, val, width=32, height=32))
    >>> bool(abs(c.mean.sum() - c.raw_mean.sum()) < 1e-9 * c.raw_mean.sum())   # energy kept
    True
    >>> bool(c.mean.max() < 0.5 * c.raw_mean.max())                          # the dots are gone
    True
    """
    if not hasattr(source, "iter_chunks") or not hasattr(source, "channels"):
        raise InputError(_WHERE, "source", f"got {type(source).__name__}; expected the samples (a SampleSet or "
                         "a sample log): pixel statistics hold no individual samples to clean")
    check_policy(nonfinite, _WHERE)
    w, h = int(source.width), int(source.height)
    pos, val, feats = _read_all(source, nonfinite)
    options = dict(k_min=k_min, neighbour_weight=neighbour_weight, frac=frac, max_radius=max_radius)
    values, moved, split = _cleaned_values(pos, val, w, h, options)
    pix = (np.floor(pos[:, 1]).astype(np.int64) * w + np.floor(pos[:, 0]).astype(np.int64)) if pos.size \
        else np.zeros(0, np.int64)
    count = np.bincount(pix, minlength=w * h).reshape(h, w).astype(np.int64)
    channels = tuple(source.channels)
    cleaned = SampleSet(pos, values, width=w, height=h, channels=channels, features=feats or None,
                        name=f"{source_name(source)} (cleaned)")
    raw_mean = _pixel_means(pix, val, count, (h, w))
    mean = _pixel_means(pix, values, count, (h, w)) if moved.any() else raw_mean.copy()
    return CleanedSamples(cleaned, mean, raw_mean, count, moved, split.excess, split.threshold,
                          float(split.moved_fraction), options, val)


def _cleaned_values(pos, val, w, h, options):
    """``(values, moved, split)``: each sample's base part plus its pixel's share of the moved energy."""
    # split_fireflies validates k_min, neighbour_weight, frac and max_radius (one-line errors naming them)
    split = split_fireflies(pos, val, width=w, height=h, sampled_only=True, **options)
    moved = np.any(split.base_values != val, axis=1) if val.size else np.zeros(0, bool)
    if not moved.any():
        return val, moved, split  # nothing moved: the samples as they came, bit for bit
    pix = np.floor(pos[:, 1]).astype(np.int64) * w + np.floor(pos[:, 0]).astype(np.int64)
    return split.base_values + split.excess.reshape(h * w, -1)[pix], moved, split
