"""``box``: the pixel mean (the naive baseline every method is measured against)."""

from __future__ import annotations

import warnings

import numpy as np

from ..errors import McreconWarning
from .base import AdaptiveState, Method, MethodInputs, RunState, uniform_counts

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
    """The per-pixel sample mean, with uniform sampling in doubling rounds (capped: see ``max_round_parts``)."""

    name = "box"
    pipeline = "default"  # uniform rounds that depend only on the sample count: bit-identical with one round of lag
    #: Largest round: 1 / max_round_parts of the budget in whole samples per pixel, but
    #: never below max_round_floor samples.  Plain doubling ends with a round of half
    #: the budget, whose commit (validation and statistics of half the samples) is the
    #: one step of a pipelined run nothing overlaps: the renderer has finished.  The cap
    #: bounds that tail at about 1/8 of the commit work (measured, throttled scene
    #: renderer 1024^2 32 spp: idle share 3.8 % with doubling; docs/pipelining.md has
    #: the capped numbers).  Below the floor (~30 ms of commit) a cap would only add
    #: rounds, each with its fixed cost.
    max_round_parts = 8
    max_round_floor = 1 << 20

    def plans_round_one_blind(self) -> bool:
        return True  # its rounds depend only on the sample count, which counts the round in flight

    def halo(self, width, height):
        return 0  # the pixel's own mean (empty pixels aside: see Method.halo)

    def reconstruct_run(self, run: RunState, inputs: MethodInputs) -> np.ndarray:
        stats = inputs.stats
        return fill_empty_pixels(stats.mean.copy(), stats.count)

    def plan(self, run: RunState, state: AdaptiveState):
        """1 spp, then rounds doubling the total up to the cap (see ``max_round_parts``); the last fills the budget.

        Depends only on the sample count (committed plus in flight), so a
        pipelined run asks for the rounds of a sequential one.
        """
        remaining = state.remaining
        if remaining <= 0:
            return None
        if state.n_samples == 0:
            return state.uniform_request(max(1, int(self.params.get("initial_spp", self.initial_spp))))
        npix = state.width * state.height
        cap_spp = max(-(-state.budget // (self.max_round_parts * npix)), -(-self.max_round_floor // npix))
        n = min(remaining, state.n_samples, cap_spp * npix)
        return state.request(counts=uniform_counts(state.width, state.height, n, state.rng))
