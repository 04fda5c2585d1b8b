"""Samples: the one validation path and NaN/Inf policy, and sample sources.

Every boundary that takes samples (the sample-log writer and reader, the
pixel statistics, the adaptive driver, the methods) checks them here, with
the same rules and the same messages:

* positions (N, 2) of a real dtype, every one finite and on the film
  ``[0, W) x [0, H)`` (x the column, y the row);
* values (N, C) of a real dtype, C the number of channels;
* non-finite values follow one policy, :data:`NONFINITE_POLICIES`.

A *sample source* is what a method that filters individual samples
(``requires.samples``) reads offline: anything with ``width``, ``height``,
``channels``, ``round_slices()`` and ``iter_chunks(rounds=..., with_round=...)``
yielding chunks with ``positions`` and ``values``.  A sample log
(:class:`mcrecon.io.SampleLog`) is one; :class:`SampleSet` holds samples
in memory.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
import threading
import warnings
from typing import Iterator, Sequence

import numpy as np

from .._lazy import public_dir as _public_dir
from ..errors import InputError, McreconWarning
# source_name lives with the features, which name sources in their messages too; its users import it from here
from .features import check_features, source_name, warn_feature_zeroed  # noqa: F401

#: The public surface; the other names here (round helpers, the float32 spread
#: check, pixel_index, source_name) serve the readers, the driver and the renderers.
__all__ = ["NONFINITE_POLICIES", "check_policy", "check_samples", "apply_nonfinite", "SampleSet", "SampleChunk",
           "SAMPLERS", "check_sampler"]

#: What happens to samples whose value is NaN or +-Inf:
#: ``drop`` skips the whole sample and counts it (default, with a warning),
#: ``zero`` replaces the non-finite channel values by 0 and keeps the sample
#: (biased low, but keeps the sample count a renderer promised),
#: ``raise`` refuses the batch.
NONFINITE_POLICIES = ("drop", "zero", "raise")


def check_policy(policy: str, where: str = "samples") -> str:
    """The non-finite policy, or an :class:`InputError` listing the valid ones."""
    if policy not in NONFINITE_POLICIES:
        raise InputError(where, "nonfinite", f"unknown policy {policy!r}; valid: {', '.join(NONFINITE_POLICIES)}")
    return policy


# ---------------------------------------------------------------- numba, on first use
_LAZY_KERNEL_LOCK = threading.Lock()


class _LazyKernel:
    """A function that becomes ``numba.njit(**options)(func)`` at its first call.

    numba itself (a third of a second to import) is imported then, not
    when the module defining the kernel is: ``mcrecon info`` and
    ``mcrecon --help`` never load it.  The compiled dispatcher replaces
    the kernel in its module's namespace, so later calls through the
    module go straight to it; numba's on-disk cache (``cache=True``) is
    keyed by the function's file and name, exactly as with a decorator.
    A lazy kernel may call other lazy kernels by their global names:
    :meth:`compile` makes their dispatchers first.  Other numba code
    calls a lazy kernel through its :func:`dispatcher`.
    """

    def __init__(self, func, options):
        functools.update_wrapper(self, func)
        self._options = options
        self._dispatcher = None

    def __call__(self, *args):
        d = self._dispatcher
        if d is None:
            d = self.compile()
        return d(*args)

    def compile(self):
        """The numba dispatcher (made once; it compiles, or loads from the cache, per signature).

        The lazy kernels the function names as globals become their dispatchers in its namespace first,
        so that numba, compiling it, finds callees it can type.
        """
        func = self.__wrapped__
        for name in func.__code__.co_names:
            callee = func.__globals__.get(name)
            if isinstance(callee, _LazyKernel) and callee is not self:
                func.__globals__[name] = callee.compile()
        with _LAZY_KERNEL_LOCK:  # threads calling a kernel for the first time make one dispatcher
            if self._dispatcher is None:
                import numba

                func = self.__wrapped__
                dispatcher = numba.njit(**self._options)(func)
                if func.__globals__.get(func.__name__) is self:
                    func.__globals__[func.__name__] = dispatcher
                self._dispatcher = dispatcher
        return self._dispatcher

    def __repr__(self) -> str:
        return f"<lazy numba kernel {self.__module__}.{self.__qualname__}>"


def dispatcher(kernel):
    """The numba dispatcher of a lazy kernel (made now, numba imported) or of one whose module already holds
    it: what other numba code calls."""
    return kernel.compile() if isinstance(kernel, _LazyKernel) else kernel


def lazy_njit(func=None, **options):
    """A numba ``njit(**options)`` decorator that imports numba and makes the dispatcher at the first call.

    ``@lazy_njit(cache=True, nogil=True)``; another lazy kernel calls it
    by name, other numba code through its :func:`dispatcher`.
    """
    if func is None:
        return lambda f: _LazyKernel(f, options)
    return _LazyKernel(func, options)


# ---------------------------------------------------------------- screening
@lazy_njit(cache=True, nogil=True)
def _quick_check_bits(pos_bits, val_bits, width_bits, height_bits, val_exp_mask):
    """Branch-free screening on the floats' bit patterns (integer reductions vectorise).

    For non-negative IEEE floats the integer view is ordered like the value,
    so ``0 <= x < width`` is ``0 <= bits(x) < bits(width)``; NaN and
    negative numbers fail it.  A value is non-finite iff its exponent bits
    are all ones.  False alarms (e.g. -0.0) only send the batch through the
    exact :func:`_scan`.
    """
    if pos_bits.shape[0] == 0:
        return True, True
    hi_x = pos_bits[0, 0]
    hi_y = pos_bits[0, 1]
    lo = min(hi_x, hi_y)
    for k in range(pos_bits.shape[0]):
        a = pos_bits[k, 0]
        b = pos_bits[k, 1]
        lo = min(lo, min(a, b))
        hi_x = max(hi_x, a)
        hi_y = max(hi_y, b)
    e = val_exp_mask & 0
    for k in range(val_bits.shape[0]):
        for c in range(val_bits.shape[1]):
            e = max(e, val_bits[k, c] & val_exp_mask)
    pos_ok = lo >= 0 and hi_x < width_bits and hi_y < height_bits
    return pos_ok, e != val_exp_mask


@lazy_njit(cache=True, nogil=True)
def _flat_bits_range(bits, exp_mask):
    """(min, max, max of bits & exp_mask) of a flat integer view: contiguous
    reductions that vectorise (3x faster than the two-column loop)."""
    lo = bits[0]
    hi = bits[0]
    e = exp_mask & 0
    for i in range(bits.shape[0]):
        a = bits[i]
        lo = min(lo, a)
        hi = max(hi, a)
        e = max(e, a & exp_mask)
    return lo, hi, e


_INT_VIEW = {np.dtype(np.float32): (np.int32, np.int32(0x7F800000)),
             np.dtype(np.float64): (np.int64, np.int64(0x7FF0000000000000))}


def _quick_check(pos, val, width, height):
    """(all positions on the film, all values finite), screened on bit patterns."""
    if pos.dtype not in _INT_VIEW or val.dtype not in _INT_VIEW or pos.shape[0] == 0:
        return False, False  # let the exact scan decide
    pint, _ = _INT_VIEW[pos.dtype]
    vint, vmask = _INT_VIEW[val.dtype]
    wb = np.array(width, pos.dtype).view(pint)[()]
    hb = np.array(height, pos.dtype).view(pint)[()]
    plo, phi, _ = _flat_bits_range(pos.view(pint).reshape(-1), pint(0))
    _, _, ve = _flat_bits_range(val.view(vint).reshape(-1), vmask)
    val_ok = bool(ve != vmask)
    if plo >= 0 and phi < min(wb, hb):
        return True, val_ok  # every coordinate below both sides: on the film
    # inconclusive on non-square films (or truly bad): the exact per-axis screen
    pos_ok, val_ok = _quick_check_bits(pos.view(pint), val.view(vint), wb, hb, vmask)
    return bool(pos_ok), bool(val_ok)


@lazy_njit(cache=True, nogil=True)
def _scan(pos, val, width, height):
    """Count bad positions (non-finite or off the film) and non-finite value rows."""
    n_bad_pos = 0
    n_nonfinite = 0
    first_bad_pos = -1
    for k in range(pos.shape[0]):
        x = pos[k, 0]
        y = pos[k, 1]
        if not (x >= 0.0 and x < width and y >= 0.0 and y < height):
            n_bad_pos += 1
            if first_bad_pos < 0:
                first_bad_pos = k
        for c in range(val.shape[1]):
            if not math.isfinite(val[k, c]):
                n_nonfinite += 1
                break
    return n_bad_pos, first_bad_pos, n_nonfinite


#: Batches of fewer samples are screened with NumPy (a few ms at most), larger ones by the kernels
#: above: a small log is checked (``mcrecon info``) without loading numba, which costs far more.
_NUMPY_SCREEN_ROWS = 1 << 16


def _scan_numpy(pos, val, width, height):
    """:func:`_scan` in NumPy: the same counts, compared in float64 as the kernel does."""
    x, y = pos[:, 0], pos[:, 1]
    w, h = np.float64(width), np.float64(height)
    bad = ~((x >= 0.0) & (x < w) & (y >= 0.0) & (y < h))
    n_bad = int(np.count_nonzero(bad))
    first = int(np.argmax(bad)) if n_bad else -1
    return n_bad, first, int(val.shape[0] - np.count_nonzero(np.isfinite(val).all(axis=1)))


# ---------------------------------------------------------------- validation
def check_samples(positions, values, *, width: int, height: int, n_channels: int, where: str = "samples",
                  channels: Sequence[str] | None = None, error=InputError):
    """Validate a batch of samples; returns ``(positions, values, n_nonfinite)``.

    Positions and values come back C-contiguous in a floating dtype (the
    one given, float16 widened to float32, integers to float64): the
    precision a caller sent is kept.  Raises ``error(where, field,
    problem)`` (an :class:`InputError` by default) for mis-shaped arrays,
    non-real dtypes, and positions that are non-finite or off the film.
    Non-finite *values* are counted, not refused: the caller applies its
    policy with :func:`apply_nonfinite`.
    """
    pos = np.asarray(positions)
    val = np.asarray(values)
    if val.ndim == 1 and n_channels == 1:
        val = val[:, None]
    if pos.ndim != 2 or pos.shape[1] != 2:
        raise error(where, "positions", f"shape {pos.shape}, expected (N, 2)")
    if val.ndim != 2 or val.shape[1] != n_channels:
        named = f" for channels {','.join(channels)}" if channels else " to match the channels"
        raise error(where, "values", f"shape {val.shape}, expected (N, {n_channels}){named}")
    if pos.shape[0] != val.shape[0]:
        raise error(where, "values", f"{val.shape[0]} rows but {pos.shape[0]} positions")
    for name, arr in (("positions", pos), ("values", val)):
        if arr.dtype.kind not in "fiu":
            raise error(where, name, f"dtype {arr.dtype}, expected float32 or float64")
    pos = _widen(pos)
    val = _widen(val)
    if pos.shape[0] == 0:
        return pos, val, 0
    pos = np.ascontiguousarray(pos)
    val = np.ascontiguousarray(val)
    if pos.shape[0] < _NUMPY_SCREEN_ROWS:
        n_bad_pos, first_bad, n_nonfinite = _scan_numpy(pos, val, width, height)
    else:
        pos_ok, val_ok = _quick_check(pos, val, width, height)
        n_bad_pos, first_bad, n_nonfinite = (0, -1, 0) if pos_ok and val_ok else _scan(pos, val, width, height)
    if n_bad_pos:
        raise error(where, "positions", f"{n_bad_pos} sample(s) off the film [0, {width}) x [0, {height}) "
                    f"or non-finite, first at row {first_bad}: {pos[first_bad].tolist()}")
    return pos, val, int(n_nonfinite)


def one_float_dtype(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two float arrays in one dtype: as given where they share it, else both float64 (the float32 one
    widened, exactly).  The kernels that read positions with values (or features) then compile for two
    dtypes, not for every mix of them."""
    if a.dtype == b.dtype:
        return a, b
    return a.astype(np.float64, copy=False), b.astype(np.float64, copy=False)


