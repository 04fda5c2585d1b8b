"""The contract every reconstruction / adaptive-sampling method implements.

A method is configuration plus a per-run state, taught as eight concepts in
``docs/methods/writing-a-method.md``:

1. **Options** -- :class:`Option` descriptions, validated once here; the object is immutable afterwards
   (variants: :func:`variant_option`).
2. **Inputs** -- :attr:`Method.requires`, a :class:`Requirements`; the reader or the driver supplies them as
   :class:`MethodInputs`.  A method never opens a file (no module in ``mcrecon.methods`` imports the I/O layer).
3. **Run state** -- :attr:`Method.run_type`, a :class:`RunState` subclass created once per run by
   :meth:`Method.start`.
4. **Reconstruction** -- :meth:`Method.reconstruct_run`.
5. **Placement** -- :meth:`Method.place` (the round sized by :meth:`Method.plan`, which a method may replace).
6. **Initial pass** -- :meth:`Method.initial_pass`: the driver takes it, so a plan never sees empty statistics.
7. **Pipelining** -- :attr:`Method.pipeline`: plans safe from statistics one round old
   (``AdaptiveState.pending``: the round in flight).
8. **Samples as they come** -- :meth:`Method.observe` (methods that declare ``requires.samples``) and
   :meth:`Method.finish`.

Resume contract: a plan may depend only on the options, the run state and the :class:`AdaptiveState`
(statistics of every committed sample, round index, budget, the round's RNG).  A resumed run rebuilds the
statistics from the log and, for methods that observe samples, replays ``observe`` for each committed round
in order, so it continues exactly where the killed run stopped.
"""
from __future__ import annotations

import dataclasses
import math
import numbers
import types
from typing import Any, ClassVar, Mapping, Sequence

import numpy as np

from ..errors import InputError
from ..core.requests import SampleBatch, SampleRequest
from ..core.stats import PixelStats
from ..core.features import usable_layout, usable_names
from ..core.halves import Halves, as_halves, split_halves
from ..core.nets import even_plan, net_plan, noise_only, round_cap_spp
from .supply import Supply, check_supply

__all__ = ['Method', 'AdaptiveState', 'Option', 'Requirements', 'MethodInputs', 'RunState', 'uniform_counts',
           'variant_option']

_MISSING = object()


