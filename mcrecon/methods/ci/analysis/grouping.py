"""Samples grouped by pixel: the per-pixel empirical distributions F-hat.

:func:`group_samples` (arrays) and :func:`group_log` (a sample source: a
sample log or a :class:`~mcrecon.core.samples.SampleSet`) sort samples by pixel
into a CSR layout, :class:`PixelSamples`, in their original (chronological)
order.  Samples are validated by :mod:`mcrecon.core.samples`, the one
validation path and NaN/Inf policy.  Nothing here opens a file.
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

import numba
import numpy as np

from ....errors import InputError
from ....core.samples import apply_nonfinite, check_policy, check_samples, source_name, warn_nonfinite

__all__ = ["PixelSamples", "group_samples", "group_log"]


@numba.njit(cache=True)
def _counting_sort(pix, n_pixels):
    """Stable counting sort: (order, offsets) with pixel p's samples at
    ``order[offsets[p]:offsets[p+1]]`` in their original order."""
    offsets = np.zeros(n_pixels + 1, np.int64)
    for i in range(pix.size):
        offsets[pix[i] + 1] += 1
    for p in range(n_pixels):
        offsets[p + 1] += offsets[p]
    fill = offsets[:-1].copy()
    order = np.empty(pix.size, np.int64)
    for i in range(pix.size):
        q = pix[i]
        order[fill[q]] = i
        fill[q] += 1
    return order, offsets


@dataclasses.dataclass(eq=False)
class PixelSamples:
    """Samples grouped by pixel, in their original (chronological) order.

    Pixel ``p = row * width + col`` owns ``values[offsets[p]:offsets[p+1]]``;
    ``order`` maps these rows back to the input rows.

    Attributes
    ----------
    width, height : int
    channels : tuple of str
    values : ndarray (N, C) float64, grouped
    offsets : ndarray (H*W + 1,) int64
    order : ndarray (N,) int64
    """

    width: int
    height: int
    channels: tuple
    values: np.ndarray
    offsets: np.ndarray
    order: np.ndarray

    @property
    def counts(self) -> np.ndarray:
        """Samples per pixel (H, W)."""
        return np.diff(self.offsets).reshape(self.height, self.width)

    def pixel(self, col: int, row: int) -> np.ndarray:
        p = int(row) * self.width + int(col)
        return self.values[self.offsets[p]:self.offsets[p + 1]]

    def means(self) -> np.ndarray:
        """Per-pixel sample means (H, W, C), 0 where empty: ``t(F-hat)``."""
        cnt = np.diff(self.offsets)
        pix = np.repeat(np.arange(cnt.size), cnt)
        sums = np.stack([np.bincount(pix, weights=self.values[:, c], minlength=cnt.size)
                         for c in range(self.values.shape[1])], axis=1)
        return (sums / np.maximum(cnt, 1)[:, None]).reshape(self.height, self.width, -1)


def group_samples(positions, values, *, width: int, height: int, channels: Sequence[str] | None = None,
                  nonfinite: str = "drop", source: str = "samples") -> PixelSamples:
    """Group samples by pixel (stable counting sort, O(N)).

    Parameters
    ----------
    positions : array_like (N, 2)
        Film positions (x = column, y = row), inside [0, W) x [0, H).
    values : array_like (N, C)
        Grouped as float64.
    channels : sequence of str, optional
        Default R, G, B for 3 columns, else C0, C1, ...
    nonfinite : {'drop', 'zero', 'raise'}
        The policy for samples with a NaN/Inf value
        (:data:`mcrecon.core.samples.NONFINITE_POLICIES`): dropped (the default,
        as in the sample log) or set to 0 with a McreconWarning that counts
        them, or refused.
    source : str
        Named in error messages and warnings.

    Raises
    ------
    InputError
        As :func:`mcrecon.core.samples.check_samples` (mis-shaped arrays,
        positions off the film or non-finite), an unknown policy, a
        non-finite value under ``nonfinite='raise'``.
    """
    check_policy(nonfinite, source)
    width, height = int(width), int(height)
    if width < 1 or height < 1:
        raise InputError(source, "width/height", f"got {width}x{height}, expected at least 1x1")
    if channels is None:
        shape = np.shape(values)
        n_ch = shape[1] if len(shape) == 2 else 1
        chans = ("R", "G", "B") if n_ch == 3 else tuple(f"C{i}" for i in range(n_ch))
    else:
        chans = tuple(str(c) for c in channels)
    if not chans:
        raise InputError(source, "values", f"shape {np.shape(values)}, expected (N, C) with C >= 1")
    pos, val, n_nonfinite = check_samples(positions, values, width=width, height=height, n_channels=len(chans),
                                          where=source, channels=chans)
    rows = None
    if n_nonfinite:
        # The policy applied to the row numbers alongside the values: the rows
        # it keeps map the grouped samples back to the input rows (``order``).
        rows, val = apply_nonfinite(np.arange(pos.shape[0]), val, n_nonfinite, nonfinite, where=source)
        pos = pos[rows]
        warn_nonfinite(source, n_nonfinite, nonfinite, stacklevel=2)
    val = val.astype(np.float64, copy=False)
    pix = (np.floor(pos[:, 1]).astype(np.int64) * width + np.floor(pos[:, 0]).astype(np.int64))
    order, offsets = _counting_sort(pix, width * height)
    grouped = np.ascontiguousarray(val[order])
    if rows is not None:
        order = rows[order]
    return PixelSamples(width, height, chans, grouped, offsets, order)


def group_log(log, *, nonfinite: str = "drop") -> PixelSamples:
    """Group the samples of a sample source (a :class:`~mcrecon.io.SampleLog` or a
    :class:`~mcrecon.core.samples.SampleSet`) by pixel; holds every sample in memory."""
    if not (hasattr(log, "iter_chunks") and hasattr(log, "width")):
        raise InputError("group_log", "log", f"got {type(log).__name__}; expected a sample source "
                         "(mcrecon.read_log(path) or a SampleSet)")
    chunks = list(log.iter_chunks(with_round=False))
    c = len(log.channels)
    pos = np.concatenate([np.asarray(ch.positions) for ch in chunks]) if chunks else np.zeros((0, 2))
    val = np.concatenate([np.asarray(ch.values) for ch in chunks]) if chunks else np.zeros((0, c))
    return group_samples(pos, val, width=log.width, height=log.height,
                         channels=log.channels, nonfinite=nonfinite, source=source_name(log))
