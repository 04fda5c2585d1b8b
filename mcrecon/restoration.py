"""Array-level reconstruction, one function per method (in the style of ``skimage.restoration``).

Each function takes pixel statistics (:class:`~mcrecon.stats.PixelStats`,
e.g. from :meth:`~mcrecon.stats.PixelStats.from_moments` on a renderer's
mean / variance / count images, or from samples in memory with
:meth:`~mcrecon.stats.PixelStats.from_samples`) or, for methods that
filter individual samples, a :class:`~mcrecon.samples.SampleSet`; :func:`auto`
also takes a half-buffer pair ``(stats_a, stats_b)`` (two independent halves
of the samples, as renderers write dual buffers); its
keyword-only options are the method's options, validated by the one
option path of :mod:`mcrecon.methods`.  The image comes back in the
precision of the input values: float32 in, float32 out.

Functions: :func:`box`, :func:`gem`, :func:`awr`, :func:`splat`, :func:`ci`, :func:`auto`.
"""

from __future__ import annotations

import inspect

import numpy as np

from .errors import InputError
from .methods import get_method, method_class
from .samples import SampleSet

__all__ = ["box", "gem", "awr", "splat", "ci", "auto"]


def _run(name: str, source, reference, nonfinite: str, options: dict) -> np.ndarray:
    """The method's image of ``source`` (read by the one dispatcher), in the precision of the input values."""
    from .reconstruction import check_given_statistics, gather_inputs

    where = f"mcrecon.restoration.{name}"
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


def _make(name: str, summary: str, input_doc: str, notes: str, references: str, examples: str):
    cls = method_class(name)
    params = [inspect.Parameter("source", inspect.Parameter.POSITIONAL_ONLY)]
    opt_docs = []
    for o in cls.options:
        params.append(inspect.Parameter(o.name, inspect.Parameter.KEYWORD_ONLY, default=o.default))
        opt_docs.append(f"{o.name} : {getattr(o.type, '__name__', o.type)}, optional\n"
                        f"    {o.help}; {o.expectation()} (default {o.default!r}).")
    uses_ref = any(o.name == "oracle" for o in cls.options)
    if uses_ref:
        params.append(inspect.Parameter("reference", inspect.Parameter.KEYWORD_ONLY, default=None))
        opt_docs.append("reference : ndarray (H, W, C), optional\n    The reference image (for ``oracle=1``).")
    params.append(inspect.Parameter("nonfinite", inspect.Parameter.KEYWORD_ONLY, default="drop"))
    opt_docs.append("nonfinite : {'drop', 'zero', 'raise'}, optional\n"
                    "    Policy for NaN/Inf sample values of a SampleSet (default 'drop').")
    valid = {o.name for o in cls.options}

    def fn(source, /, *, reference=None, nonfinite="drop", **options):
        unknown = sorted(set(options) - valid)
        if unknown:
            raise InputError(f"mcrecon.restoration.{name}", unknown[0],
                             f"unknown option; valid: {', '.join(sorted(valid)) or '(none)'}")
        return _run(name, source, reference, nonfinite, options)

    fn.__name__ = fn.__qualname__ = name
    fn.__module__ = __name__
    fn.__signature__ = inspect.Signature(params, return_annotation=np.ndarray)
    body = "\n".join(opt_docs)
    fn.__doc__ = (f"{summary}\n\nParameters\n----------\n{input_doc}\n{body}\n\nReturns\n-------\n"
                  "image : ndarray (H, W, C)\n    float32 when the input values were float32, else float64.\n\n"
                  "Raises\n------\nInputError\n    Invalid options (the message lists the valid values), NaN/Inf "
                  "in the statistics, an input without any sample, the wrong kind of input.\n\n"
                  f"Notes\n-----\n{notes}\n\nReferences\n----------\n{references}\n\nExamples\n--------\n{examples}")
    return fn


_STATS = ("source : PixelStats\n    Pixel statistics, e.g. ``PixelStats.from_moments(mean, variance, count)`` "
          "or ``PixelStats.from_samples(...)``; a SampleSet is accepted too.")

box = _make(
    "box", "The pixel mean, empty pixels filled from their nearest sampled neighbour (the baseline).", _STATS,
    "Every other method is measured against this one.",
    ".. [1] (none: the estimator every Monte Carlo renderer starts from)",
    ">>> import numpy as np\n>>> from mcrecon import PixelStats\n>>> from mcrecon.restoration import box\n"
    ">>> st = PixelStats.from_moments(np.ones((2, 3, 3), np.float32), np.zeros((2, 3, 3)), 4)\n"
    ">>> box(st).dtype, box(st).shape\n(dtype('float32'), (2, 3, 3))")

gem = _make(
    "gem", "Greedy error minimization: per-pixel Gaussian scale selection (final reconstruction).", _STATS,
    "Selects, per pixel, among Gaussian filters sqrt(2) apart the largest scale whose bias is not yet\n"
    "significant (an ICI-style selector with error rate ``gamma``), with outlier removal on the stopping maps.",
    ".. [1] F. Rousselle, C. Knaus, M. Zwicker, \"Adaptive Sampling and Reconstruction using Greedy Error\n"
    "   Minimization\", ACM Transactions on Graphics 30(6) (SIGGRAPH Asia), 2011.",
    ">>> import numpy as np\n>>> from mcrecon import PixelStats\n>>> from mcrecon.restoration import gem\n"
    ">>> rng = np.random.default_rng(0)\n"
    ">>> mean = (1.0 + rng.normal(0, 0.1, (16, 16, 3))).astype(np.float32)\n"
    ">>> st = PixelStats.from_moments(mean, np.full((16, 16, 3), 0.16), 16)\n"
    ">>> out = gem(st, gamma=0.2)\n>>> out.dtype, bool(np.abs(out - 1).std() < np.abs(mean - 1).std())\n"
    "(dtype('float32'), True)")