@dataclasses.dataclass(frozen=True)
class Option:
    """One keyword option of a method, and its CLI flag ``--NAME`` (``_`` shown as ``-``).

    Parameters
    ----------
    name : str
    type : {float, int, str, bool}
        Values are converted to this type (command-line strings too);
        ``int`` accepts integral numbers only.
    default : object
        Used when the option is not given.
    help : str
    choices : sequence, optional
        The valid values (after conversion).
    min, max : number, optional
        Bounds; ``min_open`` / ``max_open`` make them strict (``>`` / ``<``).
    nullable : bool
        Whether None is a valid value (defaults to True when the default is None).
    note : str, optional
        Why the bounds are what they are; appended to the error message.
    """

    name: str
    type: Any
    default: Any
    help: str
    choices: Sequence[Any] | None = None
    min: float | None = None
    max: float | None = None
    min_open: bool = False
    max_open: bool = False
    nullable: bool | None = None
    note: str | None = None

    @property
    def allows_none(self) -> bool:
        return self.default is None if self.nullable is None else bool(self.nullable)

    @property
    def flag(self) -> str:
        return "--" + self.name.replace("_", "-")

    def expectation(self) -> str:
        """What a valid value looks like, for error messages and ``--help``."""
        if self.choices is not None:
            text = "one of " + ", ".join(map(str, self.choices))
        else:
            kind = {int: "an integer", float: "a finite number", bool: "true or false",
                    str: "a string"}.get(self.type, getattr(self.type, "__name__", str(self.type)))
            lo = None if self.min is None else f"{'>' if self.min_open else '>='} {self.min:g}"
            hi = None if self.max is None else f"{'<' if self.max_open else '<='} {self.max:g}"
            if lo and hi:
                text = (f"{kind} with {self.min:g} {'<' if self.min_open else '<='} {self.name} "
                        f"{'<' if self.max_open else '<='} {self.max:g}")
            else:
                text = f"{kind} {lo or hi}" if (lo or hi) else kind
        text += " or None" if self.allows_none else ""
        return f"{text} ({self.note})" if self.note else text

    def convert(self, value, where: str):
        """The validated value, or an :class:`InputError` naming ``where``, the option and the valid values."""
        if value is None or (isinstance(value, str) and value.strip().lower() == "none" and self.allows_none):
            if self.allows_none:
                return None
            raise InputError(where, self.name, f"None, expected {self.expectation()}")
        bad = InputError(where, self.name, f"{value!r}, expected {self.expectation()}")
        t = self.type
        if t is bool:
            if isinstance(value, (bool, np.bool_)):
                v = bool(value)
            elif isinstance(value, numbers.Integral) and value in (0, 1):
                v = bool(value)
            elif isinstance(value, str) and value.strip().lower() in ("1", "true", "yes", "on", "0", "false",
                                                                       "no", "off"):
                v = value.strip().lower() in ("1", "true", "yes", "on")
            else:
                raise bad
        elif t in (int, float):
            if isinstance(value, (bool, np.bool_)):
                raise bad
            if t is int and isinstance(value, numbers.Integral):
                v = int(value)  # exactly: a float() detour would round beyond 2^53
            elif t is int and isinstance(value, str) and value.strip().lstrip("+-").isdigit():
                v = int(value.strip())
            else:
                try:
                    f = float(value.strip()) if isinstance(value, str) else float(value)
                except (TypeError, ValueError, AttributeError):
                    raise bad from None
                if not math.isfinite(f):
                    raise bad
                if t is int:
                    if f != int(f):
                        raise bad
                    v = int(f)
                else:
                    v = f
            if self.min is not None and (v <= self.min if self.min_open else v < self.min):
                raise bad
            if self.max is not None and (v >= self.max if self.max_open else v > self.max):
                raise bad
        elif t is str:
            if not isinstance(value, str):
                raise bad
            v = value
        else:
            try:
                v = t(value)
            except (TypeError, ValueError):
                raise bad from None
        if self.choices is not None and v not in self.choices:
            raise InputError(where, self.name, f"{value!r} is not valid; valid: {', '.join(map(str, self.choices))}")
        return v


def variant_option(variants: Mapping[str, Mapping[str, Any]], default: str = "robust") -> Option:
    """The ``variant`` option of a method whose defaults depart from its paper.

    ``variants`` maps each variant name to the option values it presets
    (the class attribute :attr:`Method.variants`); ``"paper"`` is the
    paper's algorithm, ``default`` the measured default.  Options given
    explicitly always win over a variant's presets.
    """
    names = tuple(variants)
    if default not in names or "paper" not in names:
        raise ValueError(f"variants {names}: need {default!r} and 'paper'")
    return Option("variant", str, default,
                  "algorithm variant: 'paper' presets every option to the paper's algorithm; "
                  f"{default!r} is the measured default (departures documented on the method's page)", names)


