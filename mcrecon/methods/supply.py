"""What a source supplies against what a method requires: the one place a method's inputs are refused.

A :class:`Supply` says what a source holds (the samples, two half
buffers, pixel statistics with or without a sample range or a subpixel
grid, features) and how the caller gave it (``surface``: the Python API,
:class:`~mcrecon.methods.base.MethodInputs` handed to a method, or
pixel-statistics files).  :func:`check_supply` compares it with the
method's :class:`~mcrecon.methods.base.Requirements` and refuses, in one
line naming the source and the fix, what the method cannot take; the
offline dispatcher and :meth:`~mcrecon.methods.base.Method.reconstruct`
both call it, so every method is refused the same way, and no method is
named here.  :func:`statistics_fallback` is the hook for pixel-statistics
files: the options a method declares it takes them with
(``Requirements.statistics_options``), used when the caller did not
give those options (``Method.given_options``: a value given explicitly
is never replaced, also one equal to the default).  Messages speak the
caller's language: ``--flag value`` on the command line
(``Supply.cli``), ``name=value`` in Python.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

from ..errors import InputError

__all__ = ["Supply", "check_supply", "statistics_fallback", "SURFACES"]

#: How a source was given: the Python API (``mcrecon.reconstruct``, ``mcrecon.restoration``),
#: :class:`MethodInputs` handed to ``Method.reconstruct``, or pixel-statistics files (EXR).
SURFACES = ("python", "inputs", "files")


@dataclasses.dataclass(frozen=True)
class Supply:
    """What a source holds, for :func:`check_supply`.

    Attributes
    ----------
    what : str
        How messages name the source ("these pixel statistics", a file name).
    samples, halves : bool
        The individual samples; two independent half buffers.
    subpixels : int
        The statistics' subpixel grid (a sample source builds any: -1).
    has_range : bool
        Each pixel's sample minimum and maximum.
    features : tuple of str
        The per-sample feature names.
    n_samples : int or None
        Samples in the source, when known before reading it.
    surface : {'python', 'inputs', 'files'}
        How the caller gave it (:data:`SURFACES`): the messages' wording.
    logs : bool
        Python surface: whether sample log paths are accepted (wording only).
    cli : bool
        Given on the command line: options are named as flags (``--candidates
        box,gauss``), else as keywords (``candidates='box,gauss'``).
    """

    what: str
    samples: bool = False
    halves: bool = False
    subpixels: int = 0
    has_range: bool = True
    features: tuple = ()
    n_samples: int | None = None
    surface: str = "python"
    logs: bool = True
    cli: bool = False


def _flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def _option_name(name: str, cli: bool) -> str:
    """An option as the caller names it: ``--flag`` on the command line, the keyword in Python."""
    return _flag(name) if cli else name


def _options_text(opts: dict, cli: bool) -> str:
    if cli:
        return ", ".join(f"{_flag(k)} {v}" for k, v in opts.items())
    return ", ".join(f"{k}={v!r}" for k, v in opts.items())


def _other_half(supply: Supply) -> str:
    """How the caller gives the other half of a pixel-statistics file."""
    return ("give the other half with --half-buffer B.exr" if supply.cli else
            "give the other half too, as a pair of two EXR paths (\"a.exr\", \"b.exr\")")


def _unmet(req, supply: Supply) -> list[str]:
    """What the method needs that the source lacks: 'samples' and/or 'range'."""
    out = []
    if req.samples and not supply.samples and not (req.half_buffers and supply.halves):
        out.append("samples")
    if getattr(req, "range", False) and not supply.has_range and not supply.samples:
        out.append("range")
    return out


def _given(method) -> dict:
    """The options the caller gave ``method`` (``Method.given_options``), with their values.

    Given, not "different from the default": a value given explicitly is
    the caller's choice even when it equals what the option takes
    otherwise, and is never replaced.
    """
    return {k: method.params[k] for k in getattr(method, "given_options", ()) if k in method.params}


def statistics_fallback(method, supply: Supply):
    """``(method rebuilt, note)`` for pixel statistics it cannot take as configured, or None.

    The hook of ``Requirements.statistics_options``: the option values
    under which the method takes pixel statistics alone (no samples, no
    halves, no sample range).  When ``supply`` lacks what the method's
    requirements ask for and the caller gave none of those options
    (``Method.given_options``), the method is rebuilt with them and the
    note says so; when the caller gave one, nothing changes and
    :func:`check_supply` refuses, naming it.
    """
    req = method.requires
    opts = dict(req.statistics_options)
    unmet = _unmet(req, supply)
    if not opts or not unmet:
        return None
    given = _given(method)
    if any(k in given for k in opts):
        return None
    rebuilt = type(method)(**{**given, **opts})
    if _unmet(rebuilt.requires, supply):
        return None
    need = ("the individual samples or two independent half buffers" if req.half_buffers
            else "the individual samples") if "samples" in unmet else "each pixel's sample minimum and maximum"
    more = f"; {_other_half(supply)} to keep them" if "samples" in unmet and req.half_buffers else ""
    return rebuilt, (f"{method.name}: using {_options_text(opts, supply.cli)}: the options it runs with by "
                     f"default need {need}, which {supply.what} does not hold{more}")


def check_supply(method, supply: Supply, *, where: str | None = None,
                 half_buffer_methods: Callable[[], list] | None = None,
                 statistics_methods: Callable[[], list] | None = None) -> None:
    """Refuse, in one line naming the source and the fix, inputs ``method`` cannot take.

    Parameters
    ----------
    method : Method
    supply : Supply
    where : str, optional
        How the messages name the caller (default ``method.where``).
    half_buffer_methods, statistics_methods : callable, optional
        The registry's names of the methods that take half buffers, and of
        those that take pixel statistics alone, for the messages (a caller
        below the registry gives none).
    """
    req, name, surface = method.requires, method.name, supply.surface
    m_where = where or method.where
    what = supply.what
    if supply.halves and not req.half_buffers:
        names = ", ".join(half_buffer_methods()) if half_buffer_methods is not None else \
            "the registry's mcrecon.methods.half_buffer_methods()"
        if surface == "files":
            raise InputError(m_where, "--half-buffer" if supply.cli else "source", f"{name} does not use half "
                             f"buffers; methods that do: {names} (for {name}, give one EXR of all the samples)")
        if surface == "inputs":
            raise InputError(m_where, "halves", f"{name} does not use half buffers (methods that do declare "
                             f"requires.half_buffers: {names}); give it the statistics of all the samples "
                             "(merge_halves(a, b))")
        raise InputError(m_where, "halves", f"{name} does not use half buffers; methods that do: {names} (for "
                         f"{name}, give the statistics of all the samples: mcrecon.core.halves.merge_halves(a, b))")
    if supply.halves and req.subpixels and supply.subpixels != req.subpixels:
        raise InputError(m_where, "halves", f"this configuration needs a {req.subpixels}x{req.subpixels} subpixel "
                         f"grid, got subpixels={supply.subpixels}")
    unmet = _unmet(req, supply)
    opts = dict(req.statistics_options)
    if "samples" in unmet:
        if surface == "inputs":
            if req.half_buffers:
                raise InputError(m_where, "input", f"{name} needs the individual samples or two independent half "
                                 "buffers, which one set of pixel statistics does not hold; give it samples "
                                 f"(mcrecon.reconstruct(log_or_samples, method={name!r}), MethodInputs.samples) or "
                                 f"a half-buffer pair (mcrecon.reconstruct((stats_a, stats_b), method={name!r}), "
                                 f"MethodInputs.halves, `mcrecon reconstruct A.exr --half-buffer B.exr --method "
                                 f"{name}`)")
            raise InputError(m_where, "input", f"{name} filters individual samples, which pixel statistics no "
                             f"longer hold; give it samples (mcrecon.reconstruct(log_or_samples, method={name!r}) "
                             f"or `mcrecon reconstruct LOG --method {name}`)")
        if surface == "files":
            if req.half_buffers:
                chosen = [k for k in opts if k in _given(method)]
                head = (f"{_options_text({chosen[0]: method.params[chosen[0]]}, supply.cli)} (given) needs"
                        if chosen else f"{name} (these options) needs")
                raise InputError(m_where, _option_name(chosen[0], supply.cli) if chosen else "input",
                                 f"{head} the individual samples or two independent half buffers, which {what} "
                                 f"does not hold; {_other_half(supply)}, or a sample log"
                                 + (f", or use {_options_text(opts, supply.cli)}" if opts else ""))
            others = ", ".join(statistics_methods()) if statistics_methods is not None else ""
            raise InputError(m_where, "input", f"{name} filters individual samples (their film positions and "
                             f"values), which {what} does not hold; give it a sample log"
                             + (f", or pick one of {others}" if others else ""))
        samples_from = "a sample log or a SampleSet" if supply.logs else "a mcrecon.SampleSet"
        if req.half_buffers:
            raise InputError(m_where, "input", f"{name} (these options) needs the individual samples or two "
                             f"independent half buffers, which {what} does not hold; give it {samples_from}, or "
                             "a half-buffer pair (stats_a, stats_b)"
                             + (f"; or {_options_text(opts, supply.cli)} (which needs neither)" if opts else ""))
        raise InputError(m_where, "input", f"{name} filters individual samples, which {what} does not hold; "
                         f"give it {samples_from}")
    if not supply.samples and req.subpixels and supply.subpixels != req.subpixels:
        if surface == "files":
            raise InputError(m_where, "input", f"this {name} configuration needs per-subpixel sums on a "
                             f"{req.subpixels}x{req.subpixels} grid, which {what} does not hold; give a sample "
                             "log, or options without a subpixel grid ("
                             + (f"`mcrecon methods {name}`)" if supply.cli else f"mcrecon.methods.method_class("
                                f"{name!r}).options)"))
        raise InputError(m_where, "statistics", f"need a {req.subpixels}x{req.subpixels} subpixel grid, got "
                         f"subpixels={supply.subpixels}; build them with subpixels={req.subpixels} "
                         "(method.requires.subpixels)")
    if "range" in unmet:
        chosen = [k for k in opts if k in _given(method)] or list(opts)
        field = _option_name(chosen[0], supply.cli) if chosen else "input"
        value = f"{method.params[chosen[0]]!r} " if chosen else ""
        fix = f"; use {_options_text(opts, supply.cli)}" if opts else "; give a sample log"
        raise InputError(m_where, field, f"{value}needs each pixel's sample minimum and maximum, which {what} "
                         f"does not hold{fix}")
    if req.features == "required" and not supply.features:
        raise InputError(m_where, "features", f"{name} needs per-sample features (albedo, normal, depth) and "
                         f"{what} has none; write them into the log (/features/NAME), pass "
                         "SampleSet(features=...) or PixelStats.from_moments(features=...), or pick another method")
    if req.features == "required" and supply.n_samples == 0:
        raise InputError(what, "samples", f"no sample: {name} regresses on the samples and their features, and "
                         "there is nothing to reconstruct; give a source with samples")
