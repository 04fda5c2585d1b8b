"""Array-level reconstruction, one function per method (in the style of ``skimage.restoration``).

Each function takes pixel statistics (:class:`~mcrecon.core.stats.PixelStats`,
e.g. from :meth:`~mcrecon.core.stats.PixelStats.from_moments` on a renderer's
mean / variance / count images, or from samples in memory with
:meth:`~mcrecon.core.stats.PixelStats.from_samples`) or, for methods that
filter individual samples, a :class:`~mcrecon.core.samples.SampleSet`; :func:`auto`
also takes a half-buffer pair ``(stats_a, stats_b)`` (two independent halves
of the samples, as renderers write dual buffers); its
keyword-only options are the method's options, validated by the one
option path of :mod:`mcrecon.methods`.  The image comes back in the
precision of the input values: float32 in, float32 out.

Functions: :func:`box`, :func:`gem`, :func:`awr`, :func:`splat`, :func:`auto`, :func:`nfor` (``ci``'s offline image
is :func:`box`; its stopping rule is adaptive: :func:`mcrecon.adapt`).  Each is written out with the
method's options, so static tools see them; a test keeps them equal to the methods' options.
"""

from __future__ import annotations

import functools
import inspect

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


def _given_options(fn):
    """Run ``fn``'s method with the options the caller gave.

    The functions below are written out (their signatures and docstrings are what
    static tools and readers see), with each option's default shown; the call itself
    goes through here, which sees only what was given, so that an option left out
    takes the chosen variant's preset while a value given explicitly always wins --
    also one equal to the default shown.
    """
    name = fn.__name__
    valid = frozenset(inspect.signature(fn).parameters) - {"source", "reference", "nonfinite", "unknown"}

    @functools.wraps(fn)
    def call(source, /, *, reference=None, nonfinite="drop", **given):
        options = {k: v for k, v in given.items() if k in valid}
        unknown = {k: v for k, v in given.items() if k not in valid}
        return _run(name, source, reference, nonfinite, options, unknown)

    return call