@dataclasses.dataclass(frozen=True)
class Requirements:
    """What a method consumes; the reader or the driver supplies it.

    Attributes
    ----------
    subpixels : int
        Subpixel grid per pixel axis the pixel statistics must keep (0: none).
    samples : bool
        The individual samples: offline a :class:`~mcrecon.core.samples.SampleSource` in ``inputs.samples``;
        in adaptive runs every committed round through ``observe`` (and replayed on resume).
    reference : {'none', 'optional', 'required'}
        Whether the method reads the reference image (oracle modes).
    statistics : bool
        Whether the method reads pixel statistics (a method that only
        filters samples sets False, and none are built for it offline).
    half_buffers : bool
        Whether the method can work from two independent *half buffers* (``inputs.halves``: two
        :class:`PixelStats` of disjoint halves of every pixel's samples, as renderers write dual buffers) in
        place of the individual samples.  With ``samples`` also True, offline reconstruction accepts either
        (:meth:`Method.reconstruct`); the statistics are then the Chan merge of the two halves
        (:func:`~mcrecon.core.halves.merge_halves`).  A half-buffer pair is refused for a method that does
        not declare it.  In adaptive runs :meth:`Method.observe` splits every committed round into the run's
        halves (``RunState.halves``), which :meth:`Method.finish` hands over as ``inputs.halves``.
    features : {'none', 'optional', 'required'}
        Whether the method reads per-sample features (albedo, normal,
        depth, ...; :mod:`mcrecon.core.features`).  With 'optional' or
        'required' the statistics and half buffers carry every feature
        the source has (``stats.features``); 'required' refuses a source
        without any.  With 'none' they carry none (and cost nothing).
    range : bool
        Whether the method reads each pixel's sample minimum and maximum
        (``stats.has_range``), which statistics from moments (an EXR) lack.
    statistics_options : tuple of (name, value)
        The option values under which the method takes pixel statistics
        alone (no samples, no half buffers, no sample range): the hook by
        which pixel-statistics files run a method whose default needs more,
        when the caller did not choose those options
        (:func:`mcrecon.methods.supply.statistics_fallback`); the messages
        that refuse such statistics suggest them.
    prefix_halves : bool
        Whether it reads the samples' :class:`~mcrecon.core.strata.PrefixHalves`: offline
        ``inputs.strata`` from a log or SampleSet (None from statistics: no order); adaptive ``state.strata``.

    What a source cannot supply is refused by :func:`mcrecon.methods.supply.check_supply`.
    """

    subpixels: int = 0
    samples: bool = False
    reference: str = "none"
    statistics: bool = True
    half_buffers: bool = False
    features: str = "none"
    range: bool = False
    statistics_options: tuple = ()
    prefix_halves: bool = False

    def __post_init__(self):
        object.__setattr__(self, "statistics_options", tuple(dict(self.statistics_options).items()))
        if self.reference not in ("none", "optional", "required"):
            raise ValueError(f"Requirements.reference: {self.reference!r}; valid: none, optional, required")
        if self.features not in ("none", "optional", "required"):
            raise ValueError(f"Requirements.features: {self.features!r}; valid: none, optional, required")


@dataclasses.dataclass(frozen=True, eq=False)
class MethodInputs:
    """What a reconstruction gets: the inputs its method declared.

    Attributes
    ----------
    stats : PixelStats or None
        Per-pixel statistics (with the subpixel grid the method asked
        for); None only for methods with ``requires.statistics`` False.
    samples : sample source or None
        The individual samples (:mod:`mcrecon.core.samples`), for methods with
        ``requires.samples``.
    halves : Halves or None
        Two independent half buffers (:class:`~mcrecon.core.halves.Halves`), for methods with
        ``requires.half_buffers``: in place of ``samples``, or with them only when split from those
        very samples (``halves.source``).  ``stats`` is then their Chan merge (filled in by
        :meth:`Method.reconstruct` when None, which also converts a pair ``(stats_a, stats_b)`` once).
    reference : ndarray (H, W, C) float64 or None
        The reference image, for methods that read one.
    nonfinite : {'drop', 'zero', 'raise'}
        The policy for NaN/Inf values a method reading ``samples`` applies
        (the statistics have applied it already).
    strata : PrefixHalves or None
        The samples' prefix halves, for methods with ``requires.prefix_halves`` (a log or SampleSet source).
    """

    stats: PixelStats | None
    samples: Any = None
    reference: np.ndarray | None = None
    nonfinite: str = "drop"
    halves: Halves | None = None
    strata: Any = None

    @property
    def shape(self) -> tuple[int, int, int]:
        if self.stats is not None:
            return self.stats.shape
        if self.halves is not None:
            return self.halves[0].shape
        return int(self.samples.height), int(self.samples.width), len(self.samples.channels)

    @property
    def channels(self) -> tuple[str, ...]:
        if self.stats is not None:
            return tuple(self.stats.channels)
        if self.halves is not None:
            return tuple(self.halves[0].channels)
        return tuple(self.samples.channels)