awr = _make(
    "awr", "Adaptive wavelet rendering: soft thresholding of wavelet coefficients by their propagated variance.",
    _STATS,
    "CDF 9/7 (also LeGall 5/3 and Haar) coefficients are soft-thresholded by the variance of the pixel means\n"
    "propagated through the transform.  The default variance estimator ``range`` needs each pixel's sample\n"
    "range: statistics from moments carry none, so use ``variance='sample'`` with them.",
    ".. [1] R. S. Overbeck, C. Donner, R. Ramamoorthi, \"Adaptive Wavelet Rendering\", ACM Transactions on\n"
    "   Graphics 28(5) (SIGGRAPH Asia), 2009.",
    ">>> import numpy as np\n>>> from mcrecon import PixelStats\n>>> from mcrecon.restoration import awr\n"
    ">>> rng = np.random.default_rng(1)\n>>> mean = 1.0 + rng.normal(0, 0.1, (32, 32, 3))\n"
    ">>> st = PixelStats.from_moments(mean, np.full((32, 32, 3), 0.16), 16)\n"
    ">>> out = awr(st, variance='sample')\n>>> out.shape, bool(np.abs(out - 1).std() < np.abs(mean - 1).std())\n"
    "((32, 32, 3), True)")

splat = _make(
    "splat", "Progressive, energy-preserving, variable-width Epanechnikov splatting of individual samples.",
    "source : SampleSet\n    The samples (rounds are replayed in order; a single round is split into\n"
    "    doubling pseudo-rounds per pixel).",
    "Needs the individual samples: pixel statistics are refused.",
    ".. [1] F. Suykens, Y. D. Willems, \"Adaptive Filtering for Progressive Monte Carlo Image Rendering\",\n"
    "   WSCG 2000.",
    ">>> import numpy as np, mcrecon\n>>> from mcrecon.restoration import splat\n"
    ">>> rng = np.random.default_rng(2)\n>>> pos = (rng.random((3200, 2)) * 20).astype(np.float32)\n"
    ">>> samples = mcrecon.SampleSet(pos, np.ones((3200, 3), np.float32), width=20, height=20)\n"
    ">>> out = splat(samples)\n>>> out.dtype, bool(np.isclose(out.sum(), 3 * 400 * 1.0, rtol=1e-5))\n"
    "(dtype('float32'), True)")

ci = _make(
    "ci", "Tamstorf & Jensen's estimate: the per-pixel sample mean (Eq. 2, box filter).", _STATS,
    "The method's contribution is adaptive (where to stop sampling, by tone-mapped confidence intervals);\n"
    "offline its image is the pixel mean of the samples, exactly as :func:`box`.  Its options (the stopping\n"
    "rule) are validated here too, so a rule can be checked before an adaptive run.",
    ".. [1] R. Tamstorf, H. W. Jensen, \"Adaptive Sampling and Bias Estimation in Path Tracing\",\n"
    "   Rendering Techniques '97 (Eurographics Workshop on Rendering), 1997.",
    ">>> import numpy as np\n>>> from mcrecon import PixelStats\n>>> from mcrecon.restoration import box, ci\n"
    ">>> st = PixelStats.from_moments(np.random.default_rng(3).random((4, 5, 3)), np.zeros((4, 5, 3)), 2)\n"
    ">>> bool((ci(st, tolerance=0.01) == box(st)).all())\nTrue")

auto = _make(
    "auto", "Per-pixel choice among reconstructions by their estimated (reference-free) error.",
    "source : PixelStats, SampleSet or (PixelStats, PixelStats)\n    A SampleSet (the default candidates split "
    "its samples into two halves), or a half-buffer pair\n    ``(stats_a, stats_b)``: statistics of two independent "
    "halves of the samples (dual buffers a\n    renderer wrote; same size and channels, counts may differ), used as "
    "the two halves and\n    merged for the SURE candidates.  With one set of pixel statistics pass\n"
    "    ``candidates='box,gauss'`` (the SURE candidates).",
    "Candidates: the pixel mean, GEM's Gaussian scales (error by Stein's unbiased risk estimate with the\n"
    "exact centre weight), cross-filtered non-local means and the black boxes awr/splat/oidn (error by\n"
    "dual-buffer cross-validation); each pixel takes the candidate of least smoothed relative estimate.",
    ".. [1] C. Stein, \"Estimation of the mean of a multivariate normal distribution\", Ann. Statist. 9(6), 1981.\n"
    ".. [2] T.-M. Li, Y.-T. Wu, Y.-Y. Chuang, \"SURE-based optimization for adaptive sampling and\n"
    "   reconstruction\", ACM Transactions on Graphics 31(6), 2012.\n"
    ".. [3] F. Rousselle, C. Knaus, M. Zwicker, \"Adaptive rendering with non-local means filtering\",\n"
    "   ACM Transactions on Graphics 31(6), 2012.",
    ">>> import numpy as np\n>>> from mcrecon import PixelStats\n>>> from mcrecon.restoration import auto\n"
    ">>> rng = np.random.default_rng(4)\n>>> mean = 1.0 + rng.normal(0, 0.1, (24, 24, 3))\n"
    ">>> st = PixelStats.from_moments(mean, np.full((24, 24, 3), 0.16), 16)\n"
    ">>> out = auto(st, candidates='box,gauss')\n"
    ">>> out.shape, bool(np.abs(out - 1).std() < np.abs(mean - 1).std())\n((24, 24, 3), True)")


from ._lazy import public_dir as _public_dir  # noqa: E402

__dir__ = _public_dir(__name__)