@_given_options
def box(source, /, *, nonfinite="drop", **unknown) -> np.ndarray:
    """The pixel mean, empty pixels filled from their nearest sampled neighbour (the baseline).

    Parameters
    ----------
    source : PixelStats
        Pixel statistics, e.g. ``PixelStats.from_moments(mean, variance, count)`` or
        ``PixelStats.from_samples(...)``; a SampleSet is accepted too.
    nonfinite : {'drop', 'zero', 'raise'}, optional
        Policy for NaN/Inf sample values of a SampleSet (default 'drop').

    Returns
    -------
    image : ndarray (H, W, C)
        float32 when the input values were float32, else float64.

    Raises
    ------
    InputError
        Invalid or unknown options (the message lists the valid values), NaN/Inf in the
        statistics, an input without any sample, the wrong kind of input.

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


@_given_options
def gem(source, /, *, variant="robust", gamma=0.2, oracle=0, target_rel_mse=None, initial_spp=4, iterations=8,
        uniform_share=0.25, samples_per_pick=0, adaptive_scales=4, final_scales=8, final_outliers="adaptive",
        zero_variance_votes=2, channel_weights="relative", confirm_stops=1, subpixel_exact_below=0.0,
        reference=None, nonfinite="drop", **unknown) -> np.ndarray:
    """Greedy error minimization: per-pixel Gaussian scale selection (final reconstruction).

    Parameters
    ----------
    source : PixelStats
        Pixel statistics, e.g. ``PixelStats.from_moments(mean, variance, count)`` or
        ``PixelStats.from_samples(...)``; a SampleSet is accepted too.
    variant : {'robust', 'paper'}, optional
        Algorithm variant: 'paper' presets every option to the paper's algorithm; 'robust' is the measured
        default (departures documented on the method's page) (default "robust").
    gamma : float, optional
        Target error rate of the scale selector; a finite number with 0 < gamma < 0.4 (the paper's z(gamma) =
        -log(1 - (1.9 gamma)^(1/sqrt 2)) is only calibrated there; use e.g. 0.1 to 0.3, default 0.2) (default
        0.2; ``variant='paper'``: 0.1).
    oracle : {0, 1}, optional
        1: select and sample with the true bias from the reference (OUR-GRD) (default 0).
    target_rel_mse : float or None, optional
        Stop early when the estimated relative MSE (eps 0.01) reaches this; a finite number > 0 or None
        (default None).
    initial_spp : int, optional
        Samples per pixel of the uniform initial pass; an integer >= 1 (default 4).
    iterations : int, optional
        Adaptive iterations after the initial pass; an integer >= 1 (default 8).
    uniform_share : float, optional
        Share of each adaptive round spread uniformly over the film (0: the paper's greedy distribution
        alone); a finite number with 0 <= uniform_share <= 1 (default 0.25; ``variant='paper'``: 0.0).
    samples_per_pick : int, optional
        Samples each selected pixel spreads over its filter (0: the average spp of the budget, as in the
        paper); an integer >= 0 (default 0).
    adaptive_scales : int, optional
        Dyadic Gaussian scales from 1 px used while sampling; an integer with 1 <= adaptive_scales <= 10
        (default 4).
    final_scales : int, optional
        Gaussian scales sqrt(2) apart from sqrt(2) px in the final image; an integer with 1 <= final_scales <=
        16 (default 8).
    final_outliers : {'paper', 'adaptive'}, optional
        Final outlier removal: paper (2x size, coarser only) or adaptive (1x size, both ways) (default
        "adaptive"; ``variant='paper'``: "paper").
    zero_variance_votes : {0, 1, 2, 3}, optional
        Stopping-map votes of pixels with zero variance: 0 none, 1 adaptive phase, 2 final reconstruction, 3
        both (default 2; ``variant='paper'``: 3).
    channel_weights : {'relative', 'absolute'}, optional
        Final reconstruction: how the scale selector sums channels, relative (each channel's error over
        value^2 + 0.01, the pixel's relative MSE) or absolute (plain sum, the paper) (default "relative";
        ``variant='paper'``: "absolute").
    confirm_stops : {0, 1, 2}, optional
        Final reconstruction: a raw stop of pair k counts only if pair k+1 stops too (the widest pair has
        none: unconfirmed); 0 never (the paper), 1 Gaussian pairs (k >= 1), 2 every pair (default 1;
        ``variant='paper'``: 0).
    subpixel_exact_below : float, optional
        Filter scales with sigma below this (px) on the 4x4 subpixel grid itself (slower; 0: pixel-level
        equivalent kernel); a finite number >= 0 (default 0.0).
    reference : ndarray (H, W, C), optional
        The reference image (for ``oracle=1``).
    nonfinite : {'drop', 'zero', 'raise'}, optional
        Policy for NaN/Inf sample values of a SampleSet (default 'drop').

    Returns
    -------
    image : ndarray (H, W, C)
        float32 when the input values were float32, else float64.

    Raises
    ------
    InputError
        Invalid or unknown options (the message lists the valid values), NaN/Inf in the
        statistics, an input without any sample, the wrong kind of input.

    Notes
    -----
    Selects, per pixel, among Gaussian filters sqrt(2) apart the largest scale whose bias is not yet
    significant (an ICI-style selector with error rate ``gamma``), with outlier removal on the stopping maps.

    With ``variant='paper'`` every option not given takes the paper's value (given after each
    option above); a value given explicitly always wins, also one equal to the default shown.

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


