"""Per-pixel sample statistics, built by streaming samples in chunks.

:class:`PixelStats` keeps, per pixel and channel, the sample count, the
mean and the sum of squared deviations ``m2`` (Welford updates within a
batch, Chan et al. merges between batches), the minimum and maximum, and
optionally per-subpixel sums and counts on an ``s x s`` grid per pixel
(kept only for a method that declares ``requires.subpixels``: GEM asks
for its 4 x 4 grid only with ``subpixel_exact_below > 0``; the grid costs
s^2 times the image).  Memory is bounded by the image (times s^2 with a
grid), never by the sample count.  Statistics can also be built from a
renderer's per-pixel mean / variance / count images
(:meth:`PixelStats.from_moments`), and :func:`fill_from_neighbours` is
the one policy for pixels with fewer than two samples.

Welford's update keeps the variance accurate for values near 1e6 with a
spread of 1e-3, where a sum of squares loses every significant digit.

References
----------
.. [1] B. P. Welford, "Note on a method for calculating corrected sums of
   squares and products", Technometrics 4(3), 1962.
.. [2] T. F. Chan, G. H. Golub, R. J. LeVeque, "Updating formulae and a
   pairwise algorithm for computing sample variances", 1979.
"""

from __future__ import annotations

import os

from typing import Iterable, Sequence

import numpy as np

from ..errors import InputError
from .features import (check_features, feature_components, feature_layout, layout_of, source_features, source_layout,
    warn_feature_zeroed)
from .merge import NO_RANGE, MergedOnRead, _accumulate
from .moments import stats_from_moments
from .samples import (apply_nonfinite, check_memory, check_policy, check_samples, one_float_dtype,
    touches_window, warn_nonfinite)


from .._lazy import public_dir as _public_dir

__all__ = ['PixelStats']


def _feature_stats(width: int, height: int, name: str, k: int, where: str = "PixelStats") -> "PixelStats":
    """Empty statistics of a feature of ``k`` components: count, mean and ``m2``, no range (no method reads a
    feature's extremes)."""
    return PixelStats(width, height, feature_components(name, k), where=where, keep_range=False)


