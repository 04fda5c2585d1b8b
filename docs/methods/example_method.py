"""A complete minimal mcrecon method: a k x k mean filter that samples where it is noisy.

The example of ``docs/methods/writing-a-method.md``; it runs as a test
(``tests/test_method_contract.py``), offline and adaptive.  It uses only
the public contract of :mod:`mcrecon.methods`.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy import ndimage

from mcrecon.errors import InputError
from mcrecon.methods import Method, Option, Requirements, RunState


@dataclasses.dataclass(eq=False)
class BlurRun(RunState):
    """What one run keeps: the priority map of its last plan (recomputed every round)."""

    priority: np.ndarray | None = None


class BlurMethod(Method):
    """Mean of the pixel means over a ``size`` x ``size`` window; adaptive
    rounds send samples to the pixels whose mean has the largest variance."""

    name = "blur"
    options = (
        Option("size", int, 3, "window side in pixels (odd)", min=1),
        Option("initial_spp", int, 2, "samples per pixel of the uniform initial pass", min=2),
        Option("round_spp", float, 2.0, "samples per pixel per adaptive round", min=0.0, min_open=True),
    )
    requires = Requirements()  # pixel statistics, nothing else
    run_type = BlurRun
    adaptive = True

    def _configure(self, params):
        if params["size"] % 2 == 0:
            raise InputError(self.where, "size", f"{params['size']}, expected an odd window side")

    def reconstruct_run(self, run: BlurRun, inputs) -> np.ndarray:
        stats = inputs.stats
        size = self.params["size"]
        run.diagnostics["spp"] = stats.count.astype(np.float64)
        return ndimage.uniform_filter(stats.mean, size=(size, size, 1), mode="nearest")

    def place(self, run: BlurRun, state, n: int):
        """Counts per pixel for ``n`` samples, in proportion to the variance of each pixel's mean."""
        var = state.stats.mean_variance(undefined=np.inf).mean(axis=2).ravel()
        weights = np.where(np.isfinite(var), var, var[np.isfinite(var)].max(initial=1.0))
        total = weights.sum()
        p = weights / total if total > 0 else np.full(weights.size, 1.0 / weights.size)
        run.priority = p.reshape(state.height, state.width)
        run.diagnostics["priority"] = run.priority
        return state.rng.multinomial(n, p).reshape(state.height, state.width)
