"""Per-sample features: albedo, normal, depth and any others a renderer sends.

A renderer can hand out, per sample, what its primary ray hit: the
surface's ``albedo`` (3 components), its shading ``normal`` (3) and the
hit's ``depth`` (1).  Feature-guided reconstruction (NFOR, RDFC-style
filters) uses them to tell texture from noise.  They travel with the
samples (``SampleSet(features=...)``, a sample log's ``/features/NAME``,
a renderer's ``SampleBatch.features``) and are accumulated per pixel like
the colour: :class:`~mcrecon.core.stats.PixelStats` keeps, per feature, a
``PixelStats`` of its components (mean, ``m2``, count: Welford within a
batch, Chan between batches), and each half buffer keeps its own.

The one validation path is :func:`check_features`: every feature an
(N,) or (N, k) array of a real dtype (at most :data:`MAX_COMPONENTS`
components), returned in native byte order; values that are not finite (a
depth of +inf where a ray left the scene, a NaN normal) or beyond
:data:`FEATURE_LIMIT` in magnitude (a "no hit" sentinel such as DBL_MAX)
are set to 0 and counted, because a feature is a guide, not radiance:
dropping the sample would lose its colour.  A sample the colour's NaN policy drops is dropped
from its features too (:func:`take_rows`).

An ``albedo`` is a reflectance and is read as one: :func:`check_features`
clamps it into [0, 1] (:data:`GUIDE_RANGES`, :func:`as_guide`).  Cycles'
"Denoising Albedo" carries an emitter's radiance (up to hundreds) where a
mirror or glass path ends on a light; read as a guide, that value would
make the demodulation divide by it, the feature prefilter and the
regression treat the pixel as a texture edge, and OIDN see an albedo
outside the range it is trained on.  The colour is never touched.
"""

from __future__ import annotations

import warnings
from typing import Mapping

import numpy as np

from .._lazy import public_dir as _public_dir
from ..errors import InputError, McreconWarning

__all__ = ["CANONICAL_FEATURES", "GUIDE_RANGES", "as_guide", "feature_components", "check_features", "feature_layout",
           "take_rows", "usable_layout", "usable_names"]

#: The documented feature names and their components.  Any other name is
#: kept and usable; its components are named "0", "1", ...
CANONICAL_FEATURES: dict[str, tuple[str, ...]] = {
    "albedo": ("R", "G", "B"),
    "normal": ("X", "Y", "Z"),
    "depth": ("Z",),
}


#: Feature values beyond this magnitude count as missing, as NaN and Inf do: a renderer's "no hit"
#: sentinel (DBL_MAX, 1e300) squared overflows the regression's and the gate's sums, and nfor and auto
#: wrote images of NaN with exit status 0; float32's FLT_MAX overflowed the float32 feature variance.
#: Any real albedo, normal or depth is far below it.
FEATURE_LIMIT = 1e30

#: Features that are reflectances, and the range every reader uses them in (guides, not radiance:
#: :func:`as_guide`).
GUIDE_RANGES: dict[str, tuple[float, float]] = {"albedo": (0.0, 1.0)}

#: Most components one feature may have: a writer's broadcasting slip gives an (N, N) array, whose
#: thousands of components the regression would solve for (a 32^2, 4-spp log ran for over 5 minutes).
MAX_COMPONENTS = 64


def within_feature_limit(arr: np.ndarray) -> np.ndarray:
    """Per entry of a float array: finite and within :data:`FEATURE_LIMIT` (False for NaN, Inf and
    "no hit" sentinels), the limit compared in the array's own precision."""
    if arr.dtype.itemsize < 4:  # half floats end below the limit
        return np.isfinite(arr)
    return np.abs(arr) <= arr.dtype.type(FEATURE_LIMIT)


def as_guide(name: str, arr: np.ndarray) -> np.ndarray:
    """``arr`` (a feature's values, any shape) clamped into the range of :data:`GUIDE_RANGES` for ``name``.

    The array itself comes back when nothing is outside the range (or the
    feature has none); otherwise a clamped copy of the same dtype.
    """
    rng = GUIDE_RANGES.get(str(name))
    if rng is None:
        return arr
    lo, hi = rng
    if arr.size and (arr.min() < lo or arr.max() > hi):
        return np.clip(arr, arr.dtype.type(lo), arr.dtype.type(hi))
    return arr


def feature_components(name: str, k: int) -> tuple[str, ...]:
    """Component names of a feature with ``k`` components (canonical names when they fit)."""
    canon = CANONICAL_FEATURES.get(name)
    if canon is not None and len(canon) == k:
        return canon
    return tuple(str(i) for i in range(k))