class PixelStats:
    """Running per-pixel statistics of Monte Carlo samples.

    Parameters
    ----------
    width, height : int
        Film size in pixels.
    channels : sequence of str
        Channel names.
    subpixels : int, optional
        Subpixel grid resolution per pixel axis for ``sub_sum`` and
        ``sub_count``; 0 or 1 keeps no subpixel data (1 would equal the
        pixel sums).  GEM uses 4.
    features : mapping of str to int, or sequence of str, optional
        Per-sample features to accumulate (name -> number of components,
        or canonical names: ``albedo``, ``normal``, ``depth``;
        :mod:`mcrecon.core.features`).  Every :meth:`add` must then give them.
    where : str, optional
        The source named in the error when the film's arrays would need more
        memory than the machine has available (:func:`mcrecon.core.samples.check_memory`).
    keep_range : bool
        Keep each pixel's smallest and largest sample (``min``, ``max``);
        False for a feature's statistics, whose extremes no method reads
        (they would cost 16 bytes a pixel and component in every copy).

    Attributes
    ----------
    count : ndarray of int64, shape (H, W)
    mean : ndarray of float64, shape (H, W, C)
        0 in empty pixels.
    m2 : ndarray of float64, shape (H, W, C)
        Sum of squared deviations from the mean.
    min, max : ndarray of float64, shape (H, W, C), or None
        +inf / -inf in empty pixels; None without ``keep_range`` (then
        ``has_range`` is False).
    sub_sum : ndarray of float64, shape (H*s, W*s, C), or None
    sub_count : ndarray of int64, shape (H*s, W*s), or None
    n_dropped : int
        Samples skipped by the ``drop`` non-finite policy.
    n_zeroed : int
        Samples whose non-finite values the ``zero`` policy replaced.
    features : dict of str to PixelStats
        Per feature, the statistics of its components (channels named by
        :func:`~mcrecon.core.features.feature_components`: ``albedo`` R,G,B,
        ``normal`` X,Y,Z, ``depth`` Z); same film and counts as the
        colour; count, mean and ``m2`` only (no range: ``min`` None).
        Empty when none are kept.
    n_feature_zeroed : int
        Samples whose non-finite feature entries were set to 0.
    has_range : bool
        Whether ``min`` and ``max`` are known (False for :meth:`from_moments`).
    dtype : numpy dtype
        The floating dtype of the values these statistics were built from
        (float32 if every batch was float32; float64 otherwise or when
        empty).  The statistics themselves are float64; array-level
        functions return images in this dtype.
    """

    #: ``(y0, x0, film_width, film_height)`` for the statistics of a window of a film (:meth:`window_of`):
    #: batches are then in film positions, and the samples of other pixels are skipped.  None: the film.
    _window = None
    #: The film's image-wide values of :func:`~mcrecon.core.fill.mean_variance_policy` (a callable giving a
    #: :class:`~mcrecon.core.fill.FilmRange`) for the statistics of a tile cut from a film
    #: (:func:`~mcrecon.offline.tiles.reconstruct_tiles` sets it; crops keep it, a merge drops it).  None: these
    #: statistics' own.
    film_fill = None

    def __init__(self, width: int, height: int, channels: Sequence[str] = ("R", "G", "B"), *,
                 subpixels: int = 0, features=None, where: str = "PixelStats", keep_range: bool = True):
        width, height = int(width), int(height)
        if width < 1 or height < 1:
            raise InputError("PixelStats", "width/height", f"got {width}x{height}, expected at least 1x1")
        subpixels = int(subpixels)
        if subpixels < 0:
            raise InputError("PixelStats", "subpixels", f"got {subpixels}, expected 0 or a positive integer")
        self.width, self.height = width, height
        self.channels = tuple(str(c) for c in channels)
        if not self.channels:
            raise InputError("PixelStats", "channels", "expected at least one channel name")
        c = len(self.channels)
        self.subpixels = subpixels if subpixels > 1 else 0
        layout = feature_layout(features)
        n_feat = sum(layout.values())
        # count, mean, m2, min, max (+ subpixels) (+ each feature's count, mean, m2)
        per_pixel = 8 + (4 if keep_range else 2) * 8 * c + self.subpixels ** 2 * 8 * (c + 1) + 8 * len(layout) \
            + 2 * 8 * n_feat
        check_memory(where, "width/height", float(width) * height * per_pixel,
                     f"the per-pixel statistics of a {width}x{height} film with {c} channel(s)",
                     "use a machine with more memory, or a smaller film")
        self.count = np.zeros((height, width), np.int64)
        self.mean = np.zeros((height, width, c), np.float64)
        self.m2 = np.zeros((height, width, c), np.float64)
        self.min = np.full((height, width, c), np.inf) if keep_range else None
        self.max = np.full((height, width, c), -np.inf) if keep_range else None
        if self.subpixels:
            s = self.subpixels
            self.sub_sum = np.zeros((height * s, width * s, c), np.float64)
            self.sub_count = np.zeros((height * s, width * s), np.int64)
        else:
            self.sub_sum = None
            self.sub_count = None
        self.n_dropped = 0
        self.n_zeroed = 0
        self.n_feature_zeroed = 0
        self.features = {name: _feature_stats(width, height, name, k, where) for name, k in layout.items()}
        #: False for statistics built from moments (:meth:`from_moments`):
        #: ``min`` / ``max`` are then unknown (NaN), or not kept (None).
        self.has_range = bool(keep_range)
        self._value_dtype = None

    @classmethod
    def window_of(cls, film_width: int, film_height: int, window, channels: Sequence[str] = ("R", "G", "B"), *,
                  subpixels: int = 0, features=None, where: str = "PixelStats") -> "PixelStats":
        """Empty statistics of the pixels ``window`` = ``(y0, y1, x0, x1)`` of a ``film_width`` x ``film_height``
        film, to which whole batches of the film's samples are added (:meth:`add`, in film positions).

        Runs of a pixel's consecutive samples are found on the whole batch, as
        the film's statistics find them, and only the window's are
        accumulated: the result is the film's statistics cropped to the
        window (:meth:`crop`), bit for bit, holding the window's pixels
        only.  The counts of dropped, zeroed and feature-zeroed samples are
        the whole batches' (the policy is applied to the film's samples).
        """
        y0, y1, x0, x1 = (int(v) for v in window)
        fw, fh = int(film_width), int(film_height)
        if not (0 <= y0 < y1 <= fh and 0 <= x0 < x1 <= fw):
            raise InputError(where, "window", f"rows {y0}:{y1}, columns {x0}:{x1} of a {fw}x{fh} film")
        st = cls(x1 - x0, y1 - y0, channels, subpixels=subpixels, features=features, where=where)
        st._window = (y0, x0, fw, fh)
        for fst in st.features.values():
            fst._window = st._window
        return st

    def window_rows_columns(self) -> tuple[int, int, int, int]:
        """``(y0, y1, x0, x1)``: the film's pixels these statistics hold (:meth:`window_of`; the whole film
        otherwise)."""
        y0, x0 = (0, 0) if self._window is None else self._window[:2]
        return y0, y0 + self.height, x0, x0 + self.width

    # ------------------------------------------------------------------ build
    @property
    def shape(self) -> tuple[int, int, int]:
        """(H, W, C) of the images these statistics describe."""
        return self.height, self.width, len(self.channels)

    @property
    def dtype(self) -> np.dtype:
        return np.dtype(np.float64) if self._value_dtype is None else self._value_dtype

    def _note_dtype(self, dtype) -> None:
        dtype = np.dtype(dtype)
        self._value_dtype = dtype if self._value_dtype is None else np.promote_types(self._value_dtype, dtype)

    @property
    def n_samples(self) -> int:
        return int(self.count.sum())

    def keep_features(self, features) -> "PixelStats":
        """Start keeping ``features`` (as the constructor's ``features``); only while no sample is in."""
        if self.n_samples:
            raise InputError("PixelStats.keep_features", "features", "these statistics already hold samples "
                             "without those features; give features= when creating them")
        for name, k in feature_layout(features).items():
            self.features[name] = _feature_stats(self.width, self.height, name, k)
            self.features[name]._window = self._window
        return self

    @property
    def feature_names(self) -> tuple[str, ...]:
        """Names of the features these statistics keep (``()`` when none)."""
        return tuple(self.features)

    def add(self, positions, values, *, features=None, nonfinite: str = "drop",
            source: str = "samples") -> "PixelStats":
        """Add a batch of samples (Welford/Chan updates, in place).

        Parameters
        ----------
        positions : array_like, shape (N, 2)
            Film positions, x the column and y the row.
        values : array_like, shape (N, C)
        features : mapping of str to array_like (N,) or (N, k), optional
            Per-sample features; must hold every feature these statistics
            keep (others are ignored).  Non-finite entries are set to 0
            (counted in ``n_feature_zeroed``, one warning).
        nonfinite : {'drop', 'zero', 'raise'}
            Policy for samples with a NaN or infinite value, see
            :data:`NONFINITE_POLICIES`.
        source : str
            Named in error messages (a file path, a renderer).

        Raises
        ------
        InputError
            Mis-shaped arrays, positions off the film or non-finite, or a
            non-finite value under ``nonfinite='raise'``.  The statistics
            are unchanged when it raises.
        """
        prepared = self._prepare(positions, values, nonfinite=nonfinite, source=source, features=features)
        if prepared is not None:
            self._ingest(*prepared, nonfinite=nonfinite, source=source)
        return self

    def _prepare(self, positions, values, *, nonfinite: str, source: str, features=None):
        """Validate a batch and apply the non-finite policy; touches no statistics.

        Returns ``(positions, values, n_nonfinite, features, n_feature_zeroed)``
        ready for :meth:`_ingest`, or None for an empty batch.  Split from the
        accumulation so a reader can validate the next batch while the
        previous one is accumulated.
        """
        check_policy(nonfinite, source)
        if values is None and self._window is not None:   # a reader's batch with no sample in the window
            return None
        fw, fh = (self.width, self.height) if self._window is None else self._window[2:]
        pos, val, n_nonfinite = check_samples(positions, values, width=fw, height=fh,
                                              n_channels=len(self.channels), where=source, channels=self.channels)
        if self._window is not None and not touches_window(pos, self.window_rows_columns()):
            # no sample of the window: nothing to add (its features need not even be read), the policy still said
            if n_nonfinite:
                apply_nonfinite(pos, val, n_nonfinite, nonfinite, where=source)   # raises under 'raise'
            return (pos[:0], val[:0], n_nonfinite,
                    {name: np.zeros((0, fst.mean.shape[2])) for name, fst in self.features.items()}, 0)
        feats, n_fz = {}, 0
        if self.features:
            feats, n_fz = check_features(features, pos.shape[0], where=source, layout=layout_of(self.features))
        if pos.shape[0] == 0:
            return None
        if n_nonfinite and nonfinite == "drop" and feats:
            keep = np.isfinite(val).all(axis=1)
            feats = {name: arr[keep] for name, arr in feats.items()}
        pos, val = apply_nonfinite(pos, val, n_nonfinite, nonfinite, where=source)
        return pos, val, n_nonfinite, feats, n_fz

    def _ingest(self, pos, val, n_nonfinite, feats=None, n_feature_zeroed=0, *, nonfinite: str,
                source: str) -> None:
        """Accumulate a batch prepared by :meth:`_prepare` (releases the GIL)."""
        s = self.subpixels
        sub_sum = self.sub_sum if s else np.zeros((1, 1, 1))
        sub_count = self.sub_count if s else np.zeros((1, 1), np.int64)
        ranged = self.min is not None
        oy, ox = (0, 0) if self._window is None else self._window[:2]
        _accumulate(*one_float_dtype(pos, val), s, self.count, self.mean, self.m2, self.min if ranged else NO_RANGE,
                    self.max if ranged else NO_RANGE, ranged, sub_sum, sub_count, oy, ox)
        self._note_dtype(val.dtype)
        if feats:
            no_sub, no_sub_count = np.zeros((1, 1, 1)), np.zeros((1, 1), np.int64)
            for name, fst in self.features.items():
                fp, f = one_float_dtype(pos, feats[name])
                _accumulate(fp, f, 0, fst.count, fst.mean, fst.m2, NO_RANGE, NO_RANGE, False, no_sub, no_sub_count,
                            oy, ox)
                fst._note_dtype(feats[name].dtype)  # as given, not as widened for the kernel
        if n_feature_zeroed:
            self.n_feature_zeroed += int(n_feature_zeroed)
            warn_feature_zeroed(source, n_feature_zeroed, stacklevel=3)
        if n_nonfinite:
            if nonfinite == "drop":
                self.n_dropped += int(n_nonfinite)
            else:
                self.n_zeroed += int(n_nonfinite)
            warn_nonfinite(source, n_nonfinite, nonfinite, stacklevel=3)

    def merge(self, other: "PixelStats") -> "PixelStats":
        """Merge another set of statistics into this one (Chan et al., in place; features too)."""
        self._check_mergeable(other)
        return self._merge_from(self, other)

    def merged(self, other: "PixelStats", *, features_on_read: bool = False) -> "PixelStats":
        """The merge of these statistics and ``other`` (:meth:`merge`) as new statistics; neither changes.

        Bit-identical to ``self.copy().merge(other)``, with each array written
        once instead of copied and then rewritten.  ``features_on_read``: each
        feature is merged when read (:class:`~mcrecon.core.merge.MergedOnRead`,
        which holds both inputs' features), not now.
        """
        self._check_mergeable(other)
        if not (features_on_read and self.features):
            return self._with_arrays(np.empty_like)._merge_from(self, other)
        out = self.without_features().merged(other.without_features())
        out.features = MergedOnRead(self.features, other.features)
        out.n_feature_zeroed = self.n_feature_zeroed + other.n_feature_zeroed
        return out

    def _check_mergeable(self, other: "PixelStats") -> None:
        if (other.width, other.height, other.channels, other.subpixels) != (
                self.width, self.height, self.channels, self.subpixels):
            raise InputError("PixelStats.merge", "other",
                             "size, channels and subpixels must match: "
                             f"{other.width}x{other.height} {other.channels} s={other.subpixels} vs "
                             f"{self.width}x{self.height} {self.channels} s={self.subpixels}")
        if layout_of(self.features) != layout_of(other.features):
            raise InputError("PixelStats.merge", "other", "the features must match: "
                             f"{layout_of(other.features)} vs {layout_of(self.features)}")

    def _merge_from(self, a: "PixelStats", b: "PixelStats") -> "PixelStats":
        """Make these statistics (``a`` itself, or arrays shaped as ``a``'s) the merge of ``a`` and ``b``."""
        from .merge import merge_moments

        self.__dict__.pop("film_fill", None)   # the merge is not the film's statistics the value was of
        if isinstance(self.features, MergedOnRead):  # merged into: each feature held, to be written
            self.features = dict(self.features.items())
        for name, fst in self.features.items():
            fst._merge_from(a.features[name], b.features[name])
        self.n_feature_zeroed = a.n_feature_zeroed + b.n_feature_zeroed
        merge_moments(a, b, self)
        self.has_range = a.has_range and b.has_range
        if b._value_dtype is not None:
            self._note_dtype(b._value_dtype)
        if self.subpixels:
            np.add(a.sub_sum, b.sub_sum, out=self.sub_sum)
            np.add(a.sub_count, b.sub_count, out=self.sub_count)
        self.n_dropped = a.n_dropped + b.n_dropped
        self.n_zeroed = a.n_zeroed + b.n_zeroed
        return self

    def copy(self) -> "PixelStats":
        return self._with_arrays(np.ndarray.copy)

    def _with_arrays(self, make) -> "PixelStats":
        """Statistics with these fields and ``make(array)`` for each array (features too)."""
        out = PixelStats.__new__(PixelStats)
        out.__dict__.update({k: (make(v) if isinstance(v, np.ndarray) else v) for k, v in self.__dict__.items()})
        out.features = {name: fst._with_arrays(make) for name, fst in self.features.items()}
        return out

    def without_features(self) -> "PixelStats":
        """These statistics without their features (a shallow view: the arrays are shared)."""
        out = PixelStats.__new__(PixelStats)
        out.__dict__.update(self.__dict__)
        out.features = {}
        out.n_feature_zeroed = 0
        return out

    def crop(self, y0: int, y1: int, x0: int = 0, x1: int | None = None, *, view: bool = False) -> "PixelStats":
        """The statistics of the pixels [y0:y1, x0:x1] (the subpixel grid with them).

        ``view``: arrays that are views of this object's (rows only, x0 = 0 and
        x1 the width): merging into the crop writes these statistics.
        Otherwise contiguous copies.  The counters of samples the NaN/Inf
        policy dropped or zeroed belong to the whole film: a crop starts at 0.
        """
        x1 = self.width if x1 is None else int(x1)
        y0, y1, x0 = int(y0), int(y1), int(x0)
        if not (0 <= y0 <= y1 <= self.height and 0 <= x0 <= x1 <= self.width):
            raise InputError("PixelStats.crop", "window", f"rows {y0}:{y1}, columns {x0}:{x1} of a "
                             f"{self.width}x{self.height} film")
        if view and (x0, x1) != (0, self.width):
            raise InputError("PixelStats.crop", "view", "views are of whole rows (x0=0, x1=width)")
        take = (lambda a: a) if view else np.ascontiguousarray
        d = dict(self.__dict__)
        for name in ("count", "mean", "m2", "min", "max"):
            if getattr(self, name) is not None:  # a feature's statistics keep no range
                d[name] = take(getattr(self, name)[y0:y1, x0:x1])
        s = self.subpixels
        if s:
            d["sub_sum"] = take(self.sub_sum[y0 * s:y1 * s, x0 * s:x1 * s])
            d["sub_count"] = take(self.sub_count[y0 * s:y1 * s, x0 * s:x1 * s])
        d["width"], d["height"] = x1 - x0, y1 - y0
        d["n_dropped"] = d["n_zeroed"] = d["n_feature_zeroed"] = 0
        d.pop("_window", None)   # a crop is statistics of its own pixels
        d["features"] = {name: fst.crop(y0, y1, x0, x1, view=view) for name, fst in self.features.items()}
        out = PixelStats.__new__(PixelStats)
        out.__dict__.update(d)
        return out

    def to_arrays(self) -> tuple[dict, dict]:
        """``(arrays, fields)``: the numpy arrays and the small fields, which :meth:`from_arrays` joins again
        (to ship statistics as raw array frames, e.g. between Dask workers, instead of one pickle)."""
        arrays = {k: v for k, v in self.__dict__.items() if isinstance(v, np.ndarray)}
        fields = {k: v for k, v in self.__dict__.items() if k not in arrays and k != "features"}
        fields["features"] = {}
        for name, fst in self.features.items():
            f_arrays, f_fields = fst.to_arrays()
            arrays.update({f"features/{name}/{k}": v for k, v in f_arrays.items()})
            fields["features"][name] = f_fields
        return arrays, fields

    @classmethod
    def from_arrays(cls, arrays: dict, fields: dict) -> "PixelStats":
        """Statistics from :meth:`to_arrays` (the arrays are used as they are, not copied)."""
        out = cls.__new__(cls)
        fields = dict(fields)
        feature_fields = fields.pop("features", {}) or {}
        out.__dict__.update(fields)
        out.__dict__.update({k: v for k, v in arrays.items() if not k.startswith("features/")})
        out.features = {}
        for name, f_fields in feature_fields.items():
            prefix = f"features/{name}/"
            out.features[name] = cls.from_arrays(
                {k[len(prefix):]: v for k, v in arrays.items() if k.startswith(prefix)}, f_fields)
        out.__dict__.setdefault("n_feature_zeroed", 0)
        return out

    @classmethod
    def from_moments(cls, mean, variance, count, *, channels: Sequence[str] | None = None,
                     variance_of: str = "samples", features=None, where: str = "from_moments") -> "PixelStats":
        """Statistics from per-pixel images: mean, variance and sample count.

        Most renderers can write these even when they cannot dump samples.

        Parameters
        ----------
        mean : array_like (H, W, C) or (H, W)
            Per-pixel sample mean.
        variance : array_like, same shape as ``mean``
            Per-pixel variance: of the samples (``variance_of='samples'``,
            the unbiased ``m2 / (n - 1)``; pbrt-v4's ``Variance`` channels)
            or of the pixel mean (``variance_of='mean'``, i.e. divided by n).
        count : array_like (H, W) of integers, or an int
            Samples per pixel (0 for an empty pixel: its mean and variance
            are ignored).
        channels : sequence of str, optional
            Default R, G, B for three channels, else C0, C1, ...
        variance_of : {'samples', 'mean'}
        features : mapping of str to (mean, variance), optional
            Per-pixel feature images (e.g. ``{"albedo": (mean, variance)}``,
            each (H, W, k) or (H, W)), with the same ``count`` and
            ``variance_of``; a variance of None means unknown and is taken
            as 0 (noise-free features).

        Returns
        -------
        PixelStats
            With ``has_range`` False: the per-pixel minimum and maximum
            are unknown (NaN), so estimators that need the sample range
            refuse these statistics.

        Raises
        ------
        InputError
            Mismatched shapes, NaN/Inf or negative variances in sampled
            pixels, non-integer or negative counts, a variance in a pixel
            with fewer than two samples that is not 0.

        Examples
        --------
        >>> import numpy as np
        >>> from mcrecon import PixelStats
        >>> mean = np.full((4, 5, 3), 0.5)
        >>> st = PixelStats.from_moments(mean, np.full((4, 5, 3), 0.04), 16)
        >>> st.shape, int(st.count.sum())
        ((4, 5, 3), 320)
        >>> float(st.mean_variance()[0, 0, 0])
        0.0025
        """
        return stats_from_moments(cls, mean, variance, count, channels=channels, variance_of=variance_of,
                                  features=features, where=where)

    @classmethod
    def from_samples(cls, positions, values, *, width: int, height: int,
                     channels: Sequence[str] = ("R", "G", "B"), subpixels: int = 0,
                     nonfinite: str = "drop", features=None) -> "PixelStats":
        """Statistics of one batch of samples held in memory (``features``: name -> (N, k) per-sample array)."""
        layout = {}
        if features is not None:
            from .features import check_features
            n = int(np.shape(positions)[0]) if np.ndim(positions) else 0
            checked, _ = check_features(features, n, where="PixelStats.from_samples")  # one clear error first
            layout = {name: arr.shape[1] for name, arr in checked.items()}
        return cls(width, height, channels, subpixels=subpixels, features=layout).add(
            positions, values, features=features, nonfinite=nonfinite)

    @classmethod
    def from_batches(cls, batches: Iterable, *, width: int, height: int,
                     channels: Sequence[str] = ("R", "G", "B"), subpixels: int = 0,
                     nonfinite: str = "drop", source: str = "samples", features=None,
                     each_batch=None, window=None) -> "PixelStats":
        """Stream (positions, values) batches into new statistics.

        With ``features`` (name -> components), each batch is
        ``(positions, values, {name: array})``.  The next batch is fetched
        while the previous one is accumulated (the accumulation releases the
        GIL), so reading a file and accumulating overlap.  ``each_batch``
        (a callable of positions and values), when given, sees every batch
        as read, NaN and Inf included, in stream order: another per-pixel
        accumulator (:class:`~mcrecon.core.strata.PrefixHalves`) fed by the
        same pass over the samples instead of a second one.  ``window``
        ``(y0, y1, x0, x1)``: the statistics of those pixels only
        (:meth:`window_of`).
        """
        from concurrent.futures import ThreadPoolExecutor

        stats = cls(width, height, channels, subpixels=subpixels, features=features, where=source) \
            if window is None else cls.window_of(width, height, window, channels, subpixels=subpixels,
                                                 features=features, where=source)
        it = iter(batches)
        with ThreadPoolExecutor(max_workers=1) as pool:
            pending = None
            while True:
                # Read and validate the next batch here while the worker accumulates
                # the previous one; wait for it before reading again (rotating
                # buffers get reused).  Validation errors surface before any
                # statistics change for that batch.
                batch = next(it, None)
                if batch is not None and each_batch is not None:
                    each_batch(batch[0], batch[1])
                prepared = None if batch is None else \
                    stats._prepare(batch[0], batch[1], nonfinite=nonfinite, source=source,
                                   features=batch[2] if len(batch) > 2 else None)
                if pending is not None:
                    pending.result()
                if batch is None:
                    break
                if prepared is not None:
                    pending = pool.submit(stats._ingest, *prepared, nonfinite=nonfinite, source=source)
        return stats

    @classmethod
    def from_log(cls, log, *, subpixels: int = 0, nonfinite: str = "drop",
                 rounds=None, chunk_size: int | None = None, features=(), each_batch=None,
                 window=None) -> "PixelStats":
        """Stream an opened sample log (:func:`mcrecon.read_log`, a :class:`~mcrecon.io.SampleLog`) in chunks.

        ``features``: names of the log's per-sample features to accumulate
        too (``"all"`` for every one it has; by default none).
        ``each_batch``, ``window``: as :meth:`from_batches`.
        """
        if isinstance(log, (str, os.PathLike)):
            raise InputError("PixelStats.from_log", "log", f"{os.fspath(log)!r} is a path: open it with "
                             "mcrecon.read_log(path) first (the statistics layer reads no files)")
        names = source_features(log, features)
        if names:
            kw = {} if chunk_size is None else {"chunk_size": chunk_size}
            batches = ((b.positions, b.values, b.features) for b in
                       log.iter_chunks(rounds=rounds, with_round=False, features=names, window=window, **kw))
            return cls.from_batches(batches, width=log.width, height=log.height, channels=log.channels,
                                    subpixels=subpixels, nonfinite=nonfinite, source=str(log.path),
                                    features=source_layout(log, names), each_batch=each_batch, window=window)
        if rounds is None and window is None:
            # Two rotating buffers: one is filled while the other is accumulated.
            from .samples import DEFAULT_READ_ROWS

            rows = min(int(chunk_size or DEFAULT_READ_ROWS), max(log.n_samples, 1))
            bufs = [(np.empty((rows, 2), log.position_dtype), np.empty((rows, len(log.channels)), log.value_dtype))
                    for _ in range(2)]
            batches = log.iter_into(bufs)
        else:
            kw = {} if chunk_size is None else {"chunk_size": chunk_size}
            batches = ((b.positions, b.values) for b in log.iter_chunks(rounds=rounds, with_round=False,
                                                                         window=window, **kw))
        return cls.from_batches(batches, width=log.width, height=log.height, channels=log.channels,
                                subpixels=subpixels, nonfinite=nonfinite, source=str(log.path), each_batch=each_batch,
                                window=window)

    @classmethod
    def from_source(cls, source, *, subpixels: int = 0, nonfinite: str = "drop", features=(),
                    each_batch=None, window=None) -> "PixelStats":
        """Stream any sample source: a sample log (its fast reader) or a
        :class:`~mcrecon.core.samples.SampleSet` (any object with ``width``,
        ``height``, ``channels`` and ``iter_chunks``).  ``features`` as
        :meth:`from_log`, ``each_batch`` and ``window`` as :meth:`from_batches`."""
        if hasattr(source, "iter_into"):  # a SampleLog
            return cls.from_log(source, subpixels=subpixels, nonfinite=nonfinite, features=features,
                                each_batch=each_batch, window=window)
        from .samples import source_name

        names = source_features(source, features)
        if names:
            batches = ((c.positions, c.values, c.features)
                       for c in source.iter_chunks(with_round=False, features=names))
        else:
            batches = ((c.positions, c.values) for c in source.iter_chunks(with_round=False))
        return cls.from_batches(batches, width=source.width, height=source.height, channels=source.channels,
                                subpixels=subpixels, nonfinite=nonfinite, source=source_name(source),
                                features=source_layout(source, names), each_batch=each_batch, window=window)

    # -------------------------------------------------------------- derived
    def sample_variance(self, *, ddof: int = 1, undefined: float = np.nan) -> np.ndarray:
        """Per-pixel sample variance ``m2 / (n - ddof)``, shape (H, W, C).

        Pixels with ``n <= ddof`` have no variance estimate; they get
        ``undefined`` (NaN by default: the caller picks a policy).
        Rounding can leave ``m2`` a hair below 0; it is clamped at 0.
        """
        n = self.count[..., None]
        out = np.full(self.mean.shape, undefined, dtype=np.float64)
        ok = np.broadcast_to(n > ddof, out.shape)
        np.divide(np.maximum(self.m2, 0.0), np.maximum(n - ddof, 1), out=out, where=ok)
        return out

    def mean_variance(self, *, undefined: float = np.nan) -> np.ndarray:
        """Variance of the pixel mean, ``sample_variance / n``, shape (H, W, C)."""
        var = self.sample_variance(undefined=undefined)
        n = np.maximum(self.count[..., None], 1)
        return var / n

    def subpixel_means(self, *, fill: str = "pixel") -> np.ndarray:
        """Subpixel means, shape (H*s, W*s, C).

        Empty subpixels take the mean of their pixel (``fill='pixel'``) or
        NaN (``fill='nan'``); subpixels of empty pixels take 0 or NaN.
        """
        if not self.subpixels:
            raise InputError("PixelStats", "subpixels", "these statistics keep no subpixel data; "
                             "build them with subpixels=4")
        s = self.subpixels
        cnt = self.sub_count[..., None]
        out = np.empty_like(self.sub_sum)
        np.divide(self.sub_sum, np.maximum(cnt, 1), out=out)
        if fill == "pixel":
            pix = np.repeat(np.repeat(self.mean, s, axis=0), s, axis=1)
        elif fill == "nan":
            pix = np.full_like(out, np.nan)
        else:
            raise InputError("PixelStats.subpixel_means", "fill", f"got {fill!r}; valid: pixel, nan")
        return np.where(cnt > 0, out, pix)

    def __repr__(self) -> str:
        return (f"PixelStats({self.width}x{self.height}, channels={','.join(self.channels)}, "
                f"samples={self.n_samples}, subpixels={self.subpixels})")

__dir__ = _public_dir(__name__)
