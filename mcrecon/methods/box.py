"""``box``: the pixel mean (the naive baseline every method is measured against)."""

from __future__ import annotations


import numpy as np

from .base import Method, MethodInputs, RunState
from ..core.fill import fill_empty_pixels

__all__ = ['BoxMethod']

class BoxMethod(Method):
    """The per-pixel sample mean, with uniform sampling in doubling rounds (capped: see ``Method.max_round_parts``)."""

    name = "box"
    pipeline = True  # uniform rounds that depend only on the sample count: bit-identical with one round of lag
    #: The pixel means alone, no variance: one render of means (a Cycles EXR) serves it (offline.pixel_files).
    reads_variance = False

    def halo(self, width, height):
        return 0  # the pixel's own mean (empty pixels aside: see Method.halo)

    def reconstruct_run(self, run: RunState, inputs: MethodInputs) -> np.ndarray:
        stats = inputs.stats
        return fill_empty_pixels(stats.mean.copy(), stats.count)