def feature_layout(features) -> dict[str, int]:
    """``{name: number of components}`` from a mapping of name to count, or a sequence of canonical names.

    >>> feature_layout(["albedo", "depth"])
    {'albedo': 3, 'depth': 1}
    """
    if features is None:
        return {}
    if isinstance(features, Mapping):
        out = {}
        for name, k in features.items():
            if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or int(k) < 1:
                raise InputError("features", str(name), f"got {k!r} components, expected a positive integer")
            out[str(name)] = int(k)
        return out
    if isinstance(features, str):
        features = [features]
    out = {}
    for name in features:
        if name not in CANONICAL_FEATURES:
            raise InputError("features", str(name), "a feature given by name alone must be one of "
                             f"{', '.join(CANONICAL_FEATURES)}; give others as a mapping name -> components")
        out[str(name)] = len(CANONICAL_FEATURES[name])
    return out


def check_features(features, n: int, *, where: str = "samples", error=InputError,
                   layout: Mapping[str, int] | None = None) -> tuple[dict[str, np.ndarray], int]:
    """Validate per-sample features for ``n`` samples: ``({name: (n, k) array}, n_zeroed)``.

    Each array comes back 2-D, C-contiguous, in a floating dtype (bool and
    float16 as float32, integers as float64).  Non-finite entries are set
    to 0 (in a copy) and counted in ``n_zeroed`` (samples with any such
    entry); an ``albedo`` is clamped into [0, 1] (:func:`as_guide`; not
    counted).  ``layout`` (name -> components), when given, restricts the
    result to those features, each of which must be present with that many
    components; features outside it are ignored.  Raises ``error(where,
    field, problem)`` naming ``features/NAME``.
    """
    given = {} if features is None else features
    if not isinstance(given, Mapping):
        raise error(where, "features", f"got {type(given).__name__}, expected a mapping name -> (N, k) array")
    names = list(given) if layout is None else list(layout)
    out: dict[str, np.ndarray] = {}
    bad_rows = None  # samples with a non-finite entry in any feature
    for name in names:
        if name not in given:
            raise error(where, f"features/{name}", f"missing: these statistics keep feature {name!r} "
                        f"(given: {', '.join(map(str, given)) or 'none'}); send it with every sample")
        arr = np.asarray(given[name])
        if arr.ndim == 1:
            arr = arr[:, None]
        if arr.ndim != 2 or arr.shape[0] != n:
            raise error(where, f"features/{name}", f"shape {np.shape(given[name])}, expected ({n},) or ({n}, k) "
                        "for one row per sample")
        if layout is not None and arr.shape[1] != layout[name]:
            raise error(where, f"features/{name}", f"{arr.shape[1]} component(s), expected {layout[name]}")
        if arr.dtype.kind not in "fiub":
            raise error(where, f"features/{name}", f"dtype {arr.dtype}, expected a numeric dtype "
                        "(integer, float or bool)")
        if arr.shape[1] == 0:
            raise error(where, f"features/{name}", f"shape {arr.shape}: no component; give at least one")
        if arr.shape[1] > MAX_COMPONENTS:
            raise error(where, f"features/{name}", f"shape {arr.shape}: {arr.shape[1]} components, at most "
                        f"{MAX_COMPONENTS} (one row per sample of (N,) or (N, k); an (N, N) array is usually "
                        "a broadcasting slip)")
        if arr.dtype.kind == "b" or (arr.dtype.kind == "f" and arr.dtype.itemsize < 4):
            arr = arr.astype(np.float32)  # a mask as 0/1; half floats widened
        elif arr.dtype.kind in "iu" or arr.dtype.itemsize > 8:
            arr = arr.astype(np.float64)
        elif not arr.dtype.isnative:  # big-endian from a file or a C writer: the kernels read native floats
            arr = arr.astype(arr.dtype.newbyteorder("="))
        arr = np.ascontiguousarray(arr)
        finite = within_feature_limit(arr)
        if not finite.all():
            bad = ~finite.all(axis=1)
            bad_rows = bad if bad_rows is None else bad_rows | bad
            arr = np.where(finite, arr, arr.dtype.type(0))
        out[str(name)] = as_guide(str(name), arr)  # a reflectance in [0, 1] (not counted: not an error)
    n_zeroed = 0 if bad_rows is None else int(bad_rows.sum())
    return out, n_zeroed