@dataclasses.dataclass(eq=False)
class RunState:
    """What one run of a method accumulates (created by :meth:`Method.start`); subclasses add fields.

    ``diagnostics`` holds the maps :meth:`Method.diagnostics` returns; ``halves`` the committed samples'
    two halves, for a method with ``requires.half_buffers`` that observes samples (:meth:`Method.observe`).
    """

    width: int
    height: int
    channels: tuple[str, ...]
    reference: np.ndarray | None = None
    diagnostics: dict = dataclasses.field(default_factory=dict)
    halves: Halves | None = None


@dataclasses.dataclass(eq=False)
class AdaptiveState:
    """What a method sees when it plans a round.

    The driver takes the uniform initial pass itself (:meth:`Method.initial_pass`),
    so ``stats`` always holds samples when ``plan`` is called.

    Attributes
    ----------
    stats : PixelStats
        Statistics of every committed sample (subpixel grid as the method
        asked for).
    round_index : int
        Index of the round being planned (0 = the first round of the initial pass).
    budget : int
        Total sample budget of the run (average spp x pixels).
    n_samples : int
        Samples committed so far plus those in flight (``pending``).
    rng : numpy.random.Generator
        Random numbers for this round's decisions, derived from the run's
        seed and the round index (reproducible, resumable).
    reference : ndarray (H, W, C) or None
        Ground truth when the run has one (oracle modes, experiments).
    pending : ndarray (H, W) of int64 or None
        Pipelined runs: samples per pixel of the round in flight (requested,
        not yet in ``stats``); None when every requested sample is committed.
    iteration : int
        Index of this plan among the method's own (0: the first after the
        initial pass).
    strata : PrefixHalves or None
        The committed samples' prefix halves (:func:`mcrecon.core.strata.stratified_gain`).
    sampler : str
        What the renderer's samples of a pixel are (:data:`mcrecon.core.requests.SAMPLERS`; its declaration).
    """

    stats: PixelStats
    round_index: int
    budget: int
    n_samples: int
    rng: np.random.Generator
    reference: np.ndarray | None = None
    pending: np.ndarray | None = None
    iteration: int = 0
    strata: object = None
    sampler: str = "independent"

    @property
    def remaining(self) -> int:
        return max(int(self.budget) - int(self.n_samples), 0)

    @property
    def width(self) -> int:
        return self.stats.width

    @property
    def height(self) -> int:
        return self.stats.height

    def inputs(self) -> MethodInputs:
        """The run's statistics and reference as reconstruction inputs."""
        return MethodInputs(self.stats, None, self.reference)

    def request(self, *, counts=None, positions=None) -> SampleRequest:
        """A request for this round (the driver sets the renderer seed)."""
        return SampleRequest(self.width, self.height, counts=counts, positions=positions,
                             round_index=self.round_index)

    def uniform_request(self, spp: float) -> SampleRequest:
        """``spp`` samples per pixel spread uniformly (at most what the budget has left)."""
        n = min(self.remaining, int(spp * self.width * self.height))
        return self.request(counts=uniform_counts(self.width, self.height, n, self.rng))


