"""The ``gem`` method: greedy error minimization as an adaptive sampler and reconstruction (Rousselle et al. 2011).

:class:`GEMMethod` wires the selection (:mod:`.selection`) and the sample
distribution (:mod:`.sampling`) into the method contract
(:mod:`mcrecon.methods.base`); :class:`GEMRun` is its per-run state.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ...errors import InputError
from ...core.stats import PixelStats
from ..base import AdaptiveState, Method, MethodInputs, Option, Requirements, RunState, uniform_counts, variant_option
from ...filters.gaussian import adaptive_sigmas, final_sigmas
from .kernels import filled_subpixels, pending_n_eff
from .sampling import distribute_samples, sample_priority
from .guard import RISK_RADIUS
from .selection import CHANNEL_WEIGHTS, GAMMA_MAX, OUTLIER_RULES, GEMSelection, _pick, gem_select, oracle_select
from ...core.fill import mean_variance_policy
from ...core.safeguard import RARE_THRESHOLD, rare_component_variance
from ...core.strata import stratified_gain
from ...core.nets import (counts_with_pending, even_plan, fill_lowest, net_counts, noise_only,
                          state_rare_net_floor)

__all__ = ["GEMMethod", "GEMRun", "TARGET_EPS"]

#: Relative MSE of the user's target (option ``target_rel_mse``): the same
#: eps as :func:`mcrecon.core.metrics.relative_mse`, so the target means what the
#: reported error means.
TARGET_EPS = 1e-2
#: The adaptive floor's rare-component gate with independent samples (option ``rare_threshold`` None):
#: a light one sample in 4 finds reads a per-sample relative variance of 4 in the pixel that found it,
#: so at the initial pass only a gate below 4 lets its neighbours keep their share.
RARE_THRESHOLD_INDEPENDENT = 3.0
#: Share of their part of a round's uniform share that the pixels no rare floor holds keep in a round the
#: floors' deficit exceeds, with a stratified sampler: without it the floors take such rounds whole, the unheld
#: pixels' statistics do not change, and the floor cannot spread to a pixel whose first samples missed the light
#: (docs/adaptive.md, "Floors and the pixels they do not hold").
UNHELD_SHARE = 0.1

_WHERE = "method gem"


@dataclasses.dataclass(eq=False)
class GEMRun(RunState):
    """Per-run state of :class:`GEMMethod`: the last selection, kept until its diagnostics are asked for."""

    pending: tuple | None = None


class GEMMethod(Method):
    """Greedy error minimization (Rousselle, Knaus, Zwicker 2011).

    Offline (``reconstruct``): the final-reconstruction filter selection
    (8 Gaussian scales sqrt(2) apart from sqrt(2) px, Sec. 6).  Adaptive
    (``plan``): ``initial_spp`` uniform, then ``iterations`` rounds that
    each select filters with 4 dyadic scales from 1 px and send
    ``(budget - initial) / iterations`` samples to the pixels whose
    relative MSE falls fastest (Sec. 5); ``finish`` is the final
    reconstruction.

    Options (keyword-only; also the CLI flags and ``mcrecon methods gem``):
    :attr:`options`.

    References
    ----------
    .. [1] F. Rousselle, C. Knaus, M. Zwicker, "Adaptive Sampling and
       Reconstruction using Greedy Error Minimization", SIGGRAPH Asia 2011.
    """

    name = "gem"
    run_type = GEMRun
    #: The paper's 4 x 4 subpixel grid.  The default filters emulate it exactly
    #: per pixel (:func:`pixel_kernel`), so the statistics keep the grid itself
    #: only when ``subpixel_exact_below > 0`` asks to filter on it (see __init__).
    grid = 4
    adaptive = True
    initial_spp = 4
    #: Plans with one round of lag when asked (``adapt(..., pipeline=True)``): each
    #: adaptive round discounts the samples still in flight
    #: (``state.pending``) from the pixels it would pick (see :meth:`plan`).  Not
    #: the default: the lag cost +45-54 % relative MSE on the caustic (128^2, 32 spp,
    #: 8-16 seeds; rare huge samples found one round late), +27 % on hdr and +12 % on
    #: flat, 0.90-0.97 elsewhere (16 seeds, docs/pipelining.md); with the default's
    #: uniform quarter per round: caustic +42 %, flat +22 %, 0.73-1.04 elsewhere.
    pipeline = False
    #: The paper's algorithm (``variant="paper"``) against the measured defaults
    #: (docs/methods/gem.md, "Default vs paper"): error rate 0.1 (Sec. 7), the
    #: Sec. 6 final outlier rule, every pixel voting in the stopping maps, the
    #: channels' squared errors summed without weights.
    variants = {
        "robust": {},
        "paper": {"gamma": 0.1, "final_outliers": "paper", "zero_variance_votes": 3, "uniform_share": 0.0,
                  "channel_weights": "absolute", "confirm_stops": 0, "variance_guard": 0, "risk_guard": 0.0,
                  "stratified_gain": 0, "rare_light_floor": 0, "guard_halves": 0, "net_counts": 0,
                  "rare_nets": 0},
    }
    options = (
        variant_option(variants),
        Option("gamma", float, 0.2, "target error rate of the scale selector", min=0.0, max=GAMMA_MAX,
               min_open=True, max_open=True,
               note="the paper's z(gamma) = -log(1 - (1.9 gamma)^(1/sqrt 2)) is only calibrated there; "
                    "use e.g. 0.1 to 0.3"),
        Option("oracle", int, 0, "1: select and sample with the true bias from the reference, the paper's OUR-GRD "
               "(needs one: adapt(..., reference=) or reconstruct(stats, reference=))",
               choices=(0, 1)),
        Option("target_rel_mse", float, None, "stop sampling early once the estimated relative MSE "
               "(eps 0.01) averaged over the image is at most this", min=0.0, min_open=True),
        Option("initial_spp", int, 4, "samples per pixel of the uniform initial pass", min=1),
        Option("iterations", int, 8, "adaptive iterations after the initial pass", min=1),
        Option("uniform_share", float, 0.25, "share of each adaptive round spread uniformly over the film "
               "(0: the paper's greedy distribution alone)", min=0.0, max=1.0),
        Option("uniform_fill", str, None, nullable=True, help="where the uniform share goes: lowest (the pixels "
               "of fewest samples first, raised to a common level: the pixels the greedy distribution leaves "
               "behind catch up) or even (the same to every pixel); None (default) follows the renderer: lowest "
               "for independent samples, even where it declares a stratified sampler (there a level between "
               "two nets buys little: docs/adaptive.md); in whole nets (net_counts) the share always goes to "
               "the lowest nets first", choices=("lowest", "even")),
        Option("samples_per_pick", int, 0, "samples each selected pixel spreads over its filter "
               "(0: the average spp of the budget, as in the paper)", min=0),
        Option("adaptive_scales", int, 4, "dyadic Gaussian scales from 1 px used while sampling", min=1, max=10),
        Option("final_scales", int, 8, "Gaussian scales sqrt(2) apart from sqrt(2) px in the final image", min=1,
               max=16),
        Option("final_outliers", str, "adaptive", "final outlier removal: paper (2x size, coarser only) or "
               "adaptive (1x size, both ways)", choices=OUTLIER_RULES),
        Option("zero_variance_votes", int, 2, "stopping-map votes of pixels with zero variance: "
               "0 none, 1 adaptive phase, 2 final reconstruction, 3 both", choices=(0, 1, 2, 3)),
        Option("channel_weights", str, "relative", "final reconstruction: how the scale selector sums "
               "channels, relative (each channel's error over value^2 + 0.01, the pixel's relative MSE) or "
               "absolute (plain sum, the paper); the adaptive phase always sums absolutely", choices=CHANNEL_WEIGHTS),
        Option("confirm_stops", int, 1, "final reconstruction: a raw stop of pair k counts only if pair k+1 "
               "stops too (the widest pair has none: unconfirmed); 0 never (the paper), 1 Gaussian pairs (k >= 1), "
               "2 every pair", choices=(0, 1, 2)),
        Option("variance_guard", int, 0, "final reconstruction: 1 keeps a pixel at the finer scale of a pair "
               "wherever the coarser has no less estimated variance (no outlier vote sends it coarser: thin "
               "bright geometry stays out of its dark neighbours; it costs more on the scene corpus than it "
               "saves, so it is off by default); 0 the paper", choices=(0, 1)),
        Option("risk_guard", float, RISK_RADIUS, "final reconstruction: sigma (px) of the neighbourhoods in "
               "which each pixel's scale is clamped to the maximum scale of least estimated error (the "
               "unbiased per-pixel estimates, summed): no neighbourhood ends above its pixel means' "
               "estimated error, thin geometry included; 0 off (the paper)", min=0.0),
        Option("guard_halves", int, 1, "final reconstruction: 1 has the risk guard read each pixel mean's "
               "variance as the average of s^2 / n and the estimate of its sample sequence's two prefix halves, "
               "which the selection did not see, wherever the samples' order is known (a sample log or "
               "SampleSet, an adaptive run; pixel statistics alone keep s^2 / n); 0 s^2 / n alone",
               choices=(0, 1)),
        Option("stratified_gain", int, 1, "adaptive phase: 1 scales each pixel mean's variance s^2 / n by its "
               "measured stratification gain (the halves of its sample sequence: a stratified renderer's pixel "
               "means err far less than s^2 / n), so samples go where the error is; 0 s^2 / n (the paper)",
               choices=(0, 1)),
        Option("rare_light_floor", int, 1, "adaptive phase: 1 floors each pixel mean's variance at its 5 x 5 "
               "neighbourhood's mean per-sample variance where a neighbour's samples show a rare bright "
               "component (a spotlight, a caustic: relative variance above 5), so pixels whose samples all "
               "missed it keep their share of samples; 0 the pixel's own variance (the paper)", choices=(0, 1)),
        Option("rare_threshold", float, None, nullable=True, help="adaptive phase, rare_light_floor=1: the "
               "per-sample relative variance above which a pixel's samples show a rare bright component; None "
               "(default) follows the renderer: 3 for independent samples (one hit in 4 initial samples reads 4, "
               "which 5 misses), 5 where it declares a stratified sampler (there 3 costs checker_spot: "
               "docs/adaptive.md)", min=0.0),
        Option("net_counts", int, 0, "adaptive phase: 1 spends each round in whole nets: the uniform share "
               "breadth-first (the pixels of fewest samples step up to their next power of two) and the greedy "
               "counts rounded so that every pixel's total is a power of two (a full net of a stratified "
               "sampler's sequence; mcrecon.core.nets); 0 (default) the greedy counts as they fall and the share "
               "spread uniformly (the paper: no share); -1 follows the renderer: 1 where it declares a stratified "
               "sampler (Renderer.sampler 'sobol'), 0 for independent samples (with Sobol samples whole nets cost "
               "gem more than they gain: docs/adaptive.md)", choices=(-1, 0, 1)),
        Option("rare_nets", int, 1, "adaptive phase, rare_light_floor=1: 1 (default) first raises each pixel "
               "whose neighbourhood shows a rare bright component to the power of two at or above twice its "
               "per-sample relative variance (a stratified sampler's net that holds a component found by one "
               "sample in 1/p, about two hits of independent samples; at most the budget's net per pixel), out of "
               "the round's uniform share, and where the renderer declares a stratified sampler rounds the greedy "
               "counts there to whole nets; 0 off; -1 only where the renderer declares a stratified sampler "
               "(with independent samples the greedy counts under a light that one sample in 30 to 90 finds "
               "left most pixels below uniform's: docs/adaptive.md)", choices=(-1, 0, 1)),
        Option("subpixel_exact_below", float, 0.0, "filter scales with sigma below this (px) on the 4x4 "
               "subpixel grid itself (slower; 0: pixel-level equivalent kernel)", min=0.0),
    )

    @property
    def requires(self) -> Requirements:
        # Work a run does not need is left out: 616 MB of subpixel sums at 1024^2
        # and the slowest ingestion path, unused by the pixel-level kernels.
        # the prefix halves: the final guard's second variance (offline from a log or SampleSet) and the
        # adaptive phase's stratification gain
        p = self.params
        return Requirements(subpixels=self.grid if p["subpixel_exact_below"] > 0 else 0,
                            reference="required" if p["oracle"] else "none",
                            prefix_halves=bool(p["guard_halves"] and p["risk_guard"] > 0) or bool(p["stratified_gain"]))

    def halo(self, width, height):
        # largest final filter's pixel-kernel radius + the largest outlier-removal
        # kernel's radius (twice the scale under the paper's rule) + 1 for the 3x3
        # variance fill-in + the risk guard's neighbourhood (its selections and
        # estimates): 49 + 49 + 1 + 24 = 123 px by default, 147 px with 'paper'
        from ...filters.gaussian import TRUNCATE, gaussian_kernel, pixel_kernel
        sig = final_sigmas(self.params["final_scales"])
        factor = 2.0 if self.params["final_outliers"] == "paper" else 1.0
        r_filter = max((pixel_kernel(s_, self.grid).size - 1) // 2 for s_ in sig)
        r_vote = max((gaussian_kernel(factor * s_, truncate=TRUNCATE).size - 1) // 2 for s_ in sig)
        rg = self.params["risk_guard"]
        r_guard = (gaussian_kernel(rg, truncate=TRUNCATE).size - 1) // 2 if rg > 0 else 0
        return int(r_filter + r_vote + 1 + r_guard)

    # ---------------------------------------------------------------- core
    def start(self, width, height, channels=("R", "G", "B"), *, reference=None) -> "GEMRun":
        run = super().start(width, height, channels, reference=reference)
        if reference is not None:
            ref = np.asarray(reference, dtype=np.float64)
            if ref.ndim == 2:
                ref = ref[..., None]
            expect = (int(height), int(width), len(run.channels))
            if ref.shape != expect:
                raise InputError(_WHERE, "reference", f"shape {ref.shape}, expected {expect}")
            run.reference = ref
        return run

    def select(self, run: "GEMRun", stats: PixelStats, *, final: bool, want_mse: bool = False,
               gain: np.ndarray | None = None, strata=None, rare_threshold: float | None = None) -> GEMSelection:
        """GEM's scale selection on ``stats``: the final reconstruction's (``final``) or the sampling phase's.

        ``gain`` (H, W), optional: the pixel means' stratification gain, which scales their variance.
        ``strata`` (:class:`~mcrecon.core.strata.PrefixHalves` of the same samples), optional: the
        final risk guard's second variance estimate (option ``guard_halves``).
        ``rare_threshold``: the rare-component gate of the adaptive phase's floor (None:
        :data:`~mcrecon.core.safeguard.RARE_THRESHOLD`; :meth:`place` reads the option and the sampler).
        """
        p = self.params
        sig = final_sigmas(p["final_scales"]) if final else adaptive_sigmas(p["adaptive_scales"])
        base = stats.mean
        mv = mean_variance_policy(stats)
        count = stats.count
        if not final and p["rare_light_floor"]:
            # pixels whose few samples all missed a rare bright component its neighbours found
            # read a variance near 0 and would get no samples (rare_component_variance)
            mv = rare_component_variance(mv, base, count, threshold=RARE_THRESHOLD if rare_threshold is None
                                         else rare_threshold)
        if gain is not None:
            mv = mv * gain[..., None]
        s = self.grid
        eb = p["subpixel_exact_below"]
        sub = filled_subpixels(stats) if (eb > 0 and stats.subpixels and np.any(sig < eb)) else None
        if p["oracle"]:
            ref = run.reference
            if ref is None:
                raise InputError(_WHERE, "oracle", "oracle=1 needs a reference image (the run's "
                                 "reference, e.g. adapt(..., reference=...)); use oracle=0 without one")
            if ref.shape != base.shape:
                raise InputError(_WHERE, "reference", f"shape {ref.shape}, expected {base.shape}")
            sel = oracle_select(base, mv, count, sig, ref, subpixels=s, sub=sub, exact_below=eb,
                                channel_weights=p["channel_weights"] if final else "absolute")
        else:
            sel = gem_select(base, mv, count, sig, gamma=p["gamma"], final=final, subpixels=s,
                             want_mse=want_mse, sub=sub, exact_below=eb, outlier_rule=p["final_outliers"],
                             zero_variance_votes=bool(p["zero_variance_votes"] & (2 if final else 1)),
                             channel_weights=p["channel_weights"] if final else "absolute",
                             confirm_stops=p["confirm_stops"] if final else 0,
                             variance_guard=bool(p["variance_guard"]) and final,
                             risk_radius=p["risk_guard"] if final else 0.0,
                             guard_variance=strata.mean_variance(count)
                             if final and strata is not None and p["guard_halves"] else None)
        # The maps are built when asked for (diagnostics()): a planning round
        # would otherwise spend ~5 % of its time on images nobody reads.
        run.diagnostics = {}
        run.pending = (sel.selected, sel.stops_raw, sel.stops, sel.mse, sel.image, stats.count.copy())
        return sel

    def diagnostics(self, run: "GEMRun"):
        """Maps of the run's last reconstruction or planning step: ``selected_scale``,
        ``sample_density``, ``stop_k`` / ``stop_raw_k`` (after confirmation and
        outlier removal / the test itself, before both) and, when sampling,
        ``est_rel_mse``."""
        if run.pending is not None:
            selected, stops_raw, stops, mse, image, count = run.pending
            d = {"selected_scale": selected.astype(np.float64),
                 "sample_density": count.astype(np.float64)}
            if stops is not None:
                for k in range(stops.shape[0]):
                    d[f"stop_{k}"] = stops[k].astype(np.float64)
                    d[f"stop_raw_{k}"] = stops_raw[k].astype(np.float64)
            if mse is not None:
                rel, _ = sample_priority(mse, image, np.ones(selected.shape), 1)
                d["est_rel_mse"] = np.where(np.isfinite(rel), rel, np.nan)
            run.diagnostics = d
            run.pending = None
        return super().diagnostics(run)

    # ------------------------------------------------------------- offline
    def reconstruct_run(self, run: "GEMRun", inputs: MethodInputs) -> np.ndarray:
        """Final reconstruction (Sec. 6): (H, W, C) float64.

        Statistics without a subpixel grid work too (the default filters
        need only pixel means).  Pixels without a sample anywhere in the
        coarsest filter's support take their nearest sampled neighbour's
        value (:func:`mcrecon.core.fill.fill_empty_pixels`, with a warning).
        With ``oracle=1`` the run's reference (``inputs.reference`` or the
        one given to :meth:`start`) gives the true bias.  With
        ``inputs.strata`` (the prefix halves of a log's or SampleSet's
        samples, or of an adaptive run's) the risk guard also reads them
        (option ``guard_halves``).
        """
        if run.reference is None and inputs.reference is not None:
            run.reference = self.start(run.width, run.height, run.channels, reference=inputs.reference).reference
        strata = inputs.strata if self.params["guard_halves"] else None
        sel = self.select(run, inputs.stats, final=True, strata=strata)
        img = sel.image
        no_data = sel.bank.weight[-1] <= 0
        if no_data.any():
            from ...core.fill import fill_empty_pixels
            img = fill_empty_pixels(img, (~no_data).astype(np.int64), source=_WHERE)
        return np.asarray(img, dtype=np.float64)

    # ------------------------------------------------------------ adaptive
    def plan(self, run: "GEMRun", state: AdaptiveState):
        """The next round (:meth:`Method.plan`): a pixel's rare-component floor first, then the greedy
        distribution and the uniform share, for independent samples filled from the lowest counts up
        (``uniform_fill``).

        The greedy distribution ranks a pixel by its selected filter's expected MSE reduction, which is
        small where a few noisy samples selected a coarse filter, however large the pixel's error (the
        fine checker under checker_spot's rare light): such pixels fall behind round after round, and
        an even share leaves them behind; filled from the bottom, the share raises them first.  With a
        stratified sampler a level between two nets buys little and the share stays even; there
        (``rare_nets``) a pixel whose neighbourhood shows a rare component is first raised to the net
        that holds it (:func:`~mcrecon.core.nets.rare_net_floor`): below it the pixel mean misses or
        doubles the component whatever its variance reads, and past it the greedy counts go in whole
        nets (the samples past a net buy little until the next).  Independent samples get the same floor
        (about two hits of the component; their greedy counts fall as they are): under a light that one
        sample in tens finds every pixel's estimates are that light's noise, and the greedy counts left
        most pixels below a uniform render's.  The floors' samples count against
        the round's uniform share; a round the floors exceed goes to them, from the bottom, but with a stratified
        sampler for a part (:data:`UNHELD_SHARE` of their part of the uniform share) that the pixels no floor holds
        keep, from their lowest counts up.  While the
        samples show no structure beyond noise (:func:`~mcrecon.core.nets.shows_structure`), no
        ``target_rel_mse`` is set and the variant is not the paper's, the round is uniform (:func:`~mcrecon.core.nets.even_round`).
        """
        p = self.params
        if p["target_rel_mse"] is None and noise_only(self, state):
            return even_plan(self, state)
        nets = p["net_counts"]
        stratified = state.sampler != "independent"
        floors = p["rare_nets"] == 1 or (p["rare_nets"] == -1 and stratified)
        fill = p["uniform_fill"] or ("even" if stratified else "lowest")
        if nets == 1 or (nets == -1 and stratified) or (fill == "even" and not floors):
            return super().plan(run, state)
        n = self.round_size(state)
        if n is None:
            return None
        current = counts_with_pending(state)
        floor = np.zeros(current.shape, np.int64)
        if floors and p["rare_light_floor"]:
            floor = state_rare_net_floor(state, threshold=self.rare_gate(state))
        deficit = np.maximum(floor - current, 0)
        d = int(deficit.sum())
        if d >= n:
            free = floor == 0
            k = int(round(UNHELD_SHARE * p["uniform_share"] * n * np.mean(free))) if stratified else 0
            unheld = np.zeros(current.shape, np.int64)
            if k > 0:
                unheld = fill_lowest(current, k, state.rng, cap=np.where(free, current + k, current))
            return state.request(counts=unheld + fill_lowest(current + unheld, n - k, state.rng,
                                                             cap=current + unheld + deficit))
        n_share = max(int(round(p["uniform_share"] * n)) - d, 0)
        placed = self.place(run, state, n - d - n_share)
        if placed is None:
            return None
        placed = np.asarray(placed)
        if placed.shape != current.shape:                   # nothing placed (an empty position list)
            placed = np.zeros(current.shape, np.int64)
        held = floor > 0
        if stratified and held.any():
            # past a rare component's net a pixel's samples buy little until the next net: whole nets there
            placed = np.where(held, 0, placed) + net_counts(np.where(held, placed, 0), current + deficit)
        if fill == "lowest":
            share = fill_lowest(current + deficit, n_share, state.rng)
        else:
            share = uniform_counts(state.width, state.height, n_share, state.rng)
        return state.request(counts=deficit + placed + share)

    def rare_gate(self, state: AdaptiveState) -> float:
        """The adaptive floor's rare-component gate: the ``rare_threshold`` option, or with None the sampler's.

        One hit in a pixel's 4 initial independent samples reads a relative variance of 4, which a gate
        of 5 misses; with stratified samples a gate of 3 costs checker_spot more than it gains
        (docs/adaptive.md).
        """
        thr = self.params["rare_threshold"]
        if thr is not None:
            return float(thr)
        return RARE_THRESHOLD if state.sampler != "independent" else RARE_THRESHOLD_INDEPENDENT

    def place(self, run: "GEMRun", state: AdaptiveState, n: int):
        """One adaptive iteration (Secs. 5, 6): ``n`` samples as counts per pixel, or None at ``target_rel_mse``.

        :meth:`Method.plan` sizes the round (iteration i sends
        ``remaining // (iterations - i)``, the last everything left) and
        spreads ``uniform_share`` of it uniformly.  Pipelined
        (``state.pending``: the round in flight, not in the statistics),
        the priorities count the pending samples as if they were taken:
        each pixel's selected filter gets its effective sample count with
        them (:func:`pending_n_eff`), and its variance shrinks accordingly
        (MSE = bias^2 + Var, Var ~ 1 / n_s), so a round does not pick the
        pixels the round in flight already serves.
        """
        p = self.params
        npix = state.width * state.height
        n_pick = p["samples_per_pick"] or max(1, int(round(state.budget / npix)))
        gain = stratified_gain(state) if p["stratified_gain"] else None
        sel = self.select(run, state.stats, final=False, want_mse=True, gain=gain, rare_threshold=self.rare_gate(state))
        value = run.reference if p["oracle"] else sel.image
        if p["target_rel_mse"] is not None and np.isfinite(sel.mse).all():
            est = float(np.mean(sel.mse / (value * value + TARGET_EPS)))
            if est <= p["target_rel_mse"]:
                return None
        # A share of the round goes uniformly (a departure from the paper, measured in
        # docs/methods/gem.md): where the estimates point at the wrong pixels (depth of
        # field: edges the blur removed) no pixel is starved of samples.
        if n <= 0:
            return np.zeros((0, 2))
        return self.place_greedy(sel, value, state, n, n_pick)

    def place_greedy(self, sel: GEMSelection, value: np.ndarray, state: AdaptiveState, n: int,
                     n_pick: int) -> np.ndarray:
        """Samples per pixel (H, W) of ``n`` samples by Sec. 5's greedy distribution over the selection ``sel``.

        Priorities from the selected filters' estimated MSE relative to
        ``value`` (the selection's image, or the reference for the oracle);
        pipelined, the pending samples are counted as taken (:func:`_with_pending`).
        """
        n_eff = _pick(sel.bank.n_eff, sel.selected)
        mse = sel.mse
        if state.pending is not None and np.any(state.pending):
            mse, n_eff = _with_pending(sel, state.stats.count, state.pending, n_eff, self.grid)
        _, pri = sample_priority(mse, value, n_eff, n_pick)
        # counts, not positions: the renderer places them, continuing each pixel's own sequence
        return distribute_samples(pri, sel.selected, sel.bank.sigmas, n, n_pick, state.rng, subpixels=self.grid,
                                  as_counts=True)


def _with_pending(sel, count, pending, n_eff, subpixels):
    """(MSE, n_s) of each pixel's selected filter once the pending samples are in.

    n_s' is the effective count of the filter with ``count + pending``
    samples per pixel; the variance part of the MSE scales by n_s / n_s'
    (each filtered variance is a weighted sum of sigma^2 / n_q).  Pixels
    without samples keep MSE inf (they keep the first priority).
    """
    n_new = _pick(pending_n_eff(count, pending, sel.bank.sigmas, subpixels=subpixels), sel.selected)
    var_sel = _pick(sel.bank.var, sel.selected)
    ratio = np.divide(n_eff, n_new, out=np.ones_like(n_new), where=n_new > 0)
    mse = sel.mse - var_sel * (1.0 - ratio)[..., None]
    return np.maximum(mse, 0.0), np.maximum(n_new, n_eff)