def touches_window(positions, window) -> bool:
    """Whether any position's pixel lies in ``window`` = ``(y0, y1, x0, x1)`` (positions on the film)."""
    pos = np.asarray(positions)
    if pos.shape[0] == 0:
        return False
    y0, y1, x0, x1 = window
    y, x = pos[:, 1], pos[:, 0]
    return bool(np.any((y >= y0) & (y < y1) & (x >= x0) & (x < x1)))


def positions_on_film(positions, width: int, height: int) -> bool:
    """Whether every position is finite and on the ``width`` x ``height`` film (what :func:`check_samples` asks of
    them): a reader that skips a batch's values checks its positions still."""
    pos = np.asarray(positions)
    if pos.shape[0] == 0:
        return True
    x, y = pos[:, 0], pos[:, 1]
    with np.errstate(invalid="ignore"):
        return bool(np.all((x >= 0) & (x < width) & (y >= 0) & (y < height)))


def available_memory() -> int | None:
    """Bytes of memory this machine can still give a process (Linux ``MemAvailable``), or None if unknown."""
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None


#: Allocations below this many bytes are not checked by :func:`check_memory`.
_MEMORY_CHECK_FROM = 1 << 25


def check_memory(where: str, field: str, nbytes: float, what: str, fix: str) -> None:
    """Refuse, in one line, an allocation of ``nbytes`` that this machine cannot hold.

    Called before the arrays of a film (its per-pixel statistics, its counts)
    or of a round of samples are allocated, so that a header or a budget
    asking for more than the available memory ends in an
    :class:`InputError`, not in a ``MemoryError`` traceback or the kernel's
    OOM killer.  ``what`` says what would be allocated, ``fix`` what to do.
    """
    if nbytes < _MEMORY_CHECK_FROM:
        return  # small films and rounds: not worth a read of /proc/meminfo each
    avail = available_memory()
    if avail is not None and nbytes > avail:
        raise InputError(where, field, f"{what} needs {nbytes / 2**30:.3g} GiB of memory, more than the "
                         f"{avail / 2**30:.3g} GiB this machine has available; {fix}")


