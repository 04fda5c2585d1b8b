"""Array-level reconstruction, one function per method (in the style of ``skimage.restoration``).

Each function takes pixel statistics (:class:`~mcrecon.core.stats.PixelStats`,
e.g. from :meth:`~mcrecon.core.stats.PixelStats.from_moments` on a renderer's
mean / variance / count images, or from samples in memory with
:meth:`~mcrecon.core.stats.PixelStats.from_samples`) or, for methods that
filter individual samples, a :class:`~mcrecon.core.samples.SampleSet`; :func:`auto`
and :func:`nfor` also take a half-buffer pair ``(stats_a, stats_b)`` (two
independent halves of the samples, as renderers write dual buffers); its
keyword-only options are the method's options, validated by the one
option path of :mod:`mcrecon.methods`.  The image comes back in the
precision of the input values: float32 in, float32 out.

Functions: :func:`box`, :func:`gem`, :func:`awr`, :func:`splat`, :func:`auto`, :func:`nfor` (``ci``'s offline image
is :func:`box`; its stopping rule is adaptive: :func:`mcrecon.adapt`).  Each is written out here with
what is its own (the input, the notes, the references, an example); its options are the method's
:class:`~mcrecon.methods.Option` list, written once there: :func:`_method_function` builds each
function's signature (keyword-only, with the real defaults and types) and the options' entries of its
docstring from them, as the command line builds its flags and ``mcrecon methods`` its listing, and
writes in the docstring entries every function shares (``nonfinite``, Returns, Raises).
"""

from __future__ import annotations

import functools
import inspect
import textwrap
import typing

import numpy as np

from .errors import InputError
from .methods import get_method, method_class
from .core.samples import SampleSet

__all__ = ["box", "gem", "awr", "splat", "auto", "nfor"]


def _run(name: str, source, reference, nonfinite: str, options: dict, unknown: dict) -> np.ndarray:
    """The method's image of ``source`` (read by the one dispatcher), in the precision of the input values.

    ``options`` are those the caller gave: the variant's presets apply to the others
    (:func:`mcrecon.methods.base.variant_option`).
    """
    from .offline.inputs import check_given_statistics, gather_inputs

    where = f"mcrecon.restoration.{name}"
    if unknown:
        valid = sorted(o.name for o in method_class(name).options)
        raise InputError(where, sorted(unknown)[0], f"unknown option; valid: {', '.join(valid) or '(none)'}")
    method = get_method(name, **options)
    inputs = gather_inputs(source, method, nonfinite=nonfinite, reference=reference, where=where, logs=False)
    if isinstance(source, SampleSet):  # samples the caller gave: refuse a set without any
        if inputs.stats is not None:
            check_given_statistics(inputs.stats, where)
        elif source.n_samples == 0:
            raise InputError(where, "samples", "no samples: there is nothing to reconstruct")
    dtype = source.values.dtype if isinstance(source, SampleSet) else inputs.stats.dtype
    image = method.reconstruct(inputs)
    return np.asarray(image).astype(np.float32 if dtype == np.float32 else np.float64, copy=False)


#: Types of the annotations of option parameters.
_TYPE_NAMES = {float: "float", int: "int", str: "str", bool: "bool"}


def _annotation(opt):
    """The annotation of an option's parameter: ``Literal[...]`` of its choices, else its type, ``| None``
    where None is valid."""
    t = typing.Literal[tuple(opt.choices)] if opt.choices is not None else opt.type
    return typing.Optional[t] if opt.allows_none else t


def _option_entry(opt, cls, indent: str = "    ") -> str:
    """The numpydoc entry of one option: its type, help, valid values, default and the variants' presets."""
    if opt.choices is not None:
        kind = "{" + ", ".join(map(repr, opt.choices)) + "}"
    else:
        kind = _TYPE_NAMES.get(opt.type, getattr(opt.type, "__name__", str(opt.type)))
        kind += " or None" if opt.allows_none else ""
    text = opt.help[:1].upper() + opt.help[1:]
    if opt.choices is None and opt.type not in (str, bool):
        text += f"; {opt.expectation()}"
    elif opt.note:
        text += f" ({opt.note})"
    presets = "".join(f"; ``variant={v!r}``: {cls.option_default(opt.name, v)!r}" for v in cls.variants
                      if opt.name != "variant" and cls.option_default(opt.name, v) != opt.default)
    text += f" (default {opt.default!r}{presets})."
    if opt.name == "variant":
        text += (" An option not given takes the variant's value (shown after each option's default); a value "
                 "given explicitly always wins, also one equal to the default.")
    body = textwrap.fill(text, 112 - len(indent), initial_indent=indent + "    ", subsequent_indent=indent + "    ",
                         break_on_hyphens=False)
    return f"{indent}{opt.name} : {kind}, optional\n{body}\n"


