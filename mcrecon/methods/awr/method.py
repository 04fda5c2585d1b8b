"""The ``awr`` method: AWR sampling and reconstruction behind the method contract (Overbeck et al. 2009)."""

from __future__ import annotations

import dataclasses

import numpy as np

from ...renderers.protocol import SampleRequest
from ..base import AdaptiveState, Method, MethodInputs, Option, RunState
from ..box import fill_empty_pixels
from .reconstruction import VARIANCE_ESTIMATORS, awr_reconstruct, pixel_variance
from .sampling import plan_awr_positions
from .wavelets import BOUNDARY_MODES, PROPAGATIONS, RECONSTRUCTION_RENORM, SAMPLING_RENORM, WAVELETS, default_levels

__all__ = ["AWRMethod", "AWRRun"]

#: Deepest decomposition the ``levels`` option accepts.
_MAX_LEVELS = 12


class AWRMethod(Method):
    """Adaptive wavelet rendering: wavelet sampling and soft-thresholding reconstruction.

    Options (keyword-only; also CLI flags): see :attr:`options`.

    Diagnostics: ``pixel_std`` and ``smoothing`` of the reconstruction,
    ``samples`` (samples per pixel) of an adaptive run.

    References
    ----------
    .. [1] R. S. Overbeck, C. Donner, R. Ramamoorthi, "Adaptive Wavelet
       Rendering", SIGGRAPH Asia 2009.
    """

    name = "awr"
    adaptive = True
    initial_spp = 4
    options = (
        Option("wavelet", str, "cdf97", "wavelet basis", tuple(WAVELETS)),
        Option("cs", float, 1.0, "smoothing constant c_s of Eq. 11 (0 = no smoothing)", min=0.0),
        Option("variance", str, "range", "sigma^2(F) estimator of the reconstruction", VARIANCE_ESTIMATORS),
        Option("levels", int, None, "reconstruction depth (default: floor(log2(min side)) - 2, at most 6)",
               min=0, max=_MAX_LEVELS),
        Option("boundary", str, "symmetric", "wavelet boundary extension", BOUNDARY_MODES),
        Option("propagation", str, "exact", "variance propagation: exact Eq. 9/10 or the paper's squared-tap DWT",
               PROPAGATIONS),
        Option("renorm", float, RECONSTRUCTION_RENORM, "sum of the squared reconstruction filters (paper 2^-1/2)",
               min=0.0, min_open=True),
        Option("sampling_renorm", float, SAMPLING_RENORM, "sum of the squared sampling filters (paper 1.05)",
               min=0.0, min_open=True),
        Option("sampling_levels", int, 5, "highest scale level the sampler ranks (paper 5)", min=0),
        Option("sampling_variance", str, "contrast", "sigma^2(F) estimator of the sampler (paper: contrast)",
               VARIANCE_ESTIMATORS),
        Option("per_coefficient", int, 64, "samples per selected level-0 coefficient (x 2^k at level k)", min=1),
        Option("round_spp", float, 4.0, "samples per pixel placed per adaptive round (priority update interval)",
               min=0.0, min_open=True),
        Option("initial_spp", int, 4, "uniform samples per pixel of the first round (paper 4)", min=1),
        Option("priority_threshold", float, None, "stop sampling when no priority exceeds this"),
        Option("reconstruction", str, "awr", "final image of an adaptive run: awr, or box (AWR sampling only)",
               ("awr", "box")),
    )

    # -------------------------------------------------------------- offline
    def halo(self, width, height):
        return None  # periodized wavelet levels and image-wide thresholds: whole-image

    def _levels(self, h: int, w: int) -> int:
        return default_levels((h, w)) if self.params["levels"] is None else self.params["levels"]

    def reconstruct_run(self, run: RunState, inputs: MethodInputs) -> np.ndarray:
        """AWR reconstruction (§4.2) of pixel statistics (any sampling)."""
        p = self.params
        stats = inputs.stats
        mean = fill_empty_pixels(stats.mean.copy(), stats.count, source="awr")
        var = pixel_variance(stats, p["variance"])
        levels = self._levels(stats.height, stats.width)
        img = awr_reconstruct(mean, var, wavelet=p["wavelet"], cs=p["cs"], levels=levels, mode=p["boundary"],
                              propagation=p["propagation"], renorm=p["renorm"])
        run.diagnostics["pixel_std"] = np.sqrt(var).mean(axis=2)
        run.diagnostics["smoothing"] = np.abs(img - mean).mean(axis=2)
        return img

    # ------------------------------------------------------------- adaptive
    def start(self, width, height, channels=("R", "G", "B"), *, reference=None) -> "AWRRun":
        base = super().start(width, height, channels, reference=reference)
        return AWRRun(**dataclasses.asdict(base))

    def plan(self, run: "AWRRun", state: AdaptiveState) -> SampleRequest | None:
        """Initial uniform pass, then batches of the wavelet sampler (§4.1)."""
        p = self.params
        remaining = state.remaining
        if remaining <= 0:
            return None
        npix = state.width * state.height
        if state.n_samples == 0:
            return state.uniform_request(p["initial_spp"])
        quota = min(remaining, max(1, int(round(p["round_spp"] * npix))))
        pos, info = plan_awr_positions(
            state.stats, quota, state.rng, wavelet=p["wavelet"], levels=p["sampling_levels"], mode=p["boundary"],
            per_coefficient=p["per_coefficient"], renorm=p["sampling_renorm"], propagation=p["propagation"],
            priority_threshold=p["priority_threshold"], estimator=p["sampling_variance"])
        run.last_plan_info = info
        if pos is None or len(pos) == 0:
            return None
        return state.request(positions=pos)

    def finish(self, run: "AWRRun", state: AdaptiveState) -> np.ndarray:
        """AWR (or, with ``reconstruction='box'``, box) image of the adaptive samples.

        Also fills the diagnostic map ``samples`` (samples per pixel): the
        sampler's density, the paper's Fig. 1 insets, and the first thing to
        compare against an error map when the sampler loses (see
        ``docs/methods/awr.md``, "Why AWR can lose").
        """
        run.diagnostics["samples"] = state.stats.count.astype(np.float64)
        if self.params["reconstruction"] == "box":
            return fill_empty_pixels(state.stats.mean.copy(), state.stats.count, source="awr")
        return self.reconstruct_run(run, state.inputs())


@dataclasses.dataclass(eq=False)
class AWRRun(RunState):
    """Per-run state of :class:`AWRMethod`: what the sampler's last round did."""

    last_plan_info: dict = dataclasses.field(default_factory=dict)
