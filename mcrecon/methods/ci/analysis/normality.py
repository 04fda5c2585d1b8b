"""Chi-square test of the normality the ``ci`` interval assumes.

Tamstorf and Jensen, Sec. 3, 5.1, Eq. (16): m independent estimates of n
samples per pixel, ``classes`` equiprobable classes of N(mu-hat, s^2),
Pearson's statistic z against the chi2(classes - 3) quantile.
:func:`chi2_normality` (on estimates), :func:`repeated_estimates` (from a
renderer), :func:`normality_experiment` (both: the paper's Sec. 5.1
experiment), :class:`ChiSquareResult`.

References
----------
.. [1] R. Tamstorf, H. W. Jensen, "Adaptive Sampling and Bias Estimation
   in Path Tracing", Rendering Techniques '97 (Proc. 8th Eurographics
   Workshop on Rendering), 1997.
.. [2] H. Chernoff, E. L. Lehmann, "The use of maximum likelihood
   estimates in chi-square tests for goodness of fit", Ann. Math. Statist.
   25(3), 1954.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ....errors import InputError
from ....core.requests import SampleRequest, validate_reply
from ....core.stats import PixelStats

__all__ = ["ChiSquareResult", "chi2_normality", "repeated_estimates", "normality_experiment"]


@dataclasses.dataclass(eq=False)
class ChiSquareResult:
    """Result of :func:`chi2_normality`.

    Attributes
    ----------
    z : ndarray (..., C)
        Pearson's statistic (Eq. 16); 0 where untestable.
    rejected : ndarray of bool (..., C)
        ``z > critical``.
    testable : ndarray of bool (..., C)
        The m estimates are not all equal (a zero-variance pixel has no
        N(mu, s^2) to test against; it is excluded from the rate).
    critical : float
        ``chi2(classes - 3)`` quantile at ``1 - alpha`` (11.07 for 8, 5%).
    df, classes, m, alpha
    """

    z: np.ndarray
    rejected: np.ndarray
    testable: np.ndarray
    critical: float
    df: int
    classes: int
    m: int
    alpha: float

    @property
    def rejection_rate(self) -> float:
        """Fraction of testable (pixel, channel) tests rejected."""
        t = self.testable
        return float(self.rejected[t].mean()) if t.any() else 0.0

    def rejection_rate_per_channel(self) -> list[float]:
        t = self.testable.reshape(-1, self.z.shape[-1])
        r = self.rejected.reshape(-1, self.z.shape[-1])
        return [float(r[t[:, c], c].mean()) if t[:, c].any() else 0.0 for c in range(t.shape[1])]

    @property
    def z_map(self) -> np.ndarray:
        """Largest z over the channels, per pixel (the Fig. 1 map)."""
        return np.max(self.z, axis=-1)

    def summary(self) -> dict:
        return {"classes": self.classes, "df": self.df, "m": self.m, "alpha": self.alpha,
                "critical": self.critical, "rejection_rate": self.rejection_rate,
                "rejection_rate_per_channel": self.rejection_rate_per_channel(),
                "tests": int(self.testable.sum()), "untestable": int((~self.testable).sum()),
                "mean_z": float(self.z[self.testable].mean()) if self.testable.any() else 0.0}


def chi2_normality(estimates, *, classes: int = 8, alpha: float = 0.05) -> ChiSquareResult:
    """Chi-square goodness-of-fit test of normality per pixel (Eq. 16).

    From m estimates of a pixel: mean mu-hat and sample variance s^2; the
    ``classes`` equiprobable classes of N(mu-hat, s^2) are delimited by its
    ``1/classes, ..., (classes-1)/classes`` quantiles; ``z = sum_i (O_i -
    m/classes)^2 / (m/classes)``.  Rejected where z exceeds the ``1 -
    alpha`` quantile of chi2 with ``classes - 3`` degrees of freedom (two
    parameters estimated), computed with scipy: 11.07 for 8 classes at 5%.

    Note: mu-hat and s^2 come from the ungrouped estimates, so under
    normality z follows chi2(classes - 3) only approximately: Chernoff and
    Lehmann [2] show its limit lies between chi2(classes-3) and
    chi2(classes-1); for 8 classes the 5% test rejects about 6% of truly
    normal pixels (5.8% at m = 100).

    Parameters
    ----------
    estimates : array_like (m, ...) or (m, ..., C)
        m independent estimates per pixel (and channel) along axis 0.
    classes : int
        Number of equiprobable classes (>= 4: the test needs df >= 1).
    alpha : float
        Level of the test.

    Returns
    -------
    ChiSquareResult
        Arrays shaped like ``estimates[0]`` (a trailing channel axis of 1 is
        added to 1-D or 2-D per-estimate shapes).

    References
    ----------
    .. [1] Tamstorf and Jensen 1997, Sec. 3 and 5.1, Eq. (16).
    .. [2] Chernoff and Lehmann 1954.
    """
    from scipy import stats as sps

    where = "chi2_normality"
    x = np.asarray(estimates, dtype=np.float64)
    if x.ndim < 2:
        raise InputError(where, "estimates", f"shape {x.shape}, expected (m, ...) with m estimates per pixel")
    if x.ndim <= 3:
        x = x[..., None]
    m = x.shape[0]
    if not isinstance(classes, (int, np.integer)) or isinstance(classes, bool) or classes < 4:
        raise InputError(where, "classes", f"got {classes!r}, expected an integer >= 4 (df = classes - 3)")
    if not (isinstance(alpha, (int, float)) and 0.0 < alpha < 1.0):
        raise InputError(where, "alpha", f"got {alpha!r}, expected 0 < alpha < 1")
    if m < 2 * classes:
        raise InputError(where, "estimates", f"{m} estimates per pixel, expected at least 2 x classes = "
                         f"{2 * classes} (the paper uses m = 100 for 8 classes)")
    if not np.isfinite(x).all():
        raise InputError(where, "estimates", f"{int((~np.isfinite(x)).sum())} non-finite value(s)")
    mu = x.mean(axis=0)
    s = x.std(axis=0, ddof=1)
    # Constant estimates (s = 0, up to rounding of the mean) have no normal
    # law to test against.
    spread = x.max(axis=0) - x.min(axis=0)
    testable = spread > 0
    bounds = sps.norm.ppf(np.arange(1, classes) / classes)
    expected = m / classes
    z = np.zeros(mu.shape)
    below_prev = np.zeros(mu.shape)
    safe_s = np.where(testable, s, 1.0)
    for i in range(classes):
        if i < classes - 1:
            # Class i is (mu + s q_{i-1}, mu + s q_i]: count x <= mu + s q_i.
            below = np.sum(x <= mu + safe_s * bounds[i], axis=0).astype(np.float64)
        else:
            below = np.full(mu.shape, float(m))
        obs = below - below_prev
        z += (obs - expected) ** 2 / expected
        below_prev = below
    z = np.where(testable, z, 0.0)
    df = classes - 3
    crit = float(sps.chi2.ppf(1.0 - alpha, df))
    return ChiSquareResult(z=z, rejected=testable & (z > crit), testable=testable, critical=crit, df=df,
                           classes=int(classes), m=int(m), alpha=float(alpha))


def repeated_estimates(renderer, *, n: int, m: int, seed: int = 0) -> np.ndarray:
    """m independent n-sample pixel means from a renderer, (m, H, W, C).

    Each estimate is its own request (``counts = n`` everywhere) with its
    own seed, so the estimates are independent even for a renderer that
    stratifies the samples within a request.
    """
    where = "repeated_estimates"
    for name, v, lo in (("n", n, 1), ("m", m, 2)):
        if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v < lo:
            raise InputError(where, name, f"got {v!r}, expected an integer >= {lo}")
    for attr in ("width", "height", "channels", "render"):
        if not hasattr(renderer, attr):
            raise InputError(where, "renderer", f"missing {attr}: expected a mcrecon.renderers.protocol.Renderer")
    w, h = int(renderer.width), int(renderer.height)
    chans = tuple(renderer.channels)
    seeds = np.random.SeedSequence(int(seed)).generate_state(int(m), np.uint32)
    counts = np.full((h, w), int(n), np.int64)
    out = np.empty((int(m), h, w, len(chans)))
    name = str(getattr(renderer, "name", type(renderer).__name__))
    for r in range(int(m)):
        req = SampleRequest(w, h, counts=counts, round_index=r, seed=int(seeds[r]))
        batch = validate_reply(req, renderer.render(req), n_channels=len(chans), renderer=name)
        st = PixelStats.from_samples(batch.positions, batch.values, width=w, height=h, channels=chans,
                                     nonfinite="raise")
        out[r] = st.mean
    return out


def normality_experiment(renderer, *, n: int = 10, m: int = 100, seed: int = 0, classes: int = 8,
                         alpha: float = 0.05) -> ChiSquareResult:
    """The paper's Sec. 5.1 experiment on any renderer.

    ``m`` independent estimates of ``n`` samples per pixel
    (:func:`repeated_estimates`), then :func:`chi2_normality`.  The paper:
    n = 10, m = 100 on a Cornell box rejects ~10% of the pixels; n = 50
    about 7%.
    """
    est = repeated_estimates(renderer, n=n, m=m, seed=seed)
    return chi2_normality(est, classes=classes, alpha=alpha)