#: The docstring parts every function shares, written in by :func:`_method_function` (unindented).
_NONFINITE_ENTRY = """\
nonfinite : {'drop', 'zero', 'raise'}, optional
    Policy for NaN/Inf sample values of a SampleSet (default 'drop').
"""
_RETURNS = """
Returns
-------
image : ndarray (H, W, C)
    float32 when the input values were float32, else float64.
"""
_RAISES = """
Raises
------
InputError
    Invalid or unknown options (the message lists the valid values), NaN/Inf in the
    statistics, an input without any sample, the wrong kind of input.
"""


def _built_doc(doc: str, cls, own: list[str]) -> str:
    """``doc`` with what the functions share written in: the entries of ``cls``'s options in its Parameters
    section, before the entry of the first of the function's own keyword-only parameters ``own``
    (reference) or else at its end; the ``nonfinite`` entry at its end; the Returns section after it, and
    the Raises section unless ``doc`` has its own."""
    lines = doc.splitlines(keepends=True)
    underlines = [i for i in range(1, len(lines)) if lines[i].strip() and set(lines[i].strip()) == {"-"}]
    headers = [lines[i - 1].strip() for i in underlines]
    start, end = underlines[0] + 1, underlines[1] - 2  # the Parameters entries; end: the blank line after them
    indent = lines[underlines[0]][:len(lines[underlines[0]]) - len(lines[underlines[0]].lstrip())]
    at = next((i for i in range(start, end) if " : " in lines[i] and lines[i].strip().split(" : ")[0] in own), end)
    options = "".join(_option_entry(o, cls, indent) for o in cls.options)
    shared = _NONFINITE_ENTRY + _RETURNS + ("" if "Raises" in headers else _RAISES)
    return ("".join(lines[:at]) + options + "".join(lines[at:end])
            + textwrap.indent(shared, indent) + "".join(lines[end:]))


def _method_function(fn):
    """The array-level function of the method named ``fn.__name__``, built from ``fn`` and the method's options.

    ``fn`` is written out with the input (``source``, positional-only), its own keyword-only parameters
    (``reference``, ``nonfinite``), ``**options`` and a docstring with what is its own (the entries of
    ``source`` and ``reference``, the notes, the references, an example); the function returned takes
    every option of the method as a keyword-only parameter with its default (its ``__signature__``, which
    ``help`` and ``inspect.signature`` show) and its docstring adds what every function shares
    (:func:`_built_doc`).
    The call sees only the options given, so that an option left out takes the chosen variant's preset
    while a value given explicitly always wins -- also one equal to the default shown.
    """
    name = fn.__name__
    cls = method_class(name)
    written = inspect.signature(fn)
    params = [p for p in written.parameters.values() if p.kind is not inspect.Parameter.VAR_KEYWORD]
    source_param, own = params[0], params[1:]
    valid = [o.name for o in cls.options]
    clash = set(valid) & {p.name for p in params}
    if clash:
        raise TypeError(f"restoration.{name}: options {sorted(clash)} clash with the function's own parameters")
    option_params = [inspect.Parameter(o.name, inspect.Parameter.KEYWORD_ONLY, default=o.default,
                                       annotation=_annotation(o)) for o in cls.options]
    own_defaults = {p.name: p.default for p in own}

    @functools.wraps(fn)
    def call(source, /, **given):
        fixed = {k: given.pop(k, d) for k, d in own_defaults.items()}
        options = {k: v for k, v in given.items() if k in valid}
        unknown = {k: v for k, v in given.items() if k not in valid}
        return _run(name, source, fixed.get("reference"), fixed["nonfinite"], options, unknown)

    call.__signature__ = written.replace(parameters=[source_param, *option_params, *own])
    call.__doc__ = _built_doc(fn.__doc__, cls, [p.name for p in own])
    del call.__wrapped__  # the signature is the one built here, not the written-out one's
    return call


@_method_function
def box(source, /, *, nonfinite="drop", **options) -> np.ndarray:
    """The pixel mean, empty pixels filled from their nearest sampled neighbour (the baseline).

    Parameters
    ----------
    source : PixelStats
        Pixel statistics, e.g. ``PixelStats.from_moments(mean, variance, count)`` or
        ``PixelStats.from_samples(...)``; a SampleSet is accepted too.

    Notes
    -----
    Every other method is measured against this one.

    References
    ----------
    .. [1] (none: the estimator every Monte Carlo renderer starts from)

    Examples
    --------
    >>> import numpy as np
    >>> from mcrecon import PixelStats
    >>> from mcrecon.restoration import box
    >>> st = PixelStats.from_moments(np.ones((2, 3, 3), np.float32), np.zeros((2, 3, 3)), 4)
    >>> box(st).dtype, box(st).shape
    (dtype('float32'), (2, 3, 3))
    """