def _widen(arr: np.ndarray) -> np.ndarray:
    if arr.dtype.kind != "f":
        return arr.astype(np.float64)
    if arr.dtype == np.float16:
        return arr.astype(np.float32)
    return arr


def check_reference(reference, shape, *, where: str = "reference"):
    """A reference image as float64 (H, W, C), or None; the one check of every entry point.

    A 2-D image is taken as one channel.  Raises :class:`InputError` naming
    ``where`` for a shape other than ``shape`` (height, width, channels) or
    NaN/Inf values.
    """
    if reference is None:
        return None
    shape = tuple(int(x) for x in shape)
    ref = np.asarray(reference, dtype=np.float64)
    if ref.ndim == 2 and shape[2] == 1:
        ref = ref[..., None]
    if ref.shape != shape:
        raise InputError(where, "shape", f"{ref.shape}, expected (height, width, channels) = {shape}")
    if not np.isfinite(ref).all():
        raise InputError(where, "values", "contains NaN or Inf")
    return ref


def apply_nonfinite(positions, values, n_nonfinite: int, policy: str, *, where: str = "samples", error=InputError):
    """Apply the non-finite policy to a checked batch; returns ``(positions, values)``.

    ``drop`` removes samples with any NaN/Inf channel, ``zero`` sets those
    channels to 0, ``raise`` refuses the batch naming ``where``.
    """
    if not n_nonfinite:
        return positions, values
    if policy == "raise":
        raise error(where, "values", f"{n_nonfinite} sample(s) with NaN or Inf values; "
                    "drop them with nonfinite='drop' or fix the renderer")
    finite = np.isfinite(values)
    if policy == "drop":
        keep = finite.all(axis=1)
        return positions[keep], values[keep]
    return positions, np.where(finite, values, values.dtype.type(0))


