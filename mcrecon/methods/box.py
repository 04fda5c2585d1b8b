"""``box``: the pixel mean (the naive baseline every method is measured against)."""

from __future__ import annotations

import warnings

import numpy as np

from ..errors import McreconWarning
from .base import Method, MethodInputs, RunState

__all__ = ["BoxMethod", "fill_empty_pixels"]


def fill_empty_pixels(image: np.ndarray, count: np.ndarray, *, source: str = "image") -> np.ndarray:
    """Fill pixels without samples from their nearest sampled neighbours.

    Policy (documented in docs/methods/box.md): each empty pixel takes the
    value of the nearest pixel with samples (Euclidean distance transform);
    an image without any sample stays 0.  A warning counts the filled pixels.
    """
    empty = count == 0
    if not empty.any():
        return image
    if empty.all():
        warnings.warn(f"{source}: no samples at all; the image is 0", McreconWarning, stacklevel=3)
        return np.zeros_like(image)
    from scipy import ndimage

    _, (iy, ix) = ndimage.distance_transform_edt(empty, return_indices=True)
    warnings.warn(f"{source}: {int(empty.sum())} pixel(s) without samples filled from their nearest "
                  "sampled neighbour", McreconWarning, stacklevel=3)
    return image[iy, ix]


class BoxMethod(Method):
    """The per-pixel sample mean, with uniform sampling in doubling rounds (capped: see ``Method.max_round_parts``)."""

    name = "box"
    pipeline = True  # uniform rounds that depend only on the sample count: bit-identical with one round of lag

    def halo(self, width, height):
        return 0  # the pixel's own mean (empty pixels aside: see Method.halo)

    def reconstruct_run(self, run: RunState, inputs: MethodInputs) -> np.ndarray:
        stats = inputs.stats
        return fill_empty_pixels(stats.mean.copy(), stats.count)
