"""The ``awr`` method: AWR sampling and reconstruction behind the method contract (Overbeck et al. 2009)."""

from __future__ import annotations

import dataclasses

import numpy as np

from ..base import AdaptiveState, Method, MethodInputs, Option, Requirements, RunState, uniform_counts, variant_option
from ...core.fill import fill_empty_pixels
from .reconstruction import DOMAINS, VARIANCE_ESTIMATORS, awr_reconstruct, log_domain_reconstruct, pixel_variance
from ...core.nets import RARE_COVER, covered_even_plan, rare_net_deficit
from ...core.safeguard import RARE_THRESHOLD, confidence_clamp, sample_range_bounds
from .sampling import plan_awr_positions
from .wavelets import BOUNDARY_MODES, PROPAGATIONS, RECONSTRUCTION_RENORM, SAMPLING_RENORM, WAVELETS, default_levels

__all__ = ["AWRMethod", "AWRRun"]

#: Samples per popped level-0 coefficient in the paper (Fig. 4): what one batch may give a pixel.
_PAPER_PER_COEFFICIENT = 64
#: Deepest decomposition the ``levels`` option accepts.
_MAX_LEVELS = 12
#: An independent run's rounds are even under a rare component whose floor covers most of the film
#: (``RARE_COVER``) only where its samples find it this often or more (per sample, ``nets.hit_rate``): there
#: the wavelet sampler ranks the light's noise, which every pixel's own samples carry (tuning checker_spot
#: at p 0.091-0.105: adaptive / uniform 1.01-1.03 with the sampler's counts, 0.993-1.005 even); below it its
#: extra samples dilute the pixels that caught a rare component (p 0.011-0.055 read 0.98-1.01 either way,
#: tests/test_awr_robust.py's firefly field at 1e-3 gains 1.8x over even rounds).  docs/adaptive.md.
EVEN_HIT_RATE = 0.075



@dataclasses.dataclass(eq=False)
class AWRRun(RunState):
    """Per-run state of :class:`AWRMethod`: what the sampler's last round did."""

    last_plan_info: dict = dataclasses.field(default_factory=dict)


