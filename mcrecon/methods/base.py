"""The contract every reconstruction / adaptive-sampling method implements.

A method is a class registered in :mod:`mcrecon.methods` under a short
name.  It is built with keyword-only options (validated in ``__init__``
with messages that list the valid values) and then used in two ways:

Offline
    ``reconstruct_log(log)`` (default: stream the log into
    :class:`~mcrecon.stats.PixelStats` with the subpixel grid the method
    asks for, then ``reconstruct(stats)``).

Adaptive (driven by :func:`mcrecon.driver.adapt`)
    Round 0: ``plan(state)`` with empty statistics returns the initial
    request.  After every round the driver validates the renderer's reply,
    commits it to the log, merges it into ``state.stats`` and calls
    ``observe(batch, round_index)``; then ``plan(state)`` again, until it
    returns ``None`` (the method's own target is met), the budget or the
    time limit is reached.  Finally ``finish(state)`` returns the image.

Resume contract: ``plan`` may depend only on the options, ``state``
(statistics of every committed sample, round index, budget, the round's
RNG) and on what ``observe`` saw.  A resumed run rebuilds the statistics
from the log and replays ``observe`` for each committed round in order,
so it continues exactly where the killed run stopped.
"""

from __future__ import annotations

import dataclasses
from typing import Any, ClassVar, Mapping, Sequence

import numpy as np

from ..errors import InputError
from ..protocol import SampleBatch, SampleRequest
from ..stats import PixelStats

__all__ = ["Method", "AdaptiveState", "Option", "uniform_counts"]


@dataclasses.dataclass(frozen=True)
class Option:
    """A method option exposed on the CLI as ``--NAME`` (``_`` shown as ``-``).

    ``type`` is a callable converting the command-line string
    (``float``, ``int``, ``str``); ``choices`` lists valid values.
    """

    name: str
    type: Any
    default: Any
    help: str
    choices: Sequence[Any] | None = None


@dataclasses.dataclass(eq=False)
class AdaptiveState:
    """What a method sees when it plans the next round.

    Attributes
    ----------
    stats : PixelStats
        Statistics of every committed sample (subpixel grid as the method
        asked for).
    round_index : int
        Index of the round being planned (0 = initial pass).
    budget : int
        Total sample budget of the run (average spp x pixels).
    n_samples : int
        Samples committed so far.
    rng : numpy.random.Generator
        Random numbers for this round's decisions, derived from the run's
        seed and the round index (reproducible, resumable).
    reference : ndarray (H, W, C) or None
        Ground truth when the run has one (oracle modes, experiments).
    """

    stats: PixelStats
    round_index: int
    budget: int
    n_samples: int
    rng: np.random.Generator
    reference: np.ndarray | None = None

    @property
    def remaining(self) -> int:
        return max(int(self.budget) - int(self.n_samples), 0)

    @property
    def width(self) -> int:
        return self.stats.width

    @property
    def height(self) -> int:
        return self.stats.height

    def request(self, *, counts=None, positions=None) -> SampleRequest:
        """A request for this round (the driver sets the renderer seed)."""
        return SampleRequest(self.width, self.height, counts=counts, positions=positions,
                             round_index=self.round_index)

    def uniform_request(self, spp: float) -> SampleRequest:
        """``spp`` samples per pixel spread uniformly (at most what the budget has left)."""
        n = min(self.remaining, int(spp * self.width * self.height))
        return self.request(counts=uniform_counts(self.width, self.height, n, self.rng))


def uniform_counts(width: int, height: int, n: int, rng: np.random.Generator) -> np.ndarray:
    """Spread ``n`` samples as evenly as possible: every pixel gets ``n // P``,
    ``n % P`` random pixels one more."""
    p = width * height
    counts = np.full(p, n // p, np.int64)
    extra = n % p
    if extra:
        counts[rng.choice(p, size=extra, replace=False)] += 1
    return counts.reshape(height, width)


class Method:
    """Base class: uniform sampling in doubling rounds, subclasses reconstruct.

    Class attributes
    ----------------
    name : str
        Registry name.
    options : tuple of Option
        Keyword options (and CLI flags).
    subpixels : int
        Subpixel grid the method needs in its statistics (0 = none).
    adaptive : bool
        Whether ``plan`` distributes samples by itself (else uniform).
    """

    name: ClassVar[str] = "?"
    options: ClassVar[tuple[Option, ...]] = ()
    subpixels: ClassVar[int] = 0
    adaptive: ClassVar[bool] = False

    #: Uniform sampling: spp of the first round, later rounds double the total.
    initial_spp: ClassVar[int] = 1

    def __init__(self, **options):
        known = {o.name: o for o in self.options}
        unknown = sorted(set(options) - set(known))
        if unknown:
            raise InputError(f"method {self.name}", unknown[0],
                             f"unknown option; valid: {', '.join(known) or '(none)'}")
        self.params = {}
        for name, opt in known.items():
            value = options.get(name, opt.default)
            if value is not None and opt.choices is not None and value not in opt.choices:
                raise InputError(f"method {self.name}", name,
                                 f"{value!r} is not valid; valid: {', '.join(map(str, opt.choices))}")
            self.params[name] = value
        self._diagnostics: dict[str, np.ndarray] = {}

    # -------------------------------------------------------------- offline
    def reconstruct(self, stats: PixelStats) -> np.ndarray:
        """Reconstruct an (H, W, C) float64 image from pixel statistics."""
        raise NotImplementedError

    def reconstruct_log(self, log, *, nonfinite: str = "drop") -> np.ndarray:
        """Reconstruct from a sample log (path or SampleLog)."""
        stats = PixelStats.from_log(log, subpixels=self.subpixels, nonfinite=nonfinite)
        return self.reconstruct(stats)

    # ------------------------------------------------------------- adaptive
    def plan(self, state: AdaptiveState) -> SampleRequest | None:
        """Next round's request, or None when the method's target is met.

        Default: uniform rounds, ``initial_spp`` first, then each round
        doubles the total, the last one filling the budget exactly.
        """
        remaining = state.remaining
        if remaining <= 0:
            return None
        if state.n_samples == 0:
            return state.uniform_request(max(1, int(self.initial_spp)))
        n = min(remaining, state.n_samples)
        return state.request(counts=uniform_counts(state.width, state.height, n, state.rng))

    def observe(self, batch: SampleBatch, round_index: int) -> None:
        """See a committed round's samples (for methods that keep their own state)."""

    def finish(self, state: AdaptiveState) -> np.ndarray:
        """Final image of an adaptive run (default: ``reconstruct(state.stats)``)."""
        return self.reconstruct(state.stats)

    def diagnostics(self) -> Mapping[str, np.ndarray]:
        """Scalar (H, W) maps from the last reconstruct/plan (selected scale, ...)."""
        return dict(self._diagnostics)

    def describe(self) -> dict:
        return {"method": self.name, **self.params}
