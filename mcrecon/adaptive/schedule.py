"""The adaptive run's schedule: round seeds, the driver's initial pass, planning a round.
"""

from __future__ import annotations

import copy
import dataclasses

import numpy as np

from ..errors import InputError
from ..methods.base import AdaptiveState, uniform_counts



__all__ = ['round_seeds', 'STORAGE_DTYPES', 'method_pipelines']

#: Precisions a run's log can store samples in (see :func:`adapt`).
STORAGE_DTYPES = ("auto", "float32", "float64")


def round_seeds(seed: int, round_index: int) -> tuple[np.random.Generator, int]:
    """(decision RNG, renderer seed) of a round, derived from the run seed."""
    rng = np.random.default_rng([int(seed), int(round_index), 1])
    renderer_seed = int(np.random.SeedSequence([int(seed), int(round_index), 2]).generate_state(1)[0])
    return rng, renderer_seed


def _pixel_counts_of(positions, w, h) -> np.ndarray:
    """Samples per pixel (H, W) of film positions (on the film: validated)."""
    pos = np.asarray(positions)
    if pos.shape[0] == 0:
        return np.zeros((h, w), np.int64)
    idx = pos[:, 1].astype(np.int64) * w + pos[:, 0].astype(np.int64)
    return np.bincount(idx, minlength=w * h).reshape(h, w)


def _request_counts(req) -> np.ndarray:
    """Samples per pixel (H, W) a request asks for (what its reply will add)."""
    c = np.zeros((req.height, req.width), np.int64) if req.counts is None else req.counts.copy()
    if req.positions is not None:
        c += _pixel_counts_of(req.positions, req.width, req.height)
    return c


def _committed(stats) -> int:
    # Samples dropped by the non-finite policy were rendered and committed: they
    # count against the budget, or a renderer that keeps returning NaN never ends.
    return stats.n_samples + stats.n_dropped


def method_pipelines(method) -> bool:
    """Whether ``method`` plans with one round of lag by default (:func:`adapt`'s ``pipeline``):
    what its class declares (``Method.pipeline``, a bool)."""
    v = getattr(type(method), "pipeline", False)
    if not isinstance(v, bool):
        raise InputError(f"method {getattr(method, 'name', type(method).__name__)}", "pipeline",
                         f"class attribute {v!r}; expected True (plans are safe from statistics one round "
                         "old) or False")
    return v


def _initial_rounds(method, pipeline: bool, budget: int, pixels: int) -> int:
    """Rounds of the uniform initial pass the driver takes: two when pipelined and the pass has
    two or more samples per pixel (half, then the rest), else one."""
    return 2 if pipeline and method.initial_pass(budget, pixels) >= 2 else 1


def _initial_request(method, state: AdaptiveState, initial_rounds: int):
    """The driver's round of the uniform initial pass (round 0, or round 1 of a split pass)."""
    w, h = state.width, state.height
    spp = method.initial_pass(state.budget, w * h)
    if state.round_index == 0:
        return state.uniform_request((spp + 1) // 2 if initial_rounds == 2 else spp)
    n = min(state.remaining, spp * w * h - state.n_samples)
    return state.request(counts=uniform_counts(w, h, max(n, 0), state.rng))


def _with_seed(req, round_index, seed, first_index=None):
    """``req`` with its round index, renderer seed and per-pixel first sample index, without validating it
    again (``first_index`` is the driver's own count, (H, W) int64).

    (``dataclasses.replace`` would re-run ``SampleRequest.__post_init__``: the
    method built the request through its constructor, which checked it.)
    """
    out = copy.copy(req)
    object.__setattr__(out, "round_index", int(round_index))
    object.__setattr__(out, "seed", int(seed))
    if first_index is not None:
        object.__setattr__(out, "first_index", np.array(first_index, np.int64))  # a copy: the count goes on
    return out


@dataclasses.dataclass(frozen=True)
class Committed:
    """What a plan knows of the committed samples beyond their statistics: their prefix halves
    (:class:`~mcrecon.core.strata.PrefixHalves`, methods with ``stratified_gain`` on) and the renderer's
    sampler (:data:`~mcrecon.core.requests.SAMPLERS`, its declaration)."""

    strata: object = None
    sampler: str = "independent"


def _adaptive_state(stats, schedule, round_index, n_samples, rng, *, pending=None,
                    initial_rounds=1, committed: Committed = Committed()) -> AdaptiveState:
    """The state a plan (or the final image) sees; ``iteration`` counts from the end of ``initial_rounds``."""
    return AdaptiveState(stats, round_index, schedule.budget, n_samples, rng, schedule.reference, pending=pending,
                         iteration=max(int(round_index) - int(initial_rounds), 0), strata=committed.strata,
                         sampler=committed.sampler)


@dataclasses.dataclass(frozen=True, eq=False)
class Schedule:
    """What decides a run's rounds: its budget, seed, the driver's initial pass and when it stops.

    The same in a live run and in its resume (only ``time_limit`` may be
    given again), so a plan depends on the committed statistics alone.

    Attributes
    ----------
    budget : int
        Samples of the whole run (``round(spp * W * H)``).
    seed : int
        The run seed (:func:`round_seeds`).
    initial_rounds : int
        Rounds of the driver's uniform initial pass (:func:`_initial_rounds`).
    reference : ndarray (H, W, C) or None
        Ground truth the plans see (oracle modes) and the per-round error uses.
    max_rounds : int
        No round with this index or later starts.
    time_limit : float or None
        Wall seconds of the run (over its sessions); no round starts after it.
    pipeline : bool
        Pipelined rounds (see :func:`mcrecon.adaptive.adapt`).
    """

    budget: int
    seed: int
    initial_rounds: int = 1
    reference: np.ndarray | None = None
    max_rounds: int = 10_000
    time_limit: float | None = None
    pipeline: bool = False

    def plan(self, method, run, stats, round_index, n_total, *, pending=None, first_index=None,
             committed: Committed = Committed()):
        """(request with its seeds, None) or (None, why the run stops) for round ``round_index``.

        ``n_total``: samples committed plus in flight (``pending``, per pixel).
        ``first_index`` (H, W): the request's per-pixel first sample index (committed plus in flight).
        ``committed``: the committed samples' prefix halves and the renderer's sampler (:class:`Committed`).
        The rounds of the initial pass are the driver's own; later ones the
        method's plan.  Depends only on its arguments: the same in a live run
        and in a resume.  ``(None, "wait")``: with a round in flight the plan
        asked for nothing (the round in flight is committed first, then this
        round is planned again without ``pending``).
        """
        if n_total >= self.budget:
            return None, "budget"
        rng, rseed = round_seeds(self.seed, round_index)
        state = _adaptive_state(stats, self, round_index, n_total, rng, pending=pending,
                                initial_rounds=self.initial_rounds, committed=committed)
        if round_index < self.initial_rounds:
            req = _initial_request(method, state, self.initial_rounds)
        else:
            req = method.plan(run, state)
        if req is None:
            return None, "converged"
        if req.total == 0:
            return None, ("wait" if pending is not None else "converged")
        if req.total > state.remaining:
            raise RuntimeError(f"method {method.name} planned {req.total} samples with only "
                               f"{state.remaining} left in the budget (a bug in the method)")
        return _with_seed(req, round_index, rseed, first_index), None

    def final_state(self, stats, round_index, rng, *, committed: Committed = Committed()) -> AdaptiveState:
        """The state the image after round ``round_index - 1`` is made from (``method.finish``)."""
        return _adaptive_state(stats, self, round_index, _committed(stats), rng, committed=committed)