def warn_nonfinite(source: str, n_nonfinite: int, policy: str, *, stacklevel: int = 2) -> None:
    """The one warning for ``n_nonfinite`` samples the ``drop``/``zero`` policy handled in ``source``.

    ``stacklevel`` as the caller would pass to :func:`warnings.warn`.
    """
    verb = "dropped" if policy == "drop" else "set to 0"
    warnings.warn(f"{source}: values: {n_nonfinite} sample(s) with NaN or Inf {verb} "
                  f"(policy nonfinite={policy!r})", McreconWarning, stacklevel=stacklevel + 1)


# ---------------------------------------------------------------- sources
def round_ends_of(rounds) -> np.ndarray:
    """Cumulative sample count at the end of each round, from a non-decreasing per-sample round index."""
    r = np.asarray(rounds)
    n = r.shape[0]
    return np.asarray((np.flatnonzero(np.diff(r)) + 1).tolist() + [n] if n else [], np.int64)


def round_slices(round_ends) -> list[tuple[int, int]]:
    """(start, stop) sample ranges of each round, from the rounds' cumulative ends."""
    ends = np.asarray(round_ends, np.int64)
    starts = np.concatenate([[0], ends[:-1]])
    return [(int(a), int(b)) for a, b in zip(starts, ends)]