def warn_feature_zeroed(source: str, n_zeroed: int, *, stacklevel: int = 2, unit: str = "sample") -> None:
    """The one warning for samples (``unit``: or pixels of a feature image) whose non-finite feature entries
    were set to 0."""
    warnings.warn(f"{source}: features: {n_zeroed} {unit}(s) with NaN, Inf or beyond +-{FEATURE_LIMIT:.0e} "
                  "feature values set to 0 (a depth of inf where a ray left the scene is common; the colour "
                  "is kept)",
                  McreconWarning, stacklevel=stacklevel + 1)


def take_rows(features: Mapping[str, np.ndarray], rows) -> dict[str, np.ndarray]:
    """The features of the samples ``rows`` selects (a boolean mask or indices)."""
    return {name: arr[rows] for name, arr in features.items()}


def usable_layout(features: Mapping) -> dict[str, int]:
    """``{name: components}`` of the per-sample features a method can accumulate: (N,) or (N, k) arrays
    of a numeric dtype.  Others (an (N, 2, 2) matrix, strings) are left out, not refused: a method
    whose features are optional ignores what it cannot use (a method that requires features is refused
    when none is left)."""
    out = {}
    for name, arr in (features or {}).items():
        a = np.asarray(arr) if not hasattr(arr, "shape") else arr
        if len(a.shape) in (1, 2) and np.dtype(a.dtype).kind in "fiub" and (
                len(a.shape) == 1 or 0 < a.shape[1] <= MAX_COMPONENTS):
            out[str(name)] = 1 if len(a.shape) == 1 else int(a.shape[1])
    return out


def usable_names(source) -> tuple[str, ...]:
    """The features of a sample source (log or SampleSet) :func:`usable_layout` keeps, by their per-sample
    shapes (``feature_shapes``) and dtypes (``feature_dtypes`` where the source has them).

    A feature of the right kind but more than :data:`MAX_COMPONENTS` components is refused here, from its
    declared shape, before anything is read or allocated: a method reading it would size its statistics
    by it (an (N, 4e9) dataset declared and never written asked for 14 TiB)."""
    shapes = getattr(source, "feature_shapes", {}) or {}
    dtypes = getattr(source, "feature_dtypes", {}) or {}
    out = []
    for n in getattr(source, "feature_names", ()):
        shape = tuple(shapes.get(n, ()))
        if len(shape) > 1 or np.dtype(dtypes.get(n, np.float64)).kind not in "fiub" or shape == (0,):
            continue
        _check_width(source, n, shape)
        out.append(n)
    return tuple(out)


def _check_width(source, name, shape) -> None:
    """Refuse a feature of more than :data:`MAX_COMPONENTS` components per sample, naming it."""
    if shape and shape[0] > MAX_COMPONENTS:
        raise InputError(source_name(source), f"features/{name}", f"per-sample shape {shape}: {shape[0]} "
                         f"components, at most {MAX_COMPONENTS} (one row per sample of (N,) or (N, k); an (N, N) "
                         "array is usually a broadcasting slip): rewrite or delete it (methods that read no "
                         "features, such as box or gem, ignore it)")


def layout_of(stats_features: Mapping) -> dict[str, int]:
    """``{name: components}`` of a statistics' ``features`` dict (features merged on read: without a merge)."""
    if isinstance(getattr(stats_features, "layout", None), dict):
        return dict(stats_features.layout)
    return {name: len(st.channels) for name, st in stats_features.items()}


def source_name(src) -> str:
    """How messages name a sample source (its file, else its repr)."""
    path = getattr(src, "path", None)
    return str(path) if path is not None else str(getattr(src, "name", "samples"))


def source_features(source, features) -> tuple[str, ...]:
    """The feature names of ``source`` to accumulate: ``features`` checked against what it has.

    ``"all"``: every feature the source has; a name it lacks is refused
    naming the source and what it has.
    """
    have = tuple(getattr(source, "feature_names", ()))
    if features is None or (not isinstance(features, str) and len(features) == 0):
        return ()
    if isinstance(features, str):
        if features == "all":
            return have
        features = (features,)
    missing = [f for f in features if f not in have]
    if missing:
        raise InputError(source_name(source), "features", f"no feature {', '.join(map(repr, missing))}; "
                         f"it has: {', '.join(have) or '(none)'}")
    return tuple(features)


def source_layout(source, names) -> dict[str, int]:
    """``{name: components}`` of the features ``names`` of ``source`` (from its ``feature_shapes``)."""
    shapes = getattr(source, "feature_shapes", {})
    out = {}
    for name in names:
        shape = tuple(shapes[name])
        if len(shape) > 1:
            raise InputError(source_name(source), f"features/{name}", f"per-sample shape {shape}, expected () "
                             "or (k,): one row of components per sample")
        _check_width(source, name, shape)
        out[name] = int(shape[0]) if shape else 1
    return out


__dir__ = _public_dir(__name__)