class AWRMethod(Method):
    """Adaptive wavelet rendering: wavelet sampling and soft-thresholding reconstruction.

    Options (keyword-only; also the CLI flags and ``mcrecon methods awr``):
    :attr:`options`.

    Diagnostics: ``pixel_std`` and ``smoothing`` of the reconstruction,
    ``samples`` (samples per pixel) of an adaptive run.

    References
    ----------
    .. [1] R. S. Overbeck, C. Donner, R. Ramamoorthi, "Adaptive Wavelet
       Rendering", SIGGRAPH Asia 2009.
    """

    name = "awr"
    run_type = AWRRun
    adaptive = True
    pipeline = False  # measured +3..31 % relative MSE with one round of lag: only when asked
    initial_spp = 16
    #: ``variant="paper"`` presets every algorithm option to Overbeck et al.
    #: 2009; the default ``robust`` departs from it where measurement says it
    #: must (docs/methods/awr.md, "Default vs paper").  Options the presets
    #: do not name (``levels``, ``priority_threshold``, ``reconstruction``,
    #: ``round_spp``) are the same in both.
    variants = {
        "robust": {},
        "paper": {
            "wavelet": "cdf97", "cs": 1.0,
            "variance": "range",             # §4.2: (Imax - Imin)^2
            "domain": "linear",              # Eq. 11 on the pixel values
            "log_offset": 0.01,              # (unused in the linear domain)
            "safeguard": None,               # no confidence-interval clamp
            "boundary": "symmetric",
            "propagation": "exact",          # Eq. 9/10 as written (the paper's squared-tap cascade: "cascade")
            "renorm": RECONSTRUCTION_RENORM,  # 2^-1/2
            "sampling_renorm": SAMPLING_RENORM,  # 1.05
            "sampling_levels": 5,
            "sampling_variance": "contrast",  # Eq. 5, Mitchell's contrast
            "per_coefficient": 64,           # Fig. 4: 64 x 2^k samples per popped coefficient
            "initial_spp": 4,                # Fig. 4 Step 1
            "rare_light_floor": 0,           # each pixel's own sigma^2(F)
            "uniform_share": 0.0,            # every sample by priority
            "net_counts": 0,                 # the sampler's counts as they fall
        },
    }
    @property
    def requires(self) -> Requirements:
        # the 'range' estimator reads each pixel's sample minimum and maximum; 'sample' takes statistics alone
        return Requirements(range=self.params["variance"] == "range", statistics_options={"variance": "sample"})

    options = (
        variant_option(variants),
        Option("wavelet", str, "cdf97", "wavelet basis", tuple(WAVELETS)),
        Option("cs", float, 1.0, "smoothing constant c_s of Eq. 11 (0 = no smoothing)", min=0.0),
        Option("variance", str, "sample", "sigma^2(F) estimator of the reconstruction (paper: range)",
               VARIANCE_ESTIMATORS),
        Option("domain", str, "log", "domain of the wavelet shrinkage: linear (paper) or log(mean + delta), "
               "delta = log_offset x the channel's mean pixel (signed channels stay linear)", DOMAINS),
        Option("log_offset", float, 0.01, "delta of the log domain as a fraction of the channel's mean pixel",
               min=0.0, min_open=True),
        Option("safeguard", float, 2.0, nullable=True, help="clamp each pixel into mean +- k standard errors of its mean and into "
               "the range of the samples around it (k; None: no clamp, the paper)", min=0.0),
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
        Option("per_coefficient", int, 0, "samples per selected level-0 coefficient (x 2^k at level k; paper 64; "
               "0: a quarter of the run's average spp, at least 1, so that one pop of a noisy estimate puts a "
               "fraction of a pixel's share into it, not twice the budget's average)", min=0),
        Option("round_spp", float, 4.0, "samples per pixel placed per adaptive round (priority update interval)",
               min=0.0, min_open=True),
        Option("initial_spp", int, 16, "uniform samples per pixel of the first round (paper 4; capped by the budget)",
               min=1),
        Option("rare_light_floor", int, 1, "sampler: 1 floors each pixel's sigma^2(F) at its 5 x 5 "
               "neighbourhood's mean where a neighbour's samples show a rare bright component (a spotlight, "
               "a caustic), so pixels whose samples all missed it keep their samples; 0 the pixel's own "
               "(the paper)",
               choices=(0, 1)),
        Option("uniform_share", float, 0.0, "share of each adaptive round spread uniformly over the film "
               "(0: the wavelet sampler alone, the paper; a quarter costs the HDR step edge of "
               "tests/test_awr_robust.py 3x its error, docs/methods/awr.md)", min=0.0, max=1.0),
        Option("net_counts", int, -1, "adaptive rounds: 1 rounds each round's counts so that every pixel's total "
               "is a power of two (a full net of a stratified sampler's sequence; mcrecon.core.nets), the "
               "sampler's ranking deciding which pixels step up; 0 the counts as the sampler draws them (the "
               "paper); -1 (default) follows the renderer: 1 where it declares a stratified sampler "
               "(Renderer.sampler 'sobol'), 0 for independent samples", choices=(-1, 0, 1)),
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
        kw = dict(wavelet=p["wavelet"], cs=p["cs"], levels=levels, mode=p["boundary"],
                  propagation=p["propagation"], renorm=p["renorm"])
        if p["domain"] == "log":
            img = log_domain_reconstruct(mean, var, offset=p["log_offset"], **kw)
        else:
            img = awr_reconstruct(mean, var, **kw)
        if p["safeguard"] is not None:
            # The interval uses the unbiased standard error of each mean,
            # whatever estimator set the thresholds: it is a statement
            # about where the true pixel value lies.
            se2 = var if p["variance"] == "sample" else pixel_variance(stats, "sample")
            lo, hi = sample_range_bounds(stats)
            img = confidence_clamp(img, mean, se2, p["safeguard"], lo, hi)
        run.diagnostics["pixel_std"] = np.sqrt(var).mean(axis=2)
        run.diagnostics["smoothing"] = np.abs(img - mean).mean(axis=2)
        return img

    # ------------------------------------------------------------- adaptive
    @staticmethod
    def default_per_coefficient(state: AdaptiveState) -> int:
        """Samples per popped level-0 coefficient when ``per_coefficient=0``: a quarter of the run's average spp.

        The paper's 64 at 32 spp puts twice the budget's average into one pixel per pop, chosen from
        one noisy estimate and not re-ranked within the round: the counts turn bimodal and the pixels
        the estimate missed keep their initial samples (docs/adaptive.md).  A quarter of the average
        is the paper's 64 at 256 spp.
        """
        return max(1, int(round(state.budget / (4.0 * state.width * state.height))))

    def plan(self, run: "AWRRun", state: AdaptiveState):
        """:meth:`Method.plan`'s round of :meth:`place`, or an even round (``nets.covered_even_plan``) for
        independent samples where the rare component's floor covers most of the film and its samples find it at
        :data:`EVEN_HIT_RATE` or more (``rare_light_floor`` on; the paper's variant has it off)."""
        even = covered_even_plan(self, state, threshold=RARE_THRESHOLD, min_hit_rate=EVEN_HIT_RATE) \
            if self.params["rare_light_floor"] else None
        return even or super().plan(run, state)

    def place(self, run: "AWRRun", state: AdaptiveState, n: int):
        """Samples per pixel of the wavelet sampler's next batch of ``n`` (§4.1), or None when it has none.

        :meth:`Method.plan` sizes the batch (``round_spp`` per pixel).
        Pipelined, the variance of each coefficient counts the samples in
        flight (``state.pending``).
        """
        p = self.params
        if int(state.stats.count.sum()) == 0:  # nothing committed to place by (every sample dropped as NaN)
            return uniform_counts(state.width, state.height, n, state.rng)
        pc = p["per_coefficient"] or self.default_per_coefficient(state)
        pos, info = plan_awr_positions(
            state.stats, n, state.rng, wavelet=p["wavelet"], levels=p["sampling_levels"], mode=p["boundary"],
            per_coefficient=pc, renorm=p["sampling_renorm"], propagation=p["propagation"],
            priority_threshold=p["priority_threshold"], estimator=p["sampling_variance"],
            pending=state.pending, as_counts=True,  # counts: the renderer continues each pixel's sequence
            rare_light_floor=bool(p["rare_light_floor"]),
            # the budget's per_coefficient may pop a pixel until it has the paper's 64 of the round
            pixel_pops=1 if p["per_coefficient"] else -(-_PAPER_PER_COEFFICIENT // pc),
            # a pixel first gets the net that holds a rare component its neighbourhood shows; with independent
            # samples only where the component covers most of the film (RARE_COVER)
            owed=rare_net_deficit(state, threshold=RARE_THRESHOLD,
                                  min_cover=0.0 if state.sampler != "independent" else RARE_COVER)
            if p["rare_light_floor"] else None)
        run.last_plan_info = info
        if pos is None or len(pos) == 0:
            return None
        return pos

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
