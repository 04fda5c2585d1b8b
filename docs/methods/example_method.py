"""A complete minimal mcrecon method: a k x k mean filter that samples where it is noisy.

This file is the example of ``docs/methods/writing-a-method.md`` and runs
as a test (``tests/test_method_contract.py``).  It uses only the public
contract of :mod:`mcrecon.methods.base`: immutable options, a per-run
state, declared inputs, no file access.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy import ndimage

from mcrecon.methods import Method, MethodInputs, Option, RunState


@dataclasses.dataclass(eq=False)
class BlurRun(RunState):
    """What one run keeps: the priority map of its last planning step.

    ``plan`` recomputes it from ``state`` every round, so a resumed run
    (whose state is fresh: only ``observe`` is replayed) loses nothing.
    """

    priority: np.ndarray | None = None


class BlurMethod(Method):
    """Mean of the pixel means over a ``size`` x ``size`` window; adaptive
    rounds send samples to the pixels whose mean has the largest variance."""

    name = "blur"
    adaptive = True
    options = (
        Option("size", int, 3, "window side in pixels (odd)", min=1),
        Option("round_spp", float, 2.0, "samples per pixel per adaptive round", min=0.0, min_open=True),
    )

    def _configure(self, params):
        if params["size"] % 2 == 0:
            from mcrecon.errors import InputError
            raise InputError(self.where, "size", f"{params['size']}, expected an odd window side")

    def start(self, width, height, channels=("R", "G", "B"), *, reference=None):
        return BlurRun(**dataclasses.asdict(super().start(width, height, channels, reference=reference)))

    def reconstruct_run(self, run: BlurRun, inputs: MethodInputs) -> np.ndarray:
        stats = inputs.stats
        size = self.params["size"]
        image = ndimage.uniform_filter(stats.mean, size=(size, size, 1), mode="nearest")
        run.diagnostics["spp"] = stats.count.astype(np.float64)
        return image

    def plan(self, run: BlurRun, state):
        if state.n_samples == 0:
            return state.uniform_request(2)  # two samples everywhere: a first variance
        n = min(state.remaining, int(self.params["round_spp"] * state.width * state.height))
        if n <= 0:
            return None
        var = state.stats.mean_variance(undefined=np.inf).mean(axis=2).ravel()
        weights = np.where(np.isfinite(var), var, var[np.isfinite(var)].max(initial=1.0))
        total = weights.sum()
        p = weights / total if total > 0 else np.full(weights.size, 1.0 / weights.size)
        counts = state.rng.multinomial(n, p).reshape(state.height, state.width)
        run.priority = p.reshape(state.height, state.width)
        run.diagnostics["priority"] = run.priority
        return state.request(counts=counts)