@_method_function
def gem(source, /, *, reference=None, nonfinite="drop", **options) -> np.ndarray:
    """Greedy error minimization: per-pixel Gaussian scale selection (final reconstruction).

    Parameters
    ----------
    source : PixelStats
        Pixel statistics, e.g. ``PixelStats.from_moments(mean, variance, count)`` or
        ``PixelStats.from_samples(...)``; a SampleSet is accepted too.
    reference : ndarray (H, W, C), optional
        The reference image (for ``oracle=1``).

    Notes
    -----
    Selects, per pixel, among Gaussian filters sqrt(2) apart the largest scale whose bias is not yet
    significant (an ICI-style selector with error rate ``gamma``), with outlier removal on the stopping maps.

    References
    ----------
    .. [1] F. Rousselle, C. Knaus, M. Zwicker, "Adaptive Sampling and Reconstruction using Greedy Error
       Minimization", ACM Transactions on Graphics 30(6) (SIGGRAPH Asia), 2011.

    Examples
    --------
    >>> import numpy as np
    >>> from mcrecon import PixelStats
    >>> from mcrecon.restoration import gem
    >>> rng = np.random.default_rng(0)
    >>> mean = (1.0 + rng.normal(0, 0.1, (16, 16, 3))).astype(np.float32)
    >>> st = PixelStats.from_moments(mean, np.full((16, 16, 3), 0.16), 16)
    >>> out = gem(st, gamma=0.2)
    >>> out.dtype, bool(np.abs(out - 1).std() < np.abs(mean - 1).std())
    (dtype('float32'), True)
    """


@_method_function
def awr(source, /, *, nonfinite="drop", **options) -> np.ndarray:
    """Adaptive wavelet rendering: soft thresholding of wavelet coefficients by their propagated variance.

    Parameters
    ----------
    source : PixelStats
        Pixel statistics with each pixel's sample range for the default variance estimator ``range``
        (``PixelStats.from_samples(...)``, or a SampleSet); statistics from moments
        (``PixelStats.from_moments(mean, variance, count)``) carry none, so with them the estimator not
        given is ``sample`` and ``range``/``contrast`` given are refused.

    Notes
    -----
    CDF 9/7 (also LeGall 5/3 and Haar) coefficients are soft-thresholded by the variance of the pixel means
    propagated through the transform.

    References
    ----------
    .. [1] R. S. Overbeck, C. Donner, R. Ramamoorthi, "Adaptive Wavelet Rendering", ACM Transactions on
       Graphics 28(5) (SIGGRAPH Asia), 2009.

    Examples
    --------
    Statistics of samples carry each pixel's sample range, which the default ``variance='range'`` reads:

    >>> import numpy as np
    >>> from mcrecon import PixelStats
    >>> from mcrecon.restoration import awr
    >>> rng = np.random.default_rng(1)
    >>> pos = rng.random((16 * 32 * 32, 2)) * 32
    >>> st = PixelStats.from_samples(pos, rng.exponential(1.0, (len(pos), 3)), width=32, height=32)
    >>> st.has_range
    True
    >>> err = np.mean((awr(st) - 1) ** 2), np.mean((st.mean - 1) ** 2)
    >>> bool(err[0] < 0.5 * err[1])
    True
    """


@_method_function
def splat(source, /, *, nonfinite="drop", **options) -> np.ndarray:
    """Progressive, energy-preserving, variable-width Epanechnikov splatting of individual samples.

    Parameters
    ----------
    source : SampleSet
        The samples (rounds are replayed in order; a single round is split into doubling pseudo-rounds per
        pixel).

    Notes
    -----
    Needs the individual samples: pixel statistics are refused.

    References
    ----------
    .. [1] F. Suykens, Y. D. Willems, "Adaptive Filtering for Progressive Monte Carlo Image Rendering",
       WSCG 2000.

    Examples
    --------
    >>> import numpy as np, mcrecon
    >>> from mcrecon.restoration import splat
    >>> rng = np.random.default_rng(2)
    >>> pos = (rng.random((3200, 2)) * 20).astype(np.float32)
    >>> samples = mcrecon.SampleSet(pos, np.ones((3200, 3), np.float32), width=20, height=20)
    >>> out = splat(samples)
    >>> out.dtype, bool(np.isclose(out.sum(), 3 * 400 * 1.0, rtol=1e-5))
    (dtype('float32'), True)
    """