@dataclasses.dataclass(eq=False)
class SampleChunk:
    """A contiguous run of samples of a source."""

    positions: np.ndarray
    values: np.ndarray
    round: np.ndarray | None
    start: int
    features: dict = dataclasses.field(default_factory=dict)  # name -> (n, k), the features asked for

    def __len__(self) -> int:
        return int(self.positions.shape[0])


#: What a renderer's samples of a pixel are (``Renderer.sampler``; a reply file's ``sampler`` attribute):
#: ``independent``, each sample drawn on its own (what a renderer that says nothing draws); ``sobol``, each
#: pixel's own low-discrepancy sequence in base 2 continued from the request's ``first_index`` (an
#: Owen-scrambled Sobol sequence, a (0, 2)-sequence, Cycles' per-pixel patterns), whose aligned blocks of
#: ``2^k`` samples are stratified: a pixel's mean pays most on a whole block (``mcrecon.core.nets``).
SAMPLERS = ("independent", "sobol")


def check_sampler(value, *, where: str, field: str = "sampler") -> str:
    """A renderer's declared sampler, one of :data:`SAMPLERS` (None, or nothing said: ``independent``).

    Raises :class:`~mcrecon.errors.InputError` naming ``where`` and ``field`` for anything else.
    """
    if value is None:
        return "independent"
    if isinstance(value, np.ndarray) and value.ndim == 0:
        value = value.item()
    if isinstance(value, bytes):
        value = value.decode("utf-8", "replace")
    if isinstance(value, str) and value.strip().lower() in SAMPLERS:
        return value.strip().lower()
    raise InputError(where, field, f"{value!r}; declare 'sobol' where each pixel's samples continue one stratified "
                     "base-2 sequence from the request's first_index, 'independent' (or nothing) otherwise")


