"""The ``splat`` method: progressive splatting behind the method contract (Suykens and Willems 2000)."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np

from ...errors import InputError, McreconWarning
from ...core.nets import round_cap_spp
from ...core.requests import SampleBatch, SampleRequest
from ...core.samples import check_policy, source_name
from ..base import AdaptiveState, Method, MethodInputs, Option, Requirements, RunState, variant_option
from .kernels import BOUNDARY_MODES
from .progressive import FEATURE_GATES, GUIDES, NORMS, SPREADS, ProgressiveSplatter
from .schedule import _next_round, _select_by_rank, doubling_schedule

__all__ = ["SplatMethod", "SplatRun"]


@dataclasses.dataclass(eq=False)
class SplatRun(RunState):
    """Per-run state of :class:`SplatMethod`: the progressive splatter and the round schedule so far."""

    splatter: ProgressiveSplatter | None = None
    prev_spp: float | None = None
    spp_done: float = 0.0
    n_rounds_seen: int = 0


class SplatMethod(Method):
    """Progressive variable-width Epanechnikov splatting (Suykens and Willems 2000).

    Options (keyword-only; also the CLI flags and ``mcrecon methods splat``):
    :attr:`options`.

    Notes
    -----
    The method declares ``requires.samples``: it filters individual
    samples.  Adaptive runs: ``plan`` asks every pixel for the same count
    each round, N_j = 2 N_{j-1} from ``initial_spp``, the last round
    absorbing the remainder, that last round split to leave 1/8 of the budget
    (not below 2^20 samples) to a last round of its own (not the paper's
    variant); a pipelined run plans
    before it observes (:attr:`plans_before_observe`); budgets below one sample per pixel are
    refused and a remainder of fewer samples than pixels is left unspent
    (Eq. 3 assumes an even sample density).  ``observe`` splats each
    committed round.  Offline (``inputs.samples``, a sample source such as
    a log): its rounds are replayed in order; a single-round source is
    split into doubling pseudo-rounds by each pixel's sample order (paper)
    or taken as one round (robust: every sample judged against all).

    References
    ----------
    .. [1] F. Suykens and Y. D. Willems, "Adaptive Filtering for Progressive
       Monte Carlo Image Rendering", WSCG 2000 (Eqs. 3, 4, 8; Fig. 3; Sec. 5).
    """

    name = "splat"
    run_type = SplatRun
    #: Pipelines by default: the schedule is uniform doubling rounds, which the plan
    #: reads from the rounds observed plus the one in flight (``state.pending``), so
    #: a pipelined run asks for the same rounds and splats the same samples as a
    #: sequential one (bit-identical images, tested).
    pipeline = True
    #: A pipelined run plans the next round before it observes the one it commits (the plan with a
    #: round in flight reads only the counts: :func:`mcrecon.adaptive.rounds.plans_before_observe`), so
    #: the renderer renders it while the round is splatted: the same requests and image.
    plans_before_observe = True
    adaptive = False
    #: features='optional': the samples' features, when the source has them, reach the default's gate
    #: (offline in the sample chunks, adaptive in the committed rounds); no statistics are built for it.
    requires = Requirements(samples=True, statistics=False, features="optional")
    #: ``paper``: every sample splatted with Eq. 8 widths (Suykens and Willems
    #: 2000 as published).  ``robust`` (default): the excess of outliers spread
    #: guided by the local mean, consistent samples gated by the pixels' statistics
    #: (docs/methods/splat.md, "The default filters").  ``outliers``: only the
    #: excess of outliers, every consistent sample kept in its pixel.
    variants = {"robust": {"spread": "consistent", "guide": "local_mean", "c": 2.0, "alpha": 0.5,
                           "outlier_k": 2.0, "initial_spp": 16},
                "outliers": {"spread": "outliers", "guide": "local_mean", "c": 2.0, "alpha": 0.5,
                             "outlier_k": 2.0, "initial_spp": 1},
                "paper": {"spread": "all", "guide": "none", "c": 4.0, "alpha": 0.3, "initial_spp": 1}}
    options = (
        dataclasses.replace(variant_option(variants), help=(
            "algorithm variant: 'paper' presets the paper's algorithm (every sample splatted with Eq. 8's "
            "width); 'robust', the measured default, spreads the excess of outliers and the consistent "
            "samples, gated by the pixels' statistics (docs/methods/splat.md); 'outliers' spreads only the "
            "excess of outliers")),
        Option("alpha", float, 0.5, "exponent of N in the kernel width (Eq. 8), 0 < alpha <= 1",
               min=0.0, max=1.0, min_open=True,
               note="the paper uses 1.5/5; 1/5 and 1/2 are the classical extremes"),
        Option("c", float, 2.0, "kernel diameter constant C in pixels (Eq. 8; the paper: 4)", min=0.0,
               min_open=True),
        Option("c_prime", float, 8.0, "pilot kernel diameter constant C' in pixels (C' N0^-1/2)",
               min=0.0, min_open=True),
        Option("initial_spp", int, 16, "samples per pixel of the first round N0 (the paper: 1); the outlier "
               "test judges a sample once its 3x3 window holds 64 samples and only judged samples spread, so "
               "16 (8 + 8 when pipelined) judges the first round already", min=1),
        Option("min_width", float, 1.0, "smallest kernel diameter in pixels (>= 1)", min=1.0),
        Option("max_width", float, 32.0, "largest kernel diameter in pixels (cap for huge G/f; >= min_width)",
               min=1.0),
        Option("boundary", str, "mirror", "boundary-bias remedy", BOUNDARY_MODES),
        Option("norm", str, "luminance", "scalar value of a colour sample in Eq. 8", NORMS),
        Option("spread", str, "consistent", "which samples are splatted: all (the paper), outliers (only the "
               "excess of outliers above their 3x3 neighbourhood's mean + k std; the rest stays in its pixel) "
               "or consistent (as outliers, and the other samples into the pixels whose statistics match)",
               SPREADS),
        Option("outlier_k", float, 2.0, "spread='outliers': a sample is an outlier above mean + k std of "
               "the G of its 3x3 neighbourhood's samples", min=0.0),
        Option("guide", str, "local_mean", "footprint weights of the spread part: none (Epanechnikov, the "
               "paper) or local_mean (Epanechnikov times the pooled 3x3 mean of G at each pixel)", GUIDES),
        Option("false_rejection", float, 0.05, "spread='consistent': rate at which two pixels of the same "
               "expectation are told apart (sets the gate's k standard errors)", min=0.0, max=1.0,
               min_open=True, max_open=True),
        Option("spread_c", float, 8.0, "spread='consistent': Eq. 8's C (diameter in pixels at N = 1, G/f = 1) "
               "of the consistent samples' kernels", min=0.0, min_open=True),
        Option("spread_alpha", float, 0.3, "spread='consistent': Eq. 8's exponent of N for the consistent "
               "samples' kernels (the paper's 1.5/5)", min=0.0, max=1.0, min_open=True),
        Option("feature_gate", str, "auto", "spread='consistent': also refuse a pixel whose feature means "
               "(albedo, normal, depth) differ by more than k times the pixels' own feature spread (auto: when "
               "the samples carry features) or compare the colour only (none); without features both give the "
               "same image", FEATURE_GATES),
    )

    def _configure(self, params: dict) -> None:
        if params["max_width"] < params["min_width"]:
            raise InputError(self.where, "max_width", f"{params['max_width']!r}, expected >= min_width "
                             f"({params['min_width']!r})")

    def _new_splatter(self, width, height, n_channels) -> ProgressiveSplatter:
        p = self.params
        return ProgressiveSplatter(width, height, n_channels, c=p["c"], alpha=p["alpha"], c_prime=p["c_prime"],
                                   min_width=p["min_width"], max_width=p["max_width"],
                                   boundary=p["boundary"], norm=p["norm"], spread=p["spread"],
                                   outlier_k=p["outlier_k"], guide=p["guide"],
                                   false_rejection=p["false_rejection"], spread_c=p["spread_c"],
                                   spread_alpha=p["spread_alpha"], feature_gate=p["feature_gate"])

    def start(self, width, height, channels=("R", "G", "B"), *, reference=None) -> "SplatRun":
        run = super().start(width, height, channels, reference=reference)
        run.splatter = self._new_splatter(run.width, run.height, len(run.channels))
        return run

    # ------------------------------------------------------------ offline
    def halo(self, width, height):
        if self.params["spread"] == "all":
            # largest splat radius plus the pilot estimate's radius that sets it, +1 for the pixel cell
            return int(np.ceil(self.params["max_width"] / 2 + self.params["c_prime"] / 2)) + 1
        # A sample up to max_width/2 away reaches the pixel; its weights are normalised over its whole
        # footprint, whose guide (each covered pixel's 3x3 window mean) reaches max_width + 1 px away;
        # its threshold needs samples within 2 px of it (less).  +1 for the pixel cell.
        return int(np.ceil(self.params["max_width"])) + ProgressiveSplatter.POOL_RADIUS + 1

    def reconstruct_run(self, run: "SplatRun", inputs: MethodInputs) -> np.ndarray:
        """Replay the sample source's rounds in order through the progressive algorithm, its leading
        rounds merged into the method's own first round (:meth:`_replay_rounds`).

        Robust variant (``spread='outliers'``): a source with a single round
        is one round.  Paper: a source with a single round (an offline render) is split into
        pseudo-rounds N_0 = initial_spp, N_j = 2 N_{j-1}: within each pixel,
        its samples are taken in source order and the k-th of the pixel's
        ``n_p`` samples goes to the round whose share of ``n_p`` contains k
        (the schedule is built for ``m = min_p n_p`` samples per pixel and
        scaled by ``n_p / m``, so every pseudo-round samples every pixel).
        A plain order split would put image rows, not samples per pixel,
        into rounds for logs sorted by pixel.  ``inputs.nonfinite`` applies
        to NaN/Inf values (one warning with their number).
        """
        src = inputs.samples
        where = source_name(src)
        nonfinite = check_policy(inputs.nonfinite, where)
        if run.splatter.rounds or run.splatter.n_nonfinite:  # a reused run state starts over
            run.splatter = self._new_splatter(run.width, run.height, len(run.channels))
        sp = run.splatter
        rounds = [r for r, (a, b) in enumerate(src.round_slices()) if b > a]
        # the features the gate reads (spread='consistent', feature_gate='auto'), if the source has any
        feats = tuple(getattr(src, "feature_names", ())) \
            if self.params["spread"] == "consistent" and self.params["feature_gate"] == "auto" else ()
        fkw = {"features": feats} if feats else {}
        if len(rounds) >= 2:
            for group in self._replay_rounds(src, rounds):
                sp.add_round_stream(lambda g=group: _arrays(src.iter_chunks(rounds=g, with_round=False, **fkw)),
                                    nonfinite=nonfinite, where=where)
        elif rounds and self.params["spread"] != "all":
            # Robust variant: a single-round source is one round.  Every sample is judged
            # against the statistics of all samples (pseudo-rounds would judge the first
            # ones against a few spp, too few for the outlier test: MIN_POOL).
            sp.add_round_stream(lambda: _arrays(src.iter_chunks(with_round=False, **fkw)), nonfinite=nonfinite,
                                where=where)
        elif rounds:
            self._replay_single_round(src, sp, nonfinite, where)
        if sp.n_feature_zeroed:
            from ...core.features import warn_feature_zeroed

            warn_feature_zeroed(where, sp.n_feature_zeroed)
        if sp.n_nonfinite:
            warnings.warn(f"{where}: values: {sp.n_nonfinite} sample(s) with NaN or Inf "
                          f"{'dropped' if nonfinite == 'drop' else 'set to 0'} (policy nonfinite={nonfinite!r})",
                          McreconWarning, stacklevel=2)
        self._set_diagnostics(run)
        if not rounds:
            warnings.warn(f"{where}: no samples at all; the image is 0", McreconWarning, stacklevel=2)
        return sp.image.copy()

    def _replay_rounds(self, src, rounds: list[int]) -> list[list[int]]:
        """The source's non-empty rounds grouped into the rounds to replay, in order.

        The leading rounds are merged until they hold the first round of the
        method's own adaptive run, ``(N_0 + 1) // 2`` samples per pixel with
        ``N_0 = min(initial_spp, total spp)`` (the driver's split initial
        pass); every later round is replayed as it is.  Fig. 3 never revisits
        a round, and the outlier test judges a sample only once its 3x3
        window holds ``MIN_POOL`` samples: a renderer that writes one round
        per sample index (Cycles' sample subsets) would otherwise leave its
        first rounds' fireflies unjudged in their pixels for good.  A log of
        the method's own run starts with that round and replays as it ran.
        """
        sl = src.round_slices()
        pixels = int(src.width) * int(src.height)
        total = sum(int(sl[r][1] - sl[r][0]) for r in rounds)
        n0 = min(int(self.params["initial_spp"]), total // pixels)
        first = (n0 + 1) // 2 * pixels
        groups: list[list[int]] = [[]]
        held = 0
        for r in rounds:
            if held >= first and groups[-1]:  # under one sample per pixel (first = 0): no empty round
                groups.append([])
            groups[-1].append(r)
            held += int(sl[r][1] - sl[r][0])
        return groups

    @staticmethod
    def _pixel_index(pos, width, height):
        ix = np.clip(np.floor(pos[:, 0]).astype(np.int64), 0, width - 1)
        iy = np.clip(np.floor(pos[:, 1]).astype(np.int64), 0, height - 1)
        return iy * width + ix

    def _replay_single_round(self, src, sp, nonfinite, where):
        w, h = src.width, src.height
        n_p = np.zeros(w * h, np.int64)
        for ch in src.iter_chunks(with_round=False):
            n_p += np.bincount(self._pixel_index(np.asarray(ch.positions), w, h), minlength=w * h)
        m = int(n_p.min())
        if m == 0:
            # Some pixel has no sample at all: schedule for the mean count.
            m = max(1, int(n_p.sum() // (w * h)))
        sched = doubling_schedule(m, min(self.params["initial_spp"], m))
        ends = np.cumsum(sched)
        bounds = [np.zeros(w * h, np.int64)] + [(int(t) * n_p) // m for t in ends]
        bounds[-1] = n_p  # the last round takes every remaining sample of every pixel

        def pseudo_round(j):
            rank = np.zeros(w * h, np.int64)
            lo, hi = bounds[j], bounds[j + 1]
            for pos, val, _ in _arrays(src.iter_chunks(with_round=False)):
                pos = np.asarray(pos)
                mask = np.empty(pos.shape[0], np.bool_)
                _select_by_rank(self._pixel_index(pos, w, h), rank, lo, hi, mask)
                if mask.any():
                    yield pos[mask], np.asarray(val)[mask]

        for j in range(len(sched)):
            sp.add_round_stream(lambda j=j: pseudo_round(j), nonfinite=nonfinite, where=where)

    # ----------------------------------------------------------- adaptive
    def initial_pass(self, budget: int, pixels: int) -> int:
        """N_0 = ``initial_spp`` (capped by the budget); a budget below one sample per pixel is refused."""
        if budget // pixels < 1:
            raise InputError(self.where, "spp", f"budget of {budget} samples is below one sample per "
                             f"pixel ({pixels} pixels): splatting rounds sample every pixel")
        return min(self.params["initial_spp"], budget // pixels)

    def plan(self, run: "SplatRun", state: AdaptiveState) -> SampleRequest | None:
        """Every pixel gets N_j samples: N_0 = initial_spp, N_j = 2 N_{j-1}, the last round absorbing the rest.

        Pipelined (``state.pending``): the round in flight (every pixel the
        same count) is the previous round of the schedule, and what is left
        is the budget less the samples committed and in flight; the rounds
        asked for are those of a sequential run (unless NaN/Inf samples were
        dropped: the schedule then counts the requested samples).  That plan
        reads nothing ``observe`` keeps (:attr:`plans_before_observe`).
        """
        p_film = state.width * state.height
        if state.pending is not None:
            prev = int(state.pending.sum()) / p_film
            # every round samples every pixel alike: what the budget leaves in whole spp (the observed
            # count of a sequential run, min(total - done, remaining), is never below it)
            rem = state.remaining // p_film
        else:
            prev = run.prev_spp
            rem = min(state.budget // p_film - int(round(run.spp_done)), state.remaining // p_film)
        if rem < 1:
            return None
        n = _next_round(rem, prev, self.params["initial_spp"])
        if n == rem and self.params["spread"] != "all":
            n = self._before_last(rem, state.budget, p_film)
        return state.request(counts=np.full((state.height, state.width), n, np.int64))

    def _before_last(self, rem: int, budget: int, p_film: int) -> int:
        """The default's and outliers' last doubling round: ``rem`` spp split into ``rem - cap`` and a last
        round of ``cap``, box's cap (:meth:`Method.doubling_round`: 1 / ``max_round_parts`` of the budget in
        whole spp, not below ``max_round_floor`` samples) when ``rem`` holds two of them, so that the
        round splatted after the renderer has finished is not half the budget; one round more only (a
        round costs the gated splat a pass per pixel).  The paper's doubling is not split."""
        cap = round_cap_spp(budget, p_film, self.max_round_parts, self.max_round_floor)
        return rem - cap if rem >= 2 * cap else rem

    def observe(self, run: "SplatRun", batch: SampleBatch, round_index: int) -> None:
        """Splat a committed round.

        The driver calls it with a committed round after its NaN/Inf policy:
        validated arrays with finite values, which the splatter takes without
        checking them again (``add_round(..., checked=True)``).
        """
        pos = np.asarray(batch.positions)
        val = np.asarray(batch.values)
        if val.ndim == 1:
            val = val[:, None]
        run.n_rounds_seen += 1
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", McreconWarning)
            run.splatter.add_round(pos, val, features=batch.features or None, nonfinite="drop", where=self.where,
                                   checked=True)
        run.prev_spp = pos.shape[0] / (run.width * run.height)
        run.spp_done += run.prev_spp

    def finish(self, run: "SplatRun", state: AdaptiveState) -> np.ndarray:
        """The running image f_J (a copy)."""
        self._set_diagnostics(run)
        if not run.splatter.rounds:
            warnings.warn("method splat: no round observed; the image is 0", McreconWarning, stacklevel=2)
        return run.splatter.image.copy()

    @staticmethod
    def _set_diagnostics(run: "SplatRun") -> None:
        run.diagnostics["kernel_width"] = run.splatter.last_widths.copy()


def _arrays(chunks):
    """(positions, values, features or None) of each chunk of a sample source."""
    for ch in chunks:
        yield ch.positions, ch.values, (getattr(ch, "features", None) or None)