@_method_function
def auto(source, /, *, nonfinite="drop", **options) -> np.ndarray:
    """Per-pixel choice among reconstructions by their estimated (reference-free) error.

    Parameters
    ----------
    source : PixelStats, SampleSet or (PixelStats, PixelStats)
        A SampleSet (the default candidates split its samples into two halves), or a half-buffer pair
        ``(stats_a, stats_b)``: statistics of two independent halves of the samples (dual buffers a renderer
        wrote; same size and channels, counts may differ), used as the two halves and merged for the SURE
        candidates.  With one set of pixel statistics pass ``candidates='box,gauss'`` (the SURE candidates).

    Notes
    -----
    Candidates: the pixel mean, GEM's Gaussian scales (error by Stein's unbiased risk estimate with the
    exact centre weight), cross-filtered non-local means and the black boxes awr/splat/oidn (error by
    dual-buffer cross-validation); each pixel takes the candidate of least smoothed relative estimate.

    References
    ----------
    .. [1] C. Stein, "Estimation of the mean of a multivariate normal distribution", Ann. Statist. 9(6), 1981.
    .. [2] T.-M. Li, Y.-T. Wu, Y.-Y. Chuang, "SURE-based optimization for adaptive sampling and
       reconstruction", ACM Transactions on Graphics 31(6), 2012.
    .. [3] F. Rousselle, C. Knaus, M. Zwicker, "Adaptive rendering with non-local means filtering",
       ACM Transactions on Graphics 31(6), 2012.

    Examples
    --------
    Two independent halves of the samples, as a renderer's dual buffers hold them, cross-validate each
    candidate:

    >>> import numpy as np
    >>> from mcrecon import PixelStats
    >>> from mcrecon.restoration import auto
    >>> rng = np.random.default_rng(4)
    >>> def half(n=8 * 24 * 24):
    ...     pos = rng.random((n, 2)) * 24
    ...     return PixelStats.from_samples(pos, rng.exponential(1.0, (n, 3)), width=24, height=24)
    >>> a, b = half(), half()
    >>> out = auto((a, b))
    >>> both = (a.mean * a.count[..., None] + b.mean * b.count[..., None]) / (a.count + b.count)[..., None]
    >>> out.shape, bool(np.mean((out - 1) ** 2) < np.mean((both - 1) ** 2))
    ((24, 24, 3), True)
    """



@_method_function
def nfor(source, /, *, nonfinite="drop", **options) -> np.ndarray:
    """Feature-guided first-order regression on half buffers (NFOR): denoising with albedo, normal, depth.

    Parameters
    ----------
    source : SampleSet or (PixelStats, PixelStats)
        Samples with per-sample features (``SampleSet(features=...)``: split into two halves here), or a
        half-buffer pair ``(stats_a, stats_b)`` of two independent halves with features
        (``PixelStats(features=...)``).  Sources without features are refused.

    Raises
    ------
    InputError
        Invalid or unknown options (the message lists the valid values), a source without features or
        without any sample, NaN/Inf in given statistics, the wrong kind of input.

    Notes
    -----
    Per pixel, a first-order model of the colour in the features over a 19 x 19 window, weighted by
    NL-means weights of the colour alone, the windows' predictions averaged; everything on two half
    buffers crossed (half A filtered with half B's weights and features), whose dual-buffer error estimate
    picks the bandwidth per pixel; a second regression of the averaged halves.  The default then clamps
    each pixel into its confidence interval (a caustic's rare samples are otherwise spread over exact dim
    neighbours: 12x the pixel mean's error on the built-in caustic).  Stages, parameters,
    tolerances and measured errors and times: docs/methods/nfor.md.

    References
    ----------
    .. [1] B. Bitterli, F. Rousselle, B. Moon, J. A. Iglesias-Guitian, D. Adler, K. Mitchell, W. Jarosz,
       J. Novak, "Nonlinearly weighted first-order regression for denoising Monte Carlo renderings",
       Computer Graphics Forum 35(4), 2016.

    Examples
    --------
    >>> import numpy as np, mcrecon
    >>> from mcrecon.restoration import nfor
    >>> rng = np.random.default_rng(3)
    >>> pos = rng.random((16 * 24 * 24, 2)) * 24
    >>> albedo = np.where((pos[:, :1] // 6) % 2 == 0, 0.8, 0.2).repeat(3, 1)
    >>> values = albedo * rng.exponential(1.0, (len(pos), 1))
    >>> samples = mcrecon.SampleSet(pos, values, width=24, height=24, features={"albedo": albedo})
    >>> out = nfor(samples, radius=4)
    >>> truth = np.where((np.arange(24) // 6) % 2 == 0, 0.8, 0.2)[None, :, None]
    >>> box = mcrecon.reconstruct(samples, method="box")
    >>> bool(np.mean((out - truth) ** 2) < 0.25 * np.mean((box - truth) ** 2))
    True
    """


from ._lazy import public_dir as _public_dir  # noqa: E402

__dir__ = _public_dir(__name__)