def uniform_counts(width: int, height: int, n: int, rng: np.random.Generator) -> np.ndarray:
    """Spread ``n`` samples as evenly as possible: every pixel gets ``n // P``, ``n % P`` random pixels one more."""
    p = width * height
    counts = np.full(p, n // p, np.int64)
    extra = n % p
    if extra:
        counts[rng.choice(p, size=extra, replace=False)] += 1
    return counts.reshape(height, width)


class Method:
    """Base class: validated immutable options, a per-run state, uniform sampling in doubling rounds.

    Class attributes
    ----------------
    name : str  (registry name)
    options : tuple of Option
        Keyword options (and CLI flags), validated by ``__init__``.
    variants : mapping
        ``{variant: {option: value}}`` that a ``variant`` option presets unless given (:func:`variant_option`).
    requires : Requirements
        The inputs the method reads (a property when they depend on the options).
    run_type : type
        The :class:`RunState` subclass :meth:`start` creates for a run.
    adaptive : bool
        Whether ``plan`` distributes samples by itself (else uniform).
    initial_spp : int
        Samples per pixel of the driver's uniform initial pass (:meth:`initial_pass`; an option overrides it).
    pipeline : bool
        Whether ``plan`` is safe from statistics one round old (the round in flight as
        ``state.pending``): adaptive runs then pipeline by default (:func:`mcrecon.adaptive.adapt`).

    Subclasses never override ``__init__``: cross-option checks and derived configuration go into :meth:`_configure`.
    """

    name: ClassVar[str] = "?"
    options: ClassVar[tuple[Option, ...]] = ()
    variants: ClassVar[Mapping[str, Mapping[str, Any]]] = {}
    requires: ClassVar[Requirements] = Requirements()
    run_type: ClassVar[type] = RunState
    adaptive: ClassVar[bool] = False
    initial_spp: ClassVar[int] = 1
    pipeline: ClassVar[bool] = False
    #: Doubling rounds are capped at 1/max_round_parts of the budget (a pipelined run's last commit overlaps
    #: nothing: docs/pipelining.md), never below max_round_floor samples (below it a cap only adds rounds).
    max_round_parts: ClassVar[int] = 8
    max_round_floor: ClassVar[int] = 1 << 20
    #: ``plan`` hands out :func:`~mcrecon.core.nets.even_round` counts while the samples show no structure.
    structure_test: ClassVar[bool] = True
    #: A round in whole nets is :func:`~mcrecon.core.nets.even_round`'s unless predicted to beat it (net_plan).
    net_gate: ClassVar[bool] = True
    #: A pipelined run may plan before ``observe`` (:func:`mcrecon.adaptive.rounds.plans_before_observe`).
    plans_before_observe: ClassVar[bool] = False
    #: The pixels' variance is read (False: the means alone, one render of them serves: offline.pixel_files).
    reads_variance: ClassVar[bool] = True

    def __init__(self, **options):
        where = self.where
        known = {o.name: o for o in self.options}
        unknown = sorted(set(options) - set(known))
        if unknown:
            raise InputError(where, unknown[0], f"unknown option; valid: {', '.join(known) or '(none)'}")
        presets = {}
        if "variant" in known:
            value = options.get("variant", _MISSING)
            variant = known["variant"].default if value is _MISSING else known["variant"].convert(value, where)
            presets = dict(self.variants.get(variant, {}))
        params = {}
        for name, opt in known.items():
            value = options.get(name, _MISSING)
            if value is _MISSING:
                params[name] = presets[name] if name in presets else opt.default
            else:
                params[name] = opt.convert(value, where)
        object.__setattr__(self, "_params", params)
        self._configure(params)
        object.__setattr__(self, "params", types.MappingProxyType(params))
        object.__setattr__(self, "given_options", frozenset(options))  # chosen, not defaults: never replaced
        object.__setattr__(self, "_frozen", True)

    def _configure(self, params: dict) -> None:
        """Cross-option checks and derived configuration (may adjust ``params``; raise InputError)."""

    def __setattr__(self, key, value):
        if getattr(self, "_frozen", False):
            raise AttributeError(f"method {self.name}: options are fixed once built; create a new method "
                                 f"with get_method({self.name!r}, {key}=...) instead")
        object.__setattr__(self, key, value)

    def __repr__(self) -> str:
        opts = ", ".join(f"{k}={v!r}" for k, v in self.params.items())
        return f"{type(self).__name__}({opts})"

    @classmethod
    def option_default(cls, name: str, variant: str | None = None):
        """The value option ``name`` takes when not given, under ``variant`` (default: the default variant)."""
        known = {o.name: o for o in cls.options}
        if variant is None and "variant" in known:
            variant = known["variant"].default
        return cls.variants.get(variant, {}).get(name, known[name].default)

    @property
    def where(self) -> str:
        """How error messages name this method."""
        return f"method {self.name}"

    def halo(self, width: int, height: int) -> int | None:
        """Pixels of context the offline result at a pixel needs: an int, or None for the whole image.

        A reconstruction of a tile extended by ``halo`` pixels on every side (clipped at the film's edges)
        gives the untiled result inside the tile (:func:`mcrecon.distributed.tiles.reconstruct_tiled`),
        provided every pixel has a sample (the fill of one without, :func:`mcrecon.core.fill.fill_empty_pixels`,
        reaches the nearest sampled pixel) and the tiles read the film's fill-in values for pixels with one
        (``PixelStats.film_fill``).  Default None: a method that declares nothing is whole-image.
        """
        return None

    def tile_grid(self) -> tuple[int, int]:
        """``(rows, columns)`` a grown tile's first pixel is a multiple of: kernels that work in bands of rows
        from the array's first row sum in the film's order only on the film's bands.  Default (1, 1)."""
        return (1, 1)

    def for_tiles(self, inputs: "MethodInputs", each_tile=None) -> "Method":
        """The method the tiles of the film ``inputs`` run: its whole-image decisions (nfor: its features' scale)
        made once on the film (``each_tile(halo)``: its tiles grown by ``halo``), fixed in a copy.  Default: self."""
        return self

    # ------------------------------------------------------------- per run
    def start(self, width: int, height: int, channels: Sequence[str] = ("R", "G", "B"), *, reference=None) -> RunState:
        """A fresh per-run state for a ``width`` x ``height`` film."""
        if self.requires.reference == "required" and reference is None:
            raise InputError(self.where, "reference", "this configuration needs a reference image "
                             "(the run's reference, or one stored in the log)")
        return self.run_type(int(width), int(height), tuple(str(c) for c in channels), reference)

    # -------------------------------------------------------------- offline
    def reconstruct(self, inputs: MethodInputs, *, run: RunState | None = None) -> np.ndarray:
        """Reconstruct an (H, W, C) float64 image.

        Parameters
        ----------
        inputs : MethodInputs
            Every input the method declared (:attr:`requires`); wrap pixel statistics as ``MethodInputs(stats)``.
            To reconstruct from a file, samples, statistics or a half-buffer pair, use :func:`mcrecon.reconstruct`
            (``mcrecon.reconstruct(source, method=...)``), which reads what the method declares.
        run : RunState, optional
            A state from :meth:`start` that receives the diagnostics; a
            fresh one by default.

        A method with ``requires.samples`` and ``requires.half_buffers`` takes ``inputs.samples`` or
        ``inputs.halves`` (both only when the halves were split from those samples, ``halves.source``); with
        halves and no ``inputs.stats``, the statistics are their merge.  What the inputs cannot supply is
        refused by :func:`~mcrecon.methods.supply.check_supply`.
        """
        if not isinstance(inputs, MethodInputs):
            raise InputError(self.where, "inputs", f"got {type(inputs).__name__}, expected MethodInputs; wrap pixel "
                             "statistics as MethodInputs(stats) (a half-buffer pair as MethodInputs(None, halves=(a, "
                             f"b))), or use mcrecon.reconstruct(source, method={self.name!r}) for files, samples, "
                             "statistics and half-buffer pairs")
        halves, req = None, self.requires
        if inputs.halves is not None:
            halves = as_halves(inputs.halves, self.where)
            if inputs.samples is not None and halves.source is not inputs.samples:
                # both only as the dispatcher builds them: the halves split from exactly those samples
                raise InputError(self.where, "halves", "give the samples or a half-buffer pair, not both "
                                 "(halves split from other samples, or statistics of two buffers)")
        elif inputs.samples is not None and req.half_buffers:  # the dispatcher's split, for samples given here
            halves = split_halves(inputs.samples, nonfinite=inputs.nonfinite,
                                  features=usable_names(inputs.samples) if req.features != "none" else ())
        st = inputs.stats if inputs.stats is not None else halves.a if halves is not None else None
        feats = (halves.a if halves is not None else inputs.stats if inputs.stats is not None else None)
        features = tuple(feats.feature_names) if feats is not None else \
            tuple(getattr(inputs.samples, "feature_names", ()) or ())
        n = halves.n_samples if halves is not None else int(inputs.stats.count.sum()) \
            if inputs.stats is not None and inputs.samples is None else None
        check_supply(self, Supply("these pixel statistics", samples=inputs.samples is not None,
                                  halves=halves is not None, subpixels=st.subpixels if st is not None else -1,
                                  has_range=st.has_range if st is not None else True, features=features,
                                  n_samples=n, surface="inputs"))
        if halves is not None:
            stats = inputs.stats
            if stats is None:
                stats = halves.merged()
            elif stats.shape != halves.shape or not np.array_equal(stats.count, halves.a.count + halves.b.count):
                raise InputError(self.where, "stats", "with a half-buffer pair the statistics must be the merge "
                                 "of the two halves (counts differ); leave MethodInputs.stats None to have them "
                                 "merged")
            inputs = dataclasses.replace(inputs, stats=stats, halves=halves)
        if req.statistics and inputs.stats is None:
            raise InputError(self.where, "input", "needs pixel statistics (MethodInputs.stats)")
        if run is None:
            h, w, _ = inputs.shape
            run = self.start(w, h, inputs.channels, reference=inputs.reference)
        return self.reconstruct_run(run, inputs)

    def reconstruct_run(self, run: RunState, inputs: MethodInputs) -> np.ndarray:
        """The method's reconstruction (the hook subclasses implement)."""
        raise NotImplementedError

    # ------------------------------------------------------------- adaptive
    def initial_pass(self, budget: int, pixels: int) -> int:
        """Samples per pixel of the uniform initial pass the driver takes before the first plan.

        The ``initial_spp`` option when the method has one, else the class attribute; the driver caps the pass
        at the run's ``budget``.  A method that cannot run on that budget raises :class:`InputError` here,
        before anything is rendered.  Pipelined, the driver splits a pass of two or more samples per pixel into
        two rounds (half, then the rest), so that the first plan sees the first half while the second renders.
        """
        return max(1, int(self.params.get("initial_spp", self.initial_spp)))

    def plan(self, run: RunState, state: AdaptiveState) -> SampleRequest | None:
        """The next round's request after the initial pass, or None when the method's target is met.

        The round's size is :meth:`round_size`'s.  A share ``uniform_share`` (an option, default 0) of the
        round is spread uniformly; :meth:`place` places the rest; in whole nets (:func:`~mcrecon.core.nets.net_plan`)
        with a ``net_counts`` option of 1, or of -1 where the renderer declares a stratified sampler
        (``state.sampler``).  While the samples show no structure beyond noise an adaptive method's round is
        uniform (:func:`~mcrecon.core.nets.shows_structure`, ``structure_test``; not a paper variant).  An empty
        request in a pipelined run asks the driver to commit the round in flight and plan again from it.
        """
        nets = self.params.get("net_counts")
        if noise_only(self, state):
            return even_plan(self, state)
        if nets == 1 or (nets == -1 and state.sampler != "independent"):
            return net_plan(self, run, state)
        if (n := self.round_size(state)) is None:
            return None
        n_uniform = int(round(self.params.get("uniform_share", 0.0) * n))
        if (placed := self.place(run, state, n - n_uniform)) is None:
            return None
        counts = uniform_counts(state.width, state.height, n_uniform, state.rng) if n_uniform > 0 else None
        placed = np.asarray(placed)
        if placed.ndim == 2 and placed.shape == (state.height, state.width) and placed.dtype.kind in "iu":
            return state.request(counts=placed if counts is None else counts + placed)
        if not len(placed) and counts is None:  # nothing placed, nothing uniform: ask for nothing
            counts = np.zeros((state.height, state.width), np.int64)
        return state.request(positions=placed if len(placed) else None, counts=counts)

    def round_size(self, state: AdaptiveState) -> int | None:
        """Samples of the next round after the initial pass, None when the budget is spent: with an
        ``iterations`` option what is left over the iterations to come (the last takes everything), with
        ``round_spp`` that many per pixel, else the total doubles, each round capped (``max_round_parts``)."""
        if (remaining := state.remaining) <= 0:
            return None
        if "iterations" in (p := self.params):
            left = p["iterations"] - state.iteration
            return remaining if left <= 1 else max(1, remaining // left)
        if "round_spp" in p:
            return min(remaining, max(1, int(round(p["round_spp"] * state.width * state.height))))
        return self.doubling_round(state)

    def doubling_round(self, state: AdaptiveState) -> int:
        """Samples of a round that doubles the total, capped at 1 / ``max_round_parts`` of the budget."""
        npix = state.width * state.height
        cap_spp = round_cap_spp(state.budget, npix, self.max_round_parts, self.max_round_floor)
        return min(state.remaining, state.n_samples, cap_spp * npix)

    def place(self, run: RunState, state: AdaptiveState, n: int):
        """Where ``n`` samples of the round go: film positions (n, 2), or counts per pixel (H, W) of int.

        Default: spread uniformly.  None stops the run (the method's target is met).  Called with
        ``n`` = 0 too (it must then use no random numbers): a method that stops on a target checks it here.
        """
        return uniform_counts(state.width, state.height, n, state.rng)

    def even_under_rare(self, run: RunState, state: AdaptiveState) -> bool:
        """Whether a round in whole nets that a rare bright component keeps from the net gate is the even round
        (:func:`~mcrecon.core.nets.net_plan`; auto: under a thin vote).  Default: no, the plan's round."""
        return False

    def observe(self, run: RunState, batch: SampleBatch, round_index: int) -> None:
        """See a committed round's samples (only called when ``requires.samples``).

        For a method with ``requires.half_buffers`` the round is split into the run's two halves
        (``run.halves``, with the features the method reads; replayed in order on resume), which
        :meth:`finish` hands over as ``inputs.halves``: the method never splits samples itself
        (one that overrides ``observe`` and takes half buffers calls this one).
        """
        req = self.requires
        if not req.half_buffers:
            return
        if run.halves is None:
            self.refuse_reply(batch)  # on the first round, not after the whole budget is rendered
            # the renderer's first round says which features it sends (every later round sends the same)
            layout = usable_layout(batch.features) if req.features != "none" and batch.features else None
            run.halves = Halves.empty(run.width, run.height, run.channels, features=layout)
        run.halves.add(batch.positions, batch.values, features=batch.features if run.halves.a.features else None,
                       nonfinite="drop", source=self.where)

    def refuse_reply(self, batch: SampleBatch) -> None:
        """Refuse a reply without the features the method requires (an adaptive run asks before the commit)."""
        if self.requires.half_buffers and self.requires.features == "required" and not batch.features:
            raise InputError(self.where, "features", f"{self.name} needs per-sample features (albedo, normal, depth) "
                             "and the renderer's replies have none: the built-in scenes send them with --features all "
                             "(`mcrecon scenes`), the Mitsuba bridge by default, a renderer of your own in its replies "
                             "(SampleBatch.features; /features/NAME of a command's reply); or pick another method")

    def run_inputs(self, run: RunState, state: AdaptiveState) -> MethodInputs:
        """An adaptive run's reconstruction inputs, as the offline dispatcher builds them from the run's log (so
        the run's image is its log's, bit for bit): its statistics, its prefix halves if declared, and its halves
        (:meth:`observe`) when they hold every committed sample, the statistics then being their merge."""
        h, strata = run.halves, state.strata if self.requires.prefix_halves else None
        if h is not None and h.n_samples == int(state.stats.count.sum()):
            return MethodInputs(h.merged(), None, state.reference, halves=h, strata=strata)
        return MethodInputs(state.stats, None, state.reference, strata=strata)

    def finish(self, run: RunState, state: AdaptiveState) -> np.ndarray:
        """Final image of an adaptive run (default: :meth:`reconstruct_run` of :meth:`run_inputs`)."""
        return self.reconstruct_run(run, self.run_inputs(run, state))

    def diagnostics(self, run: RunState) -> Mapping[str, np.ndarray]:
        """Scalar (H, W) maps from the run's last reconstruction or planning step."""
        return dict(run.diagnostics)

    def describe(self) -> dict:
        return {"method": self.name, **dict(self.params)}
