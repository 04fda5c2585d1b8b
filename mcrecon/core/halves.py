"""Half buffers: two independent halves of every pixel's samples.

:class:`Halves` is the one half-buffer type.  A renderer's dual buffers arrive as a pair of
:class:`~mcrecon.core.stats.PixelStats` (:func:`as_halves`, checked by :func:`check_half_buffers`,
merged by :func:`merge_halves`); a sample source is split in one pass (:func:`split_halves`, by each
pixel's own sample order).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..errors import InputError
from . import merge as _merge
from .stats import PixelStats

import numba

from ..filters.engine import n_threads, parallel_calls
from .features import check_features, layout_of, take_rows, warn_feature_zeroed
from .samples import (apply_nonfinite, check_policy, check_sampler, check_samples, dispatcher, touches_window,
    warn_nonfinite)

#: the arithmetic of a run of samples that PixelStats adds, which a half's runs repeat bit for bit (as numba
#: dispatchers: this module loads numba anyway)
_run_add = dispatcher(_merge._run_add)
_merge_run = dispatcher(_merge._merge_run)

__all__ = ['check_half_buffers', 'merge_halves', 'is_half_buffer_pair', 'split_labels', 'split_halves', 'Halves',
           'as_halves', 'pixel_counts', 'mean_variances']

def is_half_buffer_pair(source) -> bool:
    """Whether ``source`` is meant as a half-buffer pair: :class:`Halves`, a tuple or a list
    (:func:`as_halves` then says what is wrong with one that is not two :class:`PixelStats`)."""
    return isinstance(source, (Halves, tuple, list))


def check_half_buffers(pair, where: str = "halves") -> tuple[PixelStats, PixelStats]:
    """A validated half-buffer pair ``(a, b)``, or a one-line :class:`InputError` naming the field.

    Both must be :class:`PixelStats` of the same size, channels and
    subpixel grid; each pixel's counts may differ between them.  That the
    halves are independent (disjoint samples) cannot be checked: it is
    the caller's promise.
    """
    if not isinstance(pair, (tuple, list)):
        raise InputError(where, "halves", f"got {type(pair).__name__}, expected a pair (stats_a, stats_b) of "
                         "PixelStats of two independent halves of the samples")
    if len(pair) != 2:
        raise InputError(where, "halves", f"got {len(pair)} items, expected a pair (stats_a, stats_b) of "
                         "PixelStats of two independent halves of the samples")
    for i, h in enumerate(pair):
        if not isinstance(h, PixelStats):
            raise InputError(where, f"halves[{i}]", f"got {type(h).__name__}, expected PixelStats "
                             "(e.g. PixelStats.from_moments of one half buffer)")
    a, b = pair
    if (a.height, a.width) != (b.height, b.width):
        raise InputError(where, "shape", f"the halves differ in size: {a.width}x{a.height} vs "
                         f"{b.width}x{b.height} (width x height)")
    if a.channels != b.channels:
        raise InputError(where, "channels", f"the halves differ in channels: {','.join(a.channels)} vs "
                         f"{','.join(b.channels)}")
    if a.subpixels != b.subpixels:
        raise InputError(where, "subpixels", f"the halves differ in subpixel grid: {a.subpixels} vs "
                         f"{b.subpixels}")
    return a, b


def merge_halves(a: PixelStats, b: PixelStats) -> PixelStats:
    """The statistics of all the samples of two halves: their Chan merge (:meth:`PixelStats.merge`).

    Equal, to rounding, to the statistics accumulated from every sample
    (count exactly, mean and ``m2`` to a few ulps).  Neither half changes.
    """
    return a.merged(b)


# ----------------------------------------------------------------------------
# Dual buffers
# ----------------------------------------------------------------------------

@numba.njit(cache=True, nogil=True, inline="always")
def _next_half(p, counter, totals):
    # independent samples (totals empty): the k-th sample of pixel p goes to half (k + salt(p)) & 1; salt
    # from a multiplicative hash of p, so which half gets a pixel's odd sample varies.  A stratified
    # sampler (totals[p]: the pixel's samples in the whole stream): its first ceil(n / 2) to half 0, the
    # rest to half 1 -- prefix blocks, each made of aligned blocks of the pixel's sequence
    k = counter[p]
    counter[p] = k + 1
    if totals.size:
        return 0 if 2 * k < totals[p] else 1
    salt = ((p * 2654435761) >> 16) & 1
    return (k + salt) & 1


@numba.njit(cache=True, nogil=True)
def _labels_kernel(pix, counter, totals, out):
    for i in range(pix.size):
        out[i] = _next_half(pix[i], counter, totals)


# Columns of a run record (:func:`_split_runs`): its first sample, one past its last, its pixel, its
# number of samples, its half, and the stride between its samples (2 where they are every second
# sample of [first, stop): a renderer's pixel-by-pixel order, the halves alternating; else 1, the
# labels then picking the half's samples).
_FIRST, _STOP, _PIXEL, _SIZE, _HALF, _STEP = 0, 1, 2, 3, 4, 5
_RUN_FIELDS = 6
#: The ``totals`` of independent samples: none (the halves alternate).
_NO_TOTALS = np.zeros(0, np.int64)
#: Runs found, then accumulated, at a time: the list of runs stays small (3 MB) and in cache for the
#: colour's and every feature's pass, whatever the batch's size and order.
_RUN_BLOCK = 1 << 16
#: Batches with fewer samples are accumulated on the calling thread (the pool costs more than it saves).
_PARALLEL_MIN_SAMPLES = 1 << 16


@numba.njit(cache=True, nogil=True)
def _split_runs(pos, width, counter, totals, lab, k, open_runs, runs):
    # from sample k on, the half of every sample (into lab) and the runs of each half -- consecutive
    # samples of the half's own sub-stream in one pixel -- into runs, in the order they end, until runs
    # is full; open_runs holds each half's unfinished run between calls, and the batch's end finishes
    # them.  Returns (the next sample, runs written, samples given to half 0)
    n_runs = 0
    n_a = 0
    n = pos.shape[0]
    while k < n and n_runs < runs.shape[0]:  # a sample finishes at most one run
        p = int(pos[k, 1]) * width + int(pos[k, 0])
        h = _next_half(p, counter, totals)
        lab[k] = h
        n_a += 1 - h
        if open_runs[h, _SIZE] > 0 and open_runs[h, _PIXEL] != p:
            n_runs = _end_run(open_runs, h, runs, n_runs)
        if open_runs[h, _SIZE] == 0:
            open_runs[h, _FIRST] = k
            open_runs[h, _PIXEL] = p
            open_runs[h, _HALF] = h
            open_runs[h, _STEP] = 2
        elif k != open_runs[h, _STOP] + 1:
            open_runs[h, _STEP] = 1
        open_runs[h, _SIZE] += 1
        open_runs[h, _STOP] = k + 1
        k += 1
    for h in range(2):
        if k == n and open_runs[h, _SIZE] > 0 and n_runs < runs.shape[0]:
            n_runs = _end_run(open_runs, h, runs, n_runs)
    return k, n_runs, n_a


@numba.njit(cache=True, nogil=True, inline="always")
def _end_run(open_runs, h, runs, n_runs):
    for f in range(_RUN_FIELDS):
        runs[n_runs, f] = open_runs[h, f]
    open_runs[h, _SIZE] = 0
    return n_runs + 1


@numba.njit(cache=True, nogil=True, inline="always")
def _add_run(first, stop, p, m, h, step, lab, val, width, oy, ox, count, mean, m2, vmin, vmax, ranged):
    # the m samples of half h in [first, stop), all in pixel p: a two-pass mean and sum of squared
    # deviations over the run, then one Chan et al. merge (merge._merge_run) -- term for term the
    # arithmetic of mcrecon.core.merge._accumulate on the half's samples in stream order.  The run as a
    # 0-based slice (no negative-index wraparound check in the inner loops) and a stride-2 loop that reads no
    # label: 0.24 s of CPU for the colour of 33 M samples, where one strided loop testing every label
    # takes 0.42 s
    iy = p // width - oy  # the arrays hold the window whose first pixel is (oy, ox)
    ix = p % width - ox
    na = count[iy, ix]
    n = na + m
    count[iy, ix] = n
    wb = m / n
    seg = val[first:stop]
    lseg = lab[first:stop]
    for c in range(val.shape[1]):
        acc = 0.0
        lo = np.inf
        hi = -np.inf
        if step == 2:
            for t in range(m):
                acc, lo, hi = _run_add(acc, lo, hi, float(seg[2 * t, c]))
        else:
            for j in range(stop - first):
                if lseg[j] == h:
                    acc, lo, hi = _run_add(acc, lo, hi, float(seg[j, c]))
        mu = acc / m
        q = 0.0
        if step == 2:
            for t in range(m):
                d = float(seg[2 * t, c]) - mu
                q += d * d
        else:
            for j in range(stop - first):
                if lseg[j] == h:
                    d = float(seg[j, c]) - mu
                    q += d * d
        _merge_run(mean, m2, vmin, vmax, iy, ix, c, na, wb, mu, q, lo, hi, ranged)


@numba.njit(cache=True, nogil=True)
def _add_runs(runs, n_runs, lab, val, p_lo, p_hi, width, oy, ox, ca, mean_a, m2_a, min_a, max_a, cb, mean_b, m2_b,
              min_b, max_b, ranged):
    # the runs of pixels in [p_lo, p_hi) of the window (oy, ox, ca's shape), in order, each into its half's
    # statistics
    wx = ca.shape[1]
    for r in range(n_runs):
        p = runs[r, _PIXEL]
        if p < p_lo or p >= p_hi:
            continue
        if not (0 <= p % width - ox < wx):
            continue
        h = runs[r, _HALF]
        count, mean, m2, vmin, vmax = (ca, mean_a, m2_a, min_a, max_a) if h == 0 else \
            (cb, mean_b, m2_b, min_b, max_b)
        _add_run(runs[r, _FIRST], runs[r, _STOP], p, runs[r, _SIZE], h, runs[r, _STEP], lab, val, width, oy, ox,
                 count, mean, m2, vmin, vmax, ranged)


def _split_accumulate(runs, n_runs, lab, val, width, n_parts, a: PixelStats, b: PixelStats) -> None:
    """Add the samples of ``val`` that the first ``n_runs`` of ``runs`` hold (:func:`_split_runs`) to
    their half's statistics ``a`` or ``b``.

    Each run is merged as one (:func:`_add_run`).  ``n_parts`` ranges of
    pixels are merged in parallel (the filters' thread pool: a
    ``parallel=True`` kernel cost 1.9 s of compilation on a first run),
    each by one thread going through the whole list of runs (the result
    does not depend on ``n_parts``).  Values must be finite.  The range is
    kept where the halves keep one (the colour's; a feature's keeps none).
    ``width`` is the film's; the halves may hold a window of it
    (:meth:`PixelStats.window_of`): the runs of other pixels are skipped.
    """
    oy, ox = (0, 0) if a._window is None else a._window[:2]
    rows = a.height
    ranged = a.min is not None and b.min is not None
    lo_a, hi_a, lo_b, hi_b = (a.min, a.max, b.min, b.max) if ranged else (_merge.NO_RANGE,) * 4
    # each part: whole rows of the window, as film pixel indices
    parts = [((oy + rows * part // n_parts) * width, (oy + rows * (part + 1) // n_parts) * width)
             for part in range(n_parts)]
    parallel_calls(_add_runs, [(runs, n_runs, lab, val, p_lo, p_hi, width, oy, ox, a.count, a.mean, a.m2, lo_a, hi_a,
                                b.count, b.mean, b.m2, lo_b, hi_b, ranged)
                               for p_lo, p_hi in parts], threads=n_parts)


def split_labels(positions: np.ndarray, width: int, height: int, counter: np.ndarray, *,
                 totals: np.ndarray | None = None) -> np.ndarray:
    """Half (0 or 1) of each sample, by (pixel, index within pixel).

    Without ``totals`` (independent samples) the halves alternate within
    each pixel.  With ``totals`` (H*W int64: each pixel's samples in the
    whole stream, :func:`pixel_counts`; a stratified sampler's) a pixel's
    first ``ceil(n / 2)`` samples go to half 0 and the rest to half 1:
    prefix blocks, whose means differ by the net's error and not by the
    integrand's left-right difference, as alternate samples of a Sobol
    sequence do (:mod:`mcrecon.core.strata`).

    ``counter`` (H*W int64, updated in place) holds how many samples each
    pixel has had so far, so a stream split chunk by chunk or round by
    round gets the same labels as the whole stream.  Every pixel's halves
    differ by at most one sample.  Positions outside the film are counted
    in the nearest border pixel (they are dropped later by the statistics).
    """
    pos = np.asarray(positions)
    if pos.shape[0] == 0:
        return np.zeros(0, np.int8)
    out = np.empty(pos.shape[0], np.int8)
    _labels_kernel(_pixels(pos, width, height), counter, _NO_TOTALS if totals is None else totals, out)
    return out


def _pixels(positions, width: int, height: int) -> np.ndarray:
    """Each position's pixel index (row-major), a position off the film in the nearest border pixel."""
    pos = np.asarray(positions)
    ix = np.clip(np.floor(np.nan_to_num(pos[:, 0], nan=0.0)), 0, width - 1).astype(np.int64)
    iy = np.clip(np.floor(np.nan_to_num(pos[:, 1], nan=0.0)), 0, height - 1).astype(np.int64)
    return iy * width + ix


@dataclasses.dataclass(eq=False)
class Halves:
    """Two independent half buffers: statistics of disjoint halves of every pixel's samples.

    The one half-buffer type every method reads (``MethodInputs.halves``).
    It comes from one of three places, each building it once: the offline
    dispatcher splits a sample source in one pass (:func:`split_halves`,
    ``source`` then names that source), a caller's pair of
    :class:`PixelStats` (two buffers a renderer wrote) is taken as it is
    (:func:`as_halves`), and an adaptive run adds each committed round
    (:meth:`add`).  It unpacks as the pair ``a, b = halves``.

    Attributes
    ----------
    a, b : PixelStats
        Same size, channels, subpixel grid and features; each pixel's counts
        may differ by the samples of a pixel that one half got more of.
    counter : ndarray (H*W,) int64
        Samples each pixel has had so far: the labels of the next batch
        :meth:`add` splits continue from it.
    source : sample source or None
        The samples the halves were split from (:func:`split_halves`);
        None for a pair given as statistics and for an adaptive run's.
    totals : ndarray (H*W,) int64 or None
        Each pixel's samples in the whole stream, where the halves are prefix
        blocks (:func:`split_labels`); None where they alternate.
    sampler : str
        The samples' sampler (:data:`~mcrecon.core.requests.SAMPLERS`):
        ``sobol`` halves are prefix blocks and :func:`mean_variances` reads
        the variance of a pixel mean from their difference.
    transient : bool
        Made for one reconstruction alone (the offline dispatcher's split of
        a source): the method may let go of what it has read for the last
        time (:meth:`release_features`).  False for a caller's pair and an
        adaptive run's halves, which live on.
    """

    a: PixelStats
    b: PixelStats
    counter: np.ndarray
    source: object = None
    totals: np.ndarray | None = None
    sampler: str = "independent"
    transient: bool = False

    def __iter__(self):
        return iter((self.a, self.b))

    def __len__(self) -> int:
        return 2

    def __getitem__(self, i):
        return (self.a, self.b)[i]

    @property
    def shape(self) -> tuple[int, int, int]:
        return self.a.shape

    @property
    def n_samples(self) -> int:
        return int(self.a.count.sum()) + int(self.b.count.sum())

    def merged(self) -> PixelStats:
        """The statistics of all the samples of both halves (:func:`merge_halves`)."""
        return merge_halves(self.a, self.b)

    def without_features(self) -> "Halves":
        """The same halves without per-pixel features (for a method that reads none)."""
        if not self.a.features and not self.b.features:
            return self
        return dataclasses.replace(self, a=self.a.without_features(), b=self.b.without_features())

    def release_features(self, *, keep=(), merged: PixelStats | None = None, merged_keep=()) -> bool:
        """Drop both halves' feature statistics but those named in ``keep``, in place, where the halves are
        :attr:`transient`; returns whether they were dropped.

        For a method past the last reader of those features: at 1920 x 1080 each half holds a mean,
        a second moment and a count per feature (0.56 GB for both with albedo, normal and depth), all
        of it otherwise alive beside the method's later arrays, since the caller holds the halves.
        ``merged``: the dispatcher's merge of these halves (:meth:`merged` or ``features_on_read``),
        whose features are dropped alike (read on demand, they would look for the halves' ones).
        ``merged_keep``: features whose merge is still read but no half's (auto's albedo divisor, after
        its last half-buffer candidate): ``merged`` keeps them, merged now where it merges on read
        (the same bits as a later read), and the halves drop theirs: one set of statistics held, not two.
        """
        if not self.transient:
            return False
        keep = set(keep)
        kept_merge = set(merged_keep) - keep if merged is not None else set()
        for name in kept_merge:
            if name in merged.features and isinstance(merged.features, _merge.MergedOnRead):
                merged.features[name] = merged.features[name]  # the merge, stored: read no longer from the halves
        for st in (self.a, self.b) + ((merged,) if merged is not None else ()):
            held = keep | kept_merge if st is merged else keep
            for name in [n for n in st.features if n not in held]:
                del st.features[name]
        return True

    def sample_sets(self):
        """The samples of each half as two :class:`~mcrecon.core.samples.SampleSet` (rounds dropped).

        Labelled as :func:`split_halves` labels them (:func:`split_labels`
        in stream order), so each set holds exactly the samples its half's
        statistics were built from; values are kept as they are (NaN/Inf
        too: a method reading the sets applies its policy).  Only for halves
        split from a sample source (``source``); the samples are held in
        memory.
        """
        from .samples import SampleSet

        src = self.source
        if src is None:
            raise InputError("halves", "source", "these halves were not split from samples (a pair of "
                             "statistics holds no individual samples); give the samples themselves")
        w, h = src.width, src.height
        counter = np.zeros(w * h, np.int64)
        parts = ([], []), ([], [])
        for ch in src.iter_chunks(with_round=False):
            pos, val = np.asarray(ch.positions), np.asarray(ch.values)
            lab = split_labels(pos, w, h, counter, totals=self.totals)
            for half in (0, 1):
                sel = lab == half
                parts[half][0].append(pos[sel])
                parts[half][1].append(val[sel])
        out = []
        for half in (0, 1):
            pos = np.concatenate(parts[half][0]) if parts[half][0] else np.zeros((0, 2))
            val = np.concatenate(parts[half][1]) if parts[half][1] else np.zeros((0, len(src.channels)))
            out.append(SampleSet(pos, val, width=w, height=h, channels=tuple(src.channels)))
        return out[0], out[1]

    @classmethod
    def from_pair(cls, a: PixelStats, b: PixelStats, *, sampler: str = "independent") -> "Halves":
        """Halves of two validated :class:`PixelStats` (:func:`check_half_buffers`), taken as they are
        (``sampler``: as the attribute; a crop of prefix-block halves keeps ``sobol``)."""
        return cls(a, b, (a.count + b.count).ravel().astype(np.int64), sampler=sampler)

    def add(self, positions, values, *, features=None, nonfinite: str = "drop", source: str = "samples",
            _checked: bool = False) -> None:
        """Split a batch (in stream order) and add each half to its statistics.

        One compiled pass labels every sample and finds each half's runs
        (:func:`_split_runs`); the colour and each feature (those both
        halves keep, :class:`PixelStats` ``features``) are then accumulated
        from those runs into their half, without copying the halves out
        (:func:`_split_accumulate`).  The arithmetic is that of
        :meth:`PixelStats.add` on each half's samples in stream order, so the
        statistics are bit-identical to splitting first and adding each half
        (``tests/test_error_estimates.py``).  Batches with non-finite values
        take that reference path (:meth:`_add_by_copies`), which applies the
        ``nonfinite`` policy.
        """
        a, b = self.a, self.b
        fw, fh = self._film()
        if values is None and a._window is not None:   # a reader's batch with no sample in the window
            self._count_turns(np.asarray(positions))
            return
        if _checked:  # a SampleSet's arrays, validated when it was built, all values finite
            pos, val, n_nonfinite = positions, values, 0
            feats, n_fz = ({name: features[name] for name in a.features}, 0) if a.features else ({}, 0)
        else:
            pos, val, n_nonfinite = check_samples(positions, values, width=fw, height=fh,
                                                  n_channels=len(a.channels), where=source, channels=a.channels)
            if a._window is not None and not touches_window(pos, a.window_rows_columns()):
                # halves of a window, no sample of it in the batch: only each pixel's turns are counted (the labels
                # of the window's pixels and of those whose samples end its runs in later batches; a run ends with
                # its batch), and the policy said, as the reference path says it
                check_policy(nonfinite, source)
                if n_nonfinite:
                    apply_nonfinite(pos, val, n_nonfinite, nonfinite, where=source)   # raises under 'raise'
                    warn_nonfinite(source, n_nonfinite, nonfinite, stacklevel=2)
                self._count_turns(pos)
                return
            feats, n_fz = check_features(features, pos.shape[0], where=source, layout=layout_of(a.features)) \
                if a.features else ({}, 0)
        if pos.shape[0] == 0:
            return
        check_policy(nonfinite, source)
        if n_fz:
            warn_feature_zeroed(source, n_fz, stacklevel=2)
        if n_nonfinite:
            self._add_by_copies(pos, val, nonfinite=nonfinite, source=source, n_nonfinite=n_nonfinite,
                                features=feats)
            return
        n = pos.shape[0]
        n_parts = n_threads() if n >= _PARALLEL_MIN_SAMPLES else 1
        # the colour and every feature are accumulated from the same runs: finding them once, instead
        # of each thread following every sample once per feature, took the split of 33 M samples with
        # three features from 3.2 to 1.7 s of CPU
        lab = np.empty(n, np.int8)
        runs = np.empty((min(n, _RUN_BLOCK), _RUN_FIELDS), np.int64)
        open_runs = np.zeros((2, _RUN_FIELDS), np.int64)
        k = n_a = 0
        while k < n or open_runs[:, _SIZE].any():
            k, n_runs, n_a_block = _split_runs(pos, fw, self.counter, _NO_TOTALS if self.totals is None else
                                               self.totals, lab, k, open_runs, runs)
            n_a += n_a_block
            _split_accumulate(runs, n_runs, lab, val, fw, n_parts, a, b)
            for name, f in feats.items():
                _split_accumulate(runs, n_runs, lab, f, fw, n_parts, a.features[name], b.features[name])
        for name, f in feats.items():
            a.features[name]._note_dtype(f.dtype)
            b.features[name]._note_dtype(f.dtype)
        if n_a:
            a._note_dtype(val.dtype)
        if n_a < pos.shape[0]:
            b._note_dtype(val.dtype)

    def _add_by_copies(self, positions, values, *, nonfinite: str = "drop", source: str = "samples",
                       n_nonfinite: int = 0, features=None) -> None:
        """The reference path of :meth:`add`: labels, then each half's samples into its statistics.

        Non-finite values (``n_nonfinite`` of them) get the policy on the
        whole batch, as :class:`PixelStats` applies it: ``raise`` refuses
        the batch untouched, ``drop``/``zero`` warn once with its count.
        Labels are given before the policy, so a dropped sample still
        takes its turn in its pixel (the halves of a stream do not depend
        on which of its samples were bad).
        """
        pos = np.asarray(positions)
        val = np.asarray(values)
        if val.ndim == 1:
            val = val[:, None]
        if n_nonfinite and nonfinite == "raise":
            apply_nonfinite(pos, val, n_nonfinite, nonfinite, where=source)  # raises, nothing changed
        lab = split_labels(pos, *self._film(), self.counter, totals=self.totals)
        if n_nonfinite:
            bad = ~np.isfinite(val).all(axis=1)
            for half, st in ((0, self.a), (1, self.b)):
                k = int(np.count_nonzero(bad & (lab == half)))
                if nonfinite == "drop":
                    st.n_dropped += k
                else:
                    st.n_zeroed += k
            # the policy applied to the row numbers alongside the values (as the grouping does)
            rows, val = apply_nonfinite(np.arange(pos.shape[0]), val, n_nonfinite, nonfinite, where=source)
            pos, lab = pos[rows], lab[rows]
            features = take_rows(features or {}, rows)
            warn_nonfinite(source, n_nonfinite, nonfinite, stacklevel=4)
        for half, st in ((0, self.a), (1, self.b)):
            sel = lab == half
            if sel.any():
                st.add(pos[sel], val[sel], features=take_rows(features or {}, sel), nonfinite=nonfinite,
                       source=source)

    def _count_turns(self, pos: np.ndarray) -> None:
        """Count each pixel's turns in a batch none of whose samples is added (halves of a window): the labels
        of later batches follow from them, as :func:`split_labels` counts them."""
        if pos.shape[0]:
            fw, fh = self._film()
            self.counter += np.bincount(_pixels(pos, fw, fh), minlength=fw * fh)

    def _film(self) -> tuple[int, int]:
        """``(width, height)`` of the film the batches :meth:`add` splits are of (the halves may hold a window)."""
        w = self.a._window
        return (self.a.width, self.a.height) if w is None else (w[2], w[3])

    @classmethod
    def empty(cls, width: int, height: int, channels, *, features=None, window=None) -> "Halves":
        """Empty halves of a ``width`` x ``height`` film, keeping ``features`` (as :class:`PixelStats`).

        ``window`` ``(y0, y1, x0, x1)``: halves of those pixels only (:meth:`PixelStats.window_of`), to
        which the film's batches are added: each pixel's labels and runs are the film's (``counter``
        counts every pixel of the film), so the halves are the film's cropped to the window, bit for bit.
        """
        def half():
            return PixelStats(width, height, channels, features=features) if window is None else \
                PixelStats.window_of(width, height, window, channels, features=features)
        return cls(half(), half(), np.zeros(int(width) * int(height), np.int64))


def as_halves(pair, where: str = "halves") -> Halves:
    """A caller's half-buffer pair as :class:`Halves`: the one conversion at the public boundary.

    ``pair`` is :class:`Halves` (returned as it is) or a tuple or list
    ``(stats_a, stats_b)``, validated by :func:`check_half_buffers` (a
    one-line :class:`InputError` naming ``where`` and the field).
    """
    if isinstance(pair, Halves):
        return pair
    return Halves.from_pair(*check_half_buffers(pair, where))


def pixel_counts(source, *, chunk_size: int = 1 << 20) -> np.ndarray:
    """(H*W,) int64: each pixel's samples in a sample source (a log or SampleSet), non-finite ones included.

    The counting pass the prefix-block halves of a stratified sampler need
    before their split (:func:`split_labels`): one streamed read of the
    positions (a log's values come with them), one ``bincount`` a chunk.
    Positions off the film count in the nearest border pixel, as
    :func:`split_labels` counts them.
    """
    w, h = int(source.width), int(source.height)
    out = np.zeros(w * h, np.int64)
    for ch in source.iter_chunks(chunk_size=chunk_size, with_round=False):
        if len(ch.positions):
            out += np.bincount(_pixels(ch.positions, w, h), minlength=w * h)
    return out


def split_halves(source, *, nonfinite: str = "drop", features=(), each_batch=None, window=None) -> Halves:
    """Two independent halves of a sample source (log or SampleSet), rounds in order.

    A source whose ``sampler`` is ``sobol`` (a log's attribute, a
    :class:`~mcrecon.core.samples.SampleSet`'s keyword) is split by prefix
    blocks after a counting pass (:func:`pixel_counts`, :func:`split_labels`);
    independent samples alternate.

    ``features``: the source's per-sample features to split with the
    samples (names, or ``"all"``; :meth:`PixelStats.from_log`).
    ``each_batch``: a callable given every batch's positions and values as
    read, in stream order (:meth:`PixelStats.from_batches`).
    ``window`` ``(y0, y1, x0, x1)``: the halves of those pixels only, the
    film's cropped to them bit for bit (:meth:`Halves.empty`).
    Messages name the source (its file), as the statistics' reader does.
    """
    from .samples import SampleSet, source_name
    from .features import source_features, source_layout
    name = source_name(source)
    names = source_features(source, features)
    h = Halves.empty(source.width, source.height, tuple(source.channels), features=source_layout(source, names),
                     window=window)
    h.sampler = check_sampler(getattr(source, "sampler", None), where=name)
    if h.sampler != "independent":
        h.totals = pixel_counts(source)
    # a SampleSet validated its arrays when it was built (contiguous, on the film); if
    # none of its values is NaN/Inf the policy has nothing to do: skip the re-check
    checked = isinstance(source, SampleSet) and source.n_nonfinite == 0
    # a log reads the features of the window's chunks only
    kw = {"window": window} if window is not None and hasattr(source, "iter_into") else {}
    chunks = source.iter_chunks(with_round=False, features=names, **kw) if names else \
        source.iter_chunks(with_round=False)
    for ch in chunks:
        if each_batch is not None:
            each_batch(ch.positions, ch.values)
        h.add(ch.positions, ch.values, features=ch.features if names else None, nonfinite=nonfinite, source=name,
              _checked=checked)
    h.source = source
    return h


def mean_variances(stats: PixelStats, halves: Halves | None, *,
                   pooled: bool = False) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """``(v, v_a, v_b)``: the variance of each pixel mean of ``stats`` and of each half's mean (H, W, C).

    Independent samples (or no halves): ``s^2 / n`` of each
    (:func:`~mcrecon.core.fill.mean_variance_policy`).  Prefix-block halves
    of a stratified sampler (``halves.sampler`` ``sobol``): ``s^2 / n``
    counts the integrand's spread over the pixel, which the net cancels,
    so the variances come from the halves' difference ``d = m_A - m_B``:
    ``v = d^2 n_A n_B / n^2``, ``v_A = d^2 n_B / n``, ``v_B = d^2 n_A / n``
    (for independent samples ``E[d^2] = sigma^2 n / (n_A n_B)``, so each is
    unbiased; for a net each errs high, by the gain from a half's samples
    to all of them, never low).  Linear in ``d^2``, so SURE and the
    cross-validated estimates built on them stay unbiased.  A pixel
    without a sample in each half keeps ``s^2 / n``.

    ``pooled``: instead ``g s^2 / n`` of each, ``g`` the stratification gain
    of the pixel's 5 x 5 neighbourhood (:func:`~mcrecon.core.strata.halves_gain`,
    the upper bound of the halves' pooled ratio to ``s^2 / n``, in
    ``[1/32, 1]``): smooth and many-degree like ``s^2 / n`` (what a
    confidence interval or a median of neighbours wants), but not linear in
    the halves' difference.
    """
    from .fill import mean_variance_policy

    v = mean_variance_policy(stats)
    if halves is None:
        return v, None, None
    a, b = halves
    va, vb = mean_variance_policy(a), mean_variance_policy(b)
    if halves.sampler == "independent":
        return v, va, vb
    if pooled:
        from .strata import halves_gain

        g = halves_gain(a.mean, b.mean, a.count, b.count, stats.sample_variance(undefined=0.0))[..., None]
        return v * g, va * g, vb * g
    na, nb = a.count.astype(np.float64), b.count.astype(np.float64)
    n = na + nb
    ok = ((na > 0) & (nb > 0))[..., None]
    d2 = (a.mean - b.mean) ** 2
    inv = np.divide(1.0, n, out=np.zeros_like(n), where=n > 0)[..., None]
    v = np.where(ok, d2 * (na * nb)[..., None] * inv * inv, v)
    va = np.where(ok, d2 * nb[..., None] * inv, va)
    vb = np.where(ok, d2 * na[..., None] * inv, vb)
    return v, va, vb