@_given_options
def awr(source, /, *, variant="robust", wavelet="cdf97", cs=1.0, variance="sample", domain="log",
        log_offset=0.01, safeguard=2.0, levels=None, boundary="symmetric", propagation="exact",
        renorm=0.7071067811865476, sampling_renorm=1.05, sampling_levels=5, sampling_variance="contrast",
        per_coefficient=64, round_spp=4.0, initial_spp=16, priority_threshold=None, reconstruction="awr",
        nonfinite="drop", **unknown) -> np.ndarray:
    """Adaptive wavelet rendering: soft thresholding of wavelet coefficients by their propagated variance.

    Parameters
    ----------
    source : PixelStats
        Pixel statistics, e.g. ``PixelStats.from_moments(mean, variance, count)`` or
        ``PixelStats.from_samples(...)``; a SampleSet is accepted too.
    variant : {'robust', 'paper'}, optional
        Algorithm variant: 'paper' presets every option to the paper's algorithm; 'robust' is the measured
        default (departures documented on the method's page) (default "robust").
    wavelet : {'cdf97', 'legall53', 'haar'}, optional
        Wavelet basis (default "cdf97").
    cs : float, optional
        Smoothing constant c_s of Eq. 11 (0 = no smoothing); a finite number >= 0 (default 1.0).
    variance : {'range', 'contrast', 'sample'}, optional
        Sigma^2(F) estimator of the reconstruction (paper: range) (default "sample"; ``variant='paper'``:
        "range").
    domain : {'linear', 'log'}, optional
        Domain of the wavelet shrinkage: linear (paper) or log(mean + delta), delta = log_offset x the
        channel's mean pixel (signed channels stay linear) (default "log"; ``variant='paper'``: "linear").
    log_offset : float, optional
        Delta of the log domain as a fraction of the channel's mean pixel; a finite number > 0 (default 0.01).
    safeguard : float or None, optional
        Clamp each pixel into mean +- k standard errors of its mean and into the range of the samples around
        it (k; None: no clamp, the paper); a finite number >= 0 or None (default 2.0; ``variant='paper'``:
        None).
    levels : int or None, optional
        Reconstruction depth (default: floor(log2(min side)) - 2, at most 6); an integer with 0 <= levels <=
        12 or None (default None).
    boundary : {'symmetric', 'periodization'}, optional
        Wavelet boundary extension (default "symmetric").
    propagation : {'exact', 'cascade'}, optional
        Variance propagation: exact Eq. 9/10 or the paper's squared-tap DWT (default "exact").
    renorm : float, optional
        Sum of the squared reconstruction filters (paper 2^-1/2); a finite number > 0 (default
        0.7071067811865476).
    sampling_renorm : float, optional
        Sum of the squared sampling filters (paper 1.05); a finite number > 0 (default 1.05).
    sampling_levels : int, optional
        Highest scale level the sampler ranks (paper 5); an integer >= 0 (default 5).
    sampling_variance : {'range', 'contrast', 'sample'}, optional
        Sigma^2(F) estimator of the sampler (paper: contrast) (default "contrast").
    per_coefficient : int, optional
        Samples per selected level-0 coefficient (x 2^k at level k; paper 64); an integer >= 1 (default 64).
    round_spp : float, optional
        Samples per pixel placed per adaptive round (priority update interval); a finite number > 0 (default
        4.0).
    initial_spp : int, optional
        Uniform samples per pixel of the first round (paper 4; capped by the budget); an integer >= 1 (default
        16; ``variant='paper'``: 4).
    priority_threshold : float or None, optional
        Stop sampling when no priority exceeds this; a finite number or None (default None).
    reconstruction : {'awr', 'box'}, optional
        Final image of an adaptive run: awr, or box (AWR sampling only) (default "awr").
    nonfinite : {'drop', 'zero', 'raise'}, optional
        Policy for NaN/Inf sample values of a SampleSet (default 'drop').

    Returns
    -------
    image : ndarray (H, W, C)
        float32 when the input values were float32, else float64.

    Raises
    ------
    InputError
        Invalid or unknown options (the message lists the valid values), NaN/Inf in the
        statistics, an input without any sample, the wrong kind of input.

    Notes
    -----
    CDF 9/7 (also LeGall 5/3 and Haar) coefficients are soft-thresholded by the variance of the pixel means
    propagated through the transform.  The default variance estimator ``range`` needs each pixel's sample
    range: statistics from moments carry none, so use ``variance='sample'`` with them.

    With ``variant='paper'`` every option not given takes the paper's value (given after each
    option above); a value given explicitly always wins, also one equal to the default shown.

    References
    ----------
    .. [1] R. S. Overbeck, C. Donner, R. Ramamoorthi, "Adaptive Wavelet Rendering", ACM Transactions on
       Graphics 28(5) (SIGGRAPH Asia), 2009.

    Examples
    --------
    >>> import numpy as np
    >>> from mcrecon import PixelStats
    >>> from mcrecon.restoration import awr
    >>> rng = np.random.default_rng(1)
    >>> mean = 1.0 + rng.normal(0, 0.1, (32, 32, 3))
    >>> st = PixelStats.from_moments(mean, np.full((32, 32, 3), 0.16), 16)
    >>> out = awr(st, variance='sample')
    >>> out.shape, bool(np.abs(out - 1).std() < np.abs(mean - 1).std())
    ((32, 32, 3), True)
    """