class SampleSet:
    """Samples held in memory, as a sample source (the in-memory twin of a sample log).

    Parameters
    ----------
    positions : array_like (N, 2)
        Film positions, x the column and y the row.
    values : array_like (N, C)
    width, height : int
    channels : sequence of str, optional
        Default R, G, B for 3 columns, else C0, C1, ...
    rounds : array_like of int (N,), optional
        Round index per sample, non-decreasing (default: one round).
        NaN/Inf values are kept; readers apply their policy.
    features : mapping of str to array_like (N,) or (N, k), optional
        Per-sample features (``albedo``, ``normal``, ``depth``, any
        others; :mod:`mcrecon.core.features`), validated once here;
        non-finite entries are set to 0 and counted (``n_feature_zeroed``).
    sampler : {"independent", "sobol"}, optional
        What each pixel's samples are (:data:`mcrecon.core.requests.SAMPLERS`): ``sobol`` where sample
        k of a pixel (in stream order) is sample k of its stratified sequence, as a sample log's
        ``sampler`` attribute says (:func:`~mcrecon.core.halves.split_halves` then splits each pixel
        by prefix blocks).  None: ``independent``.

    Raises
    ------
    InputError
        Mis-shaped arrays, positions off the film or non-finite, rounds
        not non-decreasing.

    Examples
    --------
    >>> import numpy as np
    >>> from mcrecon import SampleSet
    >>> pos = np.array([[0.5, 0.5], [1.2, 0.7], [1.9, 0.1], [0.1, 0.9]])
    >>> s = SampleSet(pos, np.ones((4, 3)), width=2, height=1, rounds=[0, 0, 1, 1])
    >>> s.channels, s.n_rounds, s.round_slices()
    (('R', 'G', 'B'), 2, [(0, 2), (2, 4)])
    >>> SampleSet(pos + 1, np.ones((4, 3)), width=2, height=1)
    Traceback (most recent call last):
    ...
    mcrecon.errors.InputError: samples: positions: 4 sample(s) off the film [0, 2) x [0, 1) or non-finite, first at row 0: [1.5, 1.5]
    """

    def __init__(self, positions, values, *, width: int, height: int, channels: Sequence[str] | None = None,
                 rounds=None, features=None, name: str = "samples", sampler: str | None = None):
        self.name = str(name)
        self.sampler = check_sampler(sampler, where=self.name)
        self.width, self.height = int(width), int(height)
        if self.width < 1 or self.height < 1:
            raise InputError(self.name, "width/height", f"{self.width}x{self.height}, expected at least 1x1")
        val = np.asarray(values)
        n_ch = (val.shape[1] if val.ndim == 2 else 1) if channels is None else len(channels)
        if channels is None:
            channels = ("R", "G", "B") if n_ch == 3 else tuple(f"C{i}" for i in range(n_ch))
        self.channels = tuple(str(c) for c in channels)
        self.positions, self.values, self.n_nonfinite = check_samples(
            positions, values, width=self.width, height=self.height, n_channels=len(self.channels),
            where=self.name, channels=self.channels)
        n = self.positions.shape[0]
        if rounds is None:
            self.round_ends = np.array([n] if n else [], np.int64)
        else:
            r = np.asarray(rounds)
            if r.shape != (n,) or r.dtype.kind not in "iu":
                raise InputError(self.name, "rounds", f"shape {r.shape} dtype {r.dtype}, expected ({n},) integers")
            if n and np.any(np.diff(r) < 0):
                raise InputError(self.name, "rounds", "must be non-decreasing (samples grouped by round in order)")
            self.round_ends = round_ends_of(r)
        self.features, self.n_feature_zeroed = check_features(features, n, where=self.name)
        if self.n_feature_zeroed:
            warn_feature_zeroed(self.name, self.n_feature_zeroed)

    @property
    def feature_names(self) -> tuple[str, ...]:
        return tuple(self.features)

    @property
    def feature_shapes(self) -> dict[str, tuple[int, ...]]:
        """Per-sample shape of each feature (``(k,)``)."""
        return {name: arr.shape[1:] for name, arr in self.features.items()}

    @property
    def n_samples(self) -> int:
        return int(self.positions.shape[0])

    @property
    def n_rounds(self) -> int:
        return int(self.round_ends.size)

    def round_slices(self) -> list[tuple[int, int]]:
        """(start, stop) sample ranges of each round."""
        return round_slices(self.round_ends)

    def iter_chunks(self, *, chunk_size: int = 1 << 20, rounds=None, with_round: bool = True,
                    features=()) -> Iterator[SampleChunk]:
        """Chunks of at most ``chunk_size`` samples (of some rounds), as views (``features``: names to include)."""
        for name in features:
            if name not in self.features:
                raise InputError(self.name, "features", f"no feature {name!r}; it has: "
                                 f"{', '.join(self.features) or '(none)'}")
        sl = self.round_slices()
        ranges = [(0, self.n_samples)] if rounds is None else [sl[int(r)] for r in rounds]
        for a, b in ranges:
            for s in range(a, b, max(int(chunk_size), 1)):
                e = min(b, s + max(int(chunk_size), 1))
                rnd = None
                if with_round:
                    rnd = np.searchsorted(self.round_ends, np.arange(s, e), side="right").astype(np.int64)
                yield SampleChunk(self.positions[s:e], self.values[s:e], rnd, s,
                                  {name: self.features[name][s:e] for name in features})

    def __repr__(self) -> str:
        feats = f", features={','.join(self.features)}" if self.features else ""
        return (f"SampleSet({self.width}x{self.height}, channels={','.join(self.channels)}, "
                f"samples={self.n_samples}, rounds={self.n_rounds}{feats})")


# ---------------------------------------------------------------- precision
@lazy_njit(cache=True, nogil=True)
def _spread_lost(pos, val, width, height, lo64, hi64, lo32, hi32):
    n_pix = width * height
    for p in range(n_pix):
        for c in range(val.shape[1]):
            lo64[p, c] = np.inf
            hi64[p, c] = -np.inf
            lo32[p, c] = np.inf
            hi32[p, c] = -np.inf
    for k in range(pos.shape[0]):
        p = int(pos[k, 1]) * width + int(pos[k, 0])
        for c in range(val.shape[1]):
            v = val[k, c]
            if not math.isfinite(v):
                continue
            r = float(np.float32(v))
            lo64[p, c] = min(lo64[p, c], v)
            hi64[p, c] = max(hi64[p, c], v)
            lo32[p, c] = min(lo32[p, c], r)
            hi32[p, c] = max(hi32[p, c], r)
    lost = 0
    for p in range(n_pix):
        for c in range(val.shape[1]):
            s64 = hi64[p, c] - lo64[p, c]
            if s64 > 0.0 and abs((hi32[p, c] - lo32[p, c]) - s64) > 0.5 * s64:
                lost += 1
                break
    return lost