@_given_options
def splat(source, /, *, variant="robust", alpha=0.5, c=2.0, c_prime=8.0, initial_spp=16, min_width=1.0,
          max_width=32.0, boundary="mirror", norm="luminance", spread="consistent", outlier_k=2.0,
          guide="local_mean", false_rejection=0.05, spread_c=8.0, spread_alpha=0.3, feature_gate="auto",
          nonfinite="drop", **unknown) -> np.ndarray:
    """Progressive, energy-preserving, variable-width Epanechnikov splatting of individual samples.

    Parameters
    ----------
    source : SampleSet
        The samples (rounds are replayed in order; a single round is split into doubling pseudo-rounds per
        pixel).
    variant : {'robust', 'outliers', 'paper'}, optional
        Algorithm variant: 'paper' presets every option to the paper's algorithm; 'robust' is the measured
        default (departures documented on the method's page); 'outliers' the default before issue 26
        (default "robust").
    alpha : float, optional
        Exponent of N in the kernel width (Eq. 8), 0 < alpha <= 1; a finite number with 0 < alpha <= 1 (the
        paper uses 1.5/5; 1/5 and 1/2 are the classical extremes) (default 0.5; ``variant='paper'``: 0.3).
    c : float, optional
        Kernel diameter constant C in pixels (Eq. 8; the paper: 4); a finite number > 0 (default 2.0;
        ``variant='paper'``: 4.0).
    c_prime : float, optional
        Pilot kernel diameter constant C' in pixels (C' N0^-1/2); a finite number > 0 (default 8.0).
    initial_spp : int, optional
        Samples per pixel of the first round N0 (the paper: 1); an integer >= 1 (default 16;
        ``variant='outliers'``: 1; ``variant='paper'``: 1).
    min_width : float, optional
        Smallest kernel diameter in pixels (>= 1); a finite number >= 1 (default 1.0).
    max_width : float, optional
        Largest kernel diameter in pixels (cap for huge G/f; >= min_width); a finite number >= 1 (default
        32.0).
    boundary : {'mirror', 'renormalize', 'none'}, optional
        Boundary-bias remedy (default "mirror").
    norm : {'luminance', 'mean', 'max'}, optional
        Scalar value of a colour sample in Eq. 8 (default "luminance").
    spread : {'all', 'outliers', 'consistent'}, optional
        Which samples are splatted: all (the paper), outliers (only the excess of outliers above their 3x3
        neighbourhood's mean + k std; the rest stays in its pixel) or consistent (as outliers, and the
        other samples into the pixels whose statistics match) (default "consistent"; ``variant='paper'``:
        "all"; ``variant='outliers'``: "outliers").
    outlier_k : float, optional
        With spread='outliers': a sample is an outlier above mean + k std of the G of its 3x3 neighbourhood's
        samples; a finite number >= 0 (default 2.0).
    guide : {'none', 'local_mean'}, optional
        Footprint weights of the spread part: none (Epanechnikov, the paper) or local_mean (Epanechnikov times
        the pooled 3x3 mean of G at each pixel) (default "local_mean"; ``variant='paper'``: "none").
    false_rejection : float, optional
        With spread='consistent': rate at which two pixels of the same expectation are told apart (sets the
        gate's k standard errors); a finite number with 0 < false_rejection < 1 (default 0.05).
    spread_c : float, optional
        With spread='consistent': Eq. 8's C (diameter in pixels at N = 1, G/f = 1) of the consistent
        samples' kernels; a finite number > 0 (default 8.0).
    spread_alpha : float, optional
        With spread='consistent': Eq. 8's exponent of N for the consistent samples' kernels (the paper's
        1.5/5); a finite number with 0 < spread_alpha <= 1 (default 0.3).
    feature_gate : {'auto', 'none'}, optional
        With spread='consistent': also refuse a pixel whose feature means (albedo, normal, depth) differ by
        more than k times the pixels' own feature spread (auto: when the samples carry features) or compare
        the colour only (none) (default "auto").
    nonfinite : {'drop', 'zero', 'raise'}, optional
        Policy for NaN/Inf sample values of a SampleSet (default 'drop').

    Returns
    -------
    image : ndarray (H, W, C)
        float32 when the input values were float32, else float64.

    Raises
    ------
    InputError
        Invalid or unknown options (the message lists the valid values), NaN/Inf in the
        statistics, an input without any sample, the wrong kind of input.

    Notes
    -----
    Needs the individual samples: pixel statistics are refused.

    With ``variant='paper'`` every option not given takes the paper's value (given after each
    option above); a value given explicitly always wins, also one equal to the default shown.

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


@_given_options
def auto(source, /, *, candidates="box,gauss,nlm", feature_candidates="nfor,nfor_own,dnlm,mix,fbil", scales=8, smooth=2.0, nlm_radius=3, nlm_patch=1,
         nlm_k=0.45, initial_spp=4, iterations=4, sampling="gem", uniform_share=0.5, safeguard=4.0,
         global_prior=3.0, nonfinite="drop", **unknown) -> np.ndarray:
    """Per-pixel choice among reconstructions by their estimated (reference-free) error.

    Parameters
    ----------
    source : PixelStats, SampleSet or (PixelStats, PixelStats)
        A SampleSet (the default candidates split its samples into two halves), or a half-buffer pair
        ``(stats_a, stats_b)``: statistics of two independent halves of the samples (dual buffers a renderer
        wrote; same size and channels, counts may differ), used as the two halves and merged for the SURE
        candidates.  With one set of pixel statistics pass ``candidates='box,gauss'`` (the SURE candidates).
    candidates : str, optional
        Comma-separated candidate reconstructions: box, gauss, nlm, awr, splat, oidn (nlm/awr/splat/oidn need
        the samples: dual buffers); a string (default "box,gauss,nlm").
    feature_candidates : str, optional
        When the statistics carry features: comma-separated feature-guided candidates added to candidates, on
        the halves: nfor (first-order regression on the other half's weights and features, Bitterli et al.
        2016; SURE), nfor_own (the same on the half's own), dnlm (NL-means of the colour divided by the
        albedo), mix (nfor_own and dnlm averaged 1:2, 1:1, 2:1), xbil (cross-bilateral, Rousselle et al.
        2013); fbil (bilateral with feature weights only, SURE) from pixel statistics without halves; none:
        colour only; a string (default "nfor,nfor_own,dnlm,mix,fbil").
    scales : int, optional
        Gaussian scales of the gauss candidates (GEM's final bank); an integer with 1 <= scales <= 16 (default
        8).
    smooth : float, optional
        Sigma (px) of the smoothing of the error maps before the choice (0: none); a finite number with 0 <=
        smooth <= 32 (default 2.0).
    nlm_radius : int, optional
        NL-means search window radius r ((2r+1)^2 pixels); an integer with 1 <= nlm_radius <= 15 (default 3).
    nlm_patch : int, optional
        NL-means patch radius f ((2f+1)^2 pixels); an integer with 0 <= nlm_patch <= 5 (default 1).
    nlm_k : float, optional
        NL-means damping k of the variance-normalised distance; a finite number > 0 (default 0.45).
    initial_spp : int, optional
        Samples per pixel of the uniform initial pass (>= 4: two per half); an integer >= 1 (default 4).
    iterations : int, optional
        Adaptive rounds after the initial pass; an integer >= 1 (default 4).
    sampling : {'gem', 'uniform', 'greedy'}, optional
        Adaptive runs: gem (GEM's greedy relative-MSE placement for part of each round, the rest uniform;
        measured best, docs/methods/auto.md), uniform rounds, or greedy placement by auto's own error
        estimates (default "gem").
    uniform_share : float, optional
        With sampling='gem': share of each adaptive round spread uniformly (a defence against GEM's
        estimates where they mislead); a finite number with 0 <= uniform_share <= 1 (default 0.5).
    safeguard : float or None, optional
        Clamp each pixel into mean +- k standard errors of its mean and into the range of the samples around
        it (k; None: no clamp); a finite number >= 0 or None (default 4.0).
    global_prior : float or None, optional
        Z: every pixel takes the candidate of least summed estimate over the image unless another's smoothed
        estimate is lower by more than z standard errors (None: off, the plain per-pixel choice;
        docs/methods/auto.md); a finite number >= 0 or None (default 3.0).
    nonfinite : {'drop', 'zero', 'raise'}, optional
        Policy for NaN/Inf sample values of a SampleSet (default 'drop').

    Returns
    -------
    image : ndarray (H, W, C)
        float32 when the input values were float32, else float64.

    Raises
    ------
    InputError
        Invalid or unknown options (the message lists the valid values), NaN/Inf in the
        statistics, an input without any sample, the wrong kind of input.

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
    >>> import numpy as np
    >>> from mcrecon import PixelStats
    >>> from mcrecon.restoration import auto
    >>> rng = np.random.default_rng(4)
    >>> mean = 1.0 + rng.normal(0, 0.1, (24, 24, 3))
    >>> st = PixelStats.from_moments(mean, np.full((24, 24, 3), 0.16), 16)
    >>> out = auto(st, candidates='box,gauss')
    >>> out.shape, bool(np.abs(out - 1).std() < np.abs(mean - 1).std())
    ((24, 24, 3), True)
    """



@_given_options
def nfor(source, /, *, variant="robust", bandwidths="0.5,1.0", radius=9, patch=3, feature_radius=5,
         feature_patch=3, feature_k=0.5, second_pass=True, ridge=1e-10, safeguard=4.0, threads=None,
         nonfinite="drop", **unknown) -> np.ndarray:
    """Feature-guided first-order regression on half buffers (NFOR): denoising with albedo, normal, depth.

    Parameters
    ----------
    source : SampleSet or (PixelStats, PixelStats)
        Samples with per-sample features (``SampleSet(features=...)``: split into two halves here), or a
        half-buffer pair ``(stats_a, stats_b)`` of two independent halves with features
        (``PixelStats(features=...)``).  Sources without features are refused.
    variant : {'robust', 'paper'}, optional
        Algorithm variant: 'paper' is the reference implementation's algorithm; 'robust' clamps its image
        into each pixel's confidence interval (``safeguard``, docs/methods/nfor.md) (default "robust").
    bandwidths : str, optional
        NL-means bandwidths k of the regression's candidates (one or two, comma separated; the paper: 0.5,1.0)
        (default "0.5,1.0").
    radius : int, optional
        Regression window radius (the window is (2r+1)^2; paper: 9); an integer with 1 <= radius <= 30
        (default 9).
    patch : int, optional
        NL-means patch radius of the regression weights (paper: 3); an integer with 0 <= patch <= 10
        (default 3).
    feature_radius : int, optional
        Search radius of the feature prefilter (paper: 5); an integer with 0 <= feature_radius <= 30
        (default 5).
    feature_patch : int, optional
        Patch radius of the feature prefilter (paper: 3); an integer with 0 <= feature_patch <= 10 (default 3).
    feature_k : float, optional
        Bandwidth of the feature prefilter (paper: 0.5); a finite number > 0 (default 0.5).
    second_pass : bool, optional
        Sec. 5.4's second regression of the averaged halves (default True).
    ridge : float, optional
        Ridge on the regression's non-constant columns (standardised features), times the window's total
        weight: makes flat or collinear features solvable; a finite number with 0 <= ridge <= 1
        (default 1e-10).
    safeguard : float or None, optional
        Clamp each pixel into mean +- k standard errors of its mean (the variance floored by its
        neighbourhood's, in albedo units) and into the range of the samples around it (k; None: no clamp, the
        paper); a finite number >= 0 or None (default 4.0; ``variant='paper'``: None).
    threads : int or None, optional
        Worker threads (default: $MCRECON_THREADS, else the usable cores); the result does not depend on it.
    nonfinite : {'drop', 'zero', 'raise'}, optional
        Policy for NaN/Inf sample values of a SampleSet (default 'drop').

    Returns
    -------
    image : ndarray (H, W, C)
        float32 when the input values were float32, else float64.

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