def float32_loses_spread(positions, values, *, width: int, height: int) -> int:
    """Pixels whose spread of values within this batch float32 storage would not keep.

    A pixel counts when, in some channel, the range of its float64 values
    differs from the range of the same values rounded to float32 by more
    than half (e.g. 1e6 +- 1e-3: float32's spacing at 1e6 is 0.0625, so
    every sample rounds to the same number and the variance becomes 0).
    Positions must have been checked (:func:`check_samples`).
    """
    pos = np.ascontiguousarray(positions, dtype=np.float64)
    val = np.ascontiguousarray(values, dtype=np.float64)
    if pos.shape[0] == 0:
        return 0
    shape = (int(width) * int(height), val.shape[1])
    bufs = [np.empty(shape) for _ in range(4)]
    return int(_spread_lost(pos, val, int(width), int(height), *bufs))


#: The largest finite float32.
FLOAT32_MAX = float(np.finfo(np.float32).max)


def as_hwc(image, dtype=np.float64, *, where: str | None = None, field: str = "image") -> np.ndarray:
    """An image as (H, W, C) of ``dtype``: a single-channel (H, W) array gets a channel axis.  With
    ``where``, an image that is not numeric (text, objects) is refused naming ``field``, not with
    numpy's bare ValueError."""
    if where is not None:
        try:
            given = np.asarray(image)
        except ValueError:  # a ragged nesting of lists
            raise InputError(where, field, "not an array: nested lists of unequal lengths; give an (H, W) or "
                             "(H, W, C) numeric image") from None
        if given.dtype.kind not in "fiub":
            raise InputError(where, field, f"dtype {given.dtype}, expected a numeric image")
    a = np.asarray(image, dtype=dtype)
    return a[..., None] if a.ndim == 2 else a


def pixel_index(positions: np.ndarray, width: int) -> np.ndarray:
    """Flat pixel index ``row * width + col`` of film positions."""
    pos = np.asarray(positions)
    return np.floor(pos[:, 1]).astype(np.int64) * width + np.floor(pos[:, 0]).astype(np.int64)

__dir__ = _public_dir(__name__)


@lazy_njit(cache=True, nogil=True)
def _sorted_by_row(pos, h):
    # a stable counting sort on the pixel row: O(N + H), H sequential write streams
    starts = np.zeros(h + 1, np.int64)
    key = np.empty(pos.shape[0], np.int64)
    for k in range(pos.shape[0]):
        y = min(max(int(math.floor(pos[k, 1])), 0), h - 1)
        key[k] = y
        starts[y + 1] += 1
    for p in range(h):
        starts[p + 1] += starts[p]
    out = np.empty_like(pos)
    for k in range(pos.shape[0]):
        q = starts[key[k]]
        out[q, 0] = pos[k, 0]
        out[q, 1] = pos[k, 1]
        starts[key[k]] = q + 1
    return out


def sort_by_row(positions: np.ndarray, height: int) -> np.ndarray:
    """Film positions (N, 2) ordered by pixel row, stable within a row (a copy).

    Why: a renderer answers in request order, and the statistics take
    samples row by row several times faster than scattered ones (a row's
    per-pixel accumulators stay in cache), which matters most for the
    pipelined run's unoverlapped commits.  Measured, 3.7 M samples on
    1024^2: ingest 0.90 s scattered, 0.17 s by row, 0.13 s by pixel; the
    sort by row costs 0.09 s, by pixel 0.32 s.  The order of a request does
    not change what it asks for.
    """
    pos = np.ascontiguousarray(positions, dtype=np.float64)
    if pos.shape[0] == 0:
        return pos.copy()
    return _sorted_by_row(pos, int(height))
#: Rows per read when streaming (a multiple of the chunk rows).
DEFAULT_READ_ROWS = 1 << 20
