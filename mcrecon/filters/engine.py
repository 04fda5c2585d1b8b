"""Separable, normalised image filtering on a small thread pool, bit-identical to ``scipy.ndimage``.

Every separable filter that goes through :func:`correlate_jobs` is
computed by one compiled kernel that performs, term for term, the
arithmetic of ``scipy.ndimage.correlate1d(mode="constant", cval=0)``
applied along axis 0 and then axis 1 (symmetric odd kernel:
``k_0 x_0 + sum_j k_j (x_-j + x_j)`` in double precision, outermost taps
first, the first pass rounded to the array's dtype), so its results are
bit-identical to that reference.  It fuses both passes row by row (no
intermediate image), runs on contiguous rows the compiler vectorises
(ndimage gathers strided lines along axis 0), folds in the normalisation
by the weight sums, and releases the GIL, so independent convolutions run
on a small thread pool.  Each output element is computed by exactly one
thread in a fixed order: the result does not depend on the number of
threads.

Worker threads
--------------
:func:`n_threads` is the one setting, read in this order:

1. the ``threads=`` argument of the call (e.g.
   ``mcrecon.methods.gem.filter_bank(..., threads=2)``);
2. the environment variable ``MCRECON_THREADS``: a positive integer
   (empty or unset: not given; anything else is an
   :class:`~mcrecon.errors.InputError`);
3. the usable cores of the process (``os.sched_getaffinity``, else
   ``os.cpu_count()``), at most 8.

Images smaller than ``2**15`` values are filtered on the calling thread
whatever the setting: handing them to the pool costs more than it saves.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

import numba
import numpy as np
from scipy import ndimage

from ..errors import InputError

__all__ = ["ENV_THREADS", "n_threads", "numba_threads", "parallel_calls", "parallel_rows", "correlate_jobs", "corr2", "safe_div",
           "separable_weights",
           "mask_weights"]

#: Environment variable that sets the number of worker threads.
ENV_THREADS = "MCRECON_THREADS"
#: Default: the usable cores, at most this many.
_MAX_DEFAULT_THREADS = 8
#: Images smaller than this (pixels x channels) are filtered on the calling
#: thread: handing work to the pool costs more than it saves.
_PARALLEL_MIN = 1 << 15
_POOL = None
_POOL_SIZE = 0
_POOL_PID = 0
_POOL_LOCK = threading.Lock()


# ----------------------------------------------------------------------------
# Worker threads
# ----------------------------------------------------------------------------

def n_threads(threads: int | None = None) -> int:
    """Number of worker threads: ``threads``, else ``$MCRECON_THREADS``, else the usable cores (at most 8).

    Raises
    ------
    InputError
        ``threads`` or ``MCRECON_THREADS`` is not a positive integer.
    """
    if threads is not None:
        if isinstance(threads, (bool, np.bool_)) or not isinstance(threads, (int, np.integer)) or threads < 1:
            raise InputError("worker threads", "threads", f"{threads!r}, expected a positive integer (the number of "
                             f"worker threads) or None (${ENV_THREADS}, else the usable cores)")
        return int(threads)
    raw = os.environ.get(ENV_THREADS, "").strip()
    if raw:
        try:
            t = int(raw)
        except ValueError:
            t = 0
        if t < 1:
            raise InputError("environment", ENV_THREADS,
                             f"{raw!r} is not a positive integer; set it to the number of worker threads "
                             f"(e.g. {ENV_THREADS}=4) or unset it to use the usable cores (at most "
                             f"{_MAX_DEFAULT_THREADS})")
        return t
    try:
        t = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        t = os.cpu_count() or 1
    return max(1, min(t, _MAX_DEFAULT_THREADS))


class numba_threads:
    """Context manager: numba's parallel loops use :func:`n_threads` threads inside it.

    The same one setting (``threads=``, ``$MCRECON_THREADS``) then governs
    the thread pool of the filters and numba's ``prange`` loops (capped at
    the threads numba started with, ``NUMBA_NUM_THREADS``).  numba's
    setting is per calling thread; the previous value is restored.
    """

    def __init__(self, threads: int | None = None):
        self.n = min(n_threads(threads), numba.config.NUMBA_NUM_THREADS)

    def __enter__(self):
        self._old = numba.get_num_threads()
        numba.set_num_threads(self.n)
        return self.n

    def __exit__(self, *exc):
        numba.set_num_threads(self._old)
        return False


def _pool(n: int) -> ThreadPoolExecutor:
    global _POOL, _POOL_SIZE, _POOL_PID
    with _POOL_LOCK:
        # a forked child inherits the pool object but not its threads: new pool
        if _POOL is None or _POOL_SIZE != n or _POOL_PID != os.getpid():
            if _POOL is not None and _POOL_PID == os.getpid():
                _POOL.shutdown(wait=False)
            _POOL = ThreadPoolExecutor(max_workers=n, thread_name_prefix="mcrecon-filter")
            _POOL_SIZE, _POOL_PID = n, os.getpid()
        return _POOL


def parallel_calls(fn, arg_tuples, threads: int | None = None) -> list:
    """``[fn(*args) for args in arg_tuples]``, on the thread pool (:func:`n_threads` workers).

    ``fn`` is a ``nogil`` numba kernel writing disjoint parts of its
    outputs, so the calls run in parallel and the result does not depend on
    the number of threads.  This replaces ``parallel=True`` kernels whose
    ``prange`` loop only calls such a kernel: the same parallelism, without
    numba's parallel compilation (a ``parallel=True`` wrapper costs seconds of
    compilation on a first run, e.g. 6.7 s for the NL-means bands, measured
    with benchmarks/bench_first_run.py).  One thread, or one call: run on the
    calling thread.
    """
    arg_tuples = list(arg_tuples)
    n = min(n_threads(threads), len(arg_tuples))
    if n <= 1:
        return [fn(*a) for a in arg_tuples]
    futs = [_pool(n_threads(threads)).submit(fn, *a) for a in arg_tuples]
    return [f.result() for f in futs]


#: Fewest rows per call of :func:`parallel_rows`.
ROW_BLOCK = 64


def parallel_rows(fn, args: tuple, h: int, threads: int | None = None) -> None:
    """``fn(*args, i0, i1)`` for blocks of rows ``[i0, i1)`` covering an ``h``-row image, on the thread pool
    (:func:`parallel_calls`).

    ``fn`` is a ``nogil`` kernel that computes each output row in one call, so the result does not
    depend on the number of threads (nor on the blocks).  Up to four blocks per thread (of at least
    :data:`ROW_BLOCK` rows: a task costs ~15 us, and auto's selection makes ~160 such calls), and as
    for the filters an image smaller than ``2**15`` values (the first array argument's size) stays on
    the calling thread.
    """
    n = n_threads(threads)
    size = next((a.size for a in args if isinstance(a, np.ndarray)), _PARALLEL_MIN)
    if n == 1 or size < _PARALLEL_MIN:
        fn(*args, 0, h)
        return
    rows = max(ROW_BLOCK, -(-h // (4 * n)))
    parallel_calls(fn, [(*args, i0, min(i0 + rows, h)) for i0 in range(0, h, rows)], threads)


# ----------------------------------------------------------------------------
# The compiled separable correlation
# ----------------------------------------------------------------------------

@numba.njit(cache=True, nogil=True)
def _add_pair(acc, a, b, kk):
    # acc += (a + b) * kk in double precision (ndimage's symmetric tap)
    for q in range(acc.size):
        acc[q] += (np.float64(a[q]) + np.float64(b[q])) * kk


@numba.njit(cache=True, nogil=True)
def _corr2_rows(x, k, c, den, mode, out, i0, i1):
    """Rows i0..i1-1 of the separable correlation of x (H, W*c) with k.

    mode 0: out = result (x's dtype); 1: out = result / den[i, j] where
    den > 0, else 0; 2: out = den[i, j] / result where result > 0, else 0
    (modes 1 and 2 read the result in x's dtype, as :func:`safe_div` of the
    ndimage output would).
    """
    h, n = x.shape
    r = k.size // 2
    pad = r * c
    zero = np.zeros(n, x.dtype)
    acc = np.empty(n, np.float64)
    rnd = np.empty(n, x.dtype)
    buf = np.zeros(n + 2 * pad, np.float64)
    k0 = k[r]
    w = n // c
    for i in range(i0, i1):
        # axis 0: rows outside the image are zeros (mode constant, cval 0)
        xi = x[i]
        for q in range(n):
            acc[q] = np.float64(xi[q]) * k0
        for jj in range(-r, 0):
            lo = i + jj
            hi = i - jj
            a = x[lo] if lo >= 0 else zero
            b = x[hi] if hi < h else zero
            _add_pair(acc, a, b, k[r + jj])
        # ndimage stores the first pass in x's dtype.  Element loops, not ``rnd[:] = acc``: a slice
        # assignment compiles numba's shape-mismatch message (string formatting, ~1.5 s of a first run)
        for q in range(n):
            rnd[q] = acc[q]
        # axis 1 on the zero-padded row, channel stride c
        for q in range(n):
            buf[pad + q] = rnd[q]
        for q in range(n):
            acc[q] = buf[pad + q] * k0
        for jj in range(-r, 0):
            d = -jj * c
            _add_pair(acc, buf[pad - d:pad - d + n], buf[pad + d:pad + d + n], k[r + jj])
        for q in range(n):
            rnd[q] = acc[q]
        if mode == 0:
            for q in range(n):
                out[i, q] = rnd[q]
        elif mode == 1:
            for j in range(w):
                dv = den[i, j]
                for ch in range(c):
                    q = j * c + ch
                    out[i, q] = np.float64(rnd[q]) / dv if dv > 0 else 0.0
        else:
            for j in range(w):
                for ch in range(c):
                    q = j * c + ch
                    v = np.float64(rnd[q])
                    out[i, q] = den[i, j] / v if v > 0 else 0.0


def _symmetric_odd(k: np.ndarray) -> bool:
    """ndimage's own test for its symmetric-kernel arithmetic."""
    r = k.size // 2
    eps = np.finfo(np.float64).eps
    return k.size % 2 == 1 and bool(np.all(np.abs(k[r + 1:] - k[r - 1::-1][:r]) <= eps))


def correlate_jobs(jobs, threads: int | None = None) -> list:
    """Run separable correlations; ``jobs`` is a list of ``(x, k, den, mode)``.

    x : (H, W) or (H, W, C); k : 1-D kernel (used as float64, as ndimage
    does); den : (H, W) or None; mode 0 returns the correlation in x's
    dtype, mode 1 ``safe_div(corr, den[..., None])`` and mode 2
    ``safe_div(den[..., None], corr)`` (float64).  Independent jobs, and
    row blocks of large ones, run on the thread pool (:func:`n_threads`
    workers); the result is bit-identical for any number of threads.
    """
    outs, tasks = [], []
    dummy = np.zeros((1, 1))
    for x, k, den, mode in jobs:
        k = np.asarray(k, dtype=np.float64)
        shape = x.shape
        if not _symmetric_odd(k):
            # (never for Gaussian kernels) the reference path
            y = ndimage.correlate1d(x, k, axis=0, mode="constant", cval=0.0)
            y = ndimage.correlate1d(y, k, axis=1, mode="constant", cval=0.0)
            if mode == 1:
                y = safe_div(y, den if y.ndim == 2 else den[..., None])
            elif mode == 2:
                y = safe_div(den if y.ndim == 2 else den[..., None], y.astype(np.float64))
            outs.append(y)
            continue
        h, w = shape[0], shape[1]
        c = int(np.prod(shape[2:], dtype=np.int64)) if len(shape) > 2 else 1
        x2 = np.ascontiguousarray(x).reshape(h, w * c)
        out = np.empty(shape, dtype=x.dtype if mode == 0 else np.float64)
        d2 = dummy if den is None else np.ascontiguousarray(den, dtype=np.float64)
        outs.append(out)
        tasks.append((x2, k, c, d2, mode, out.reshape(h, w * c), h))
    n = n_threads(threads)
    if n == 1 or sum(t[0].size for t in tasks) < _PARALLEL_MIN:
        for x2, k, c, d2, mode, o2, h in tasks:
            _corr2_rows(x2, k, c, d2, mode, o2, 0, h)
        return outs
    # large jobs are cut into row blocks (up to 2 per thread) so the threads
    # finish together; small ones stay whole (a task costs ~20 us)
    futs = []
    pool = _pool(n)
    for x2, k, c, d2, mode, o2, h in tasks:
        nb = max(1, min(h, 2 * n, x2.size // (4 * _PARALLEL_MIN)))
        edges = np.linspace(0, h, nb + 1).astype(np.int64)
        for a, b in zip(edges[:-1], edges[1:]):
            if b > a:
                futs.append(pool.submit(_corr2_rows, x2, k, c, d2, mode, o2, int(a), int(b)))
    for f in futs:
        f.result()
    return outs


def corr2(x: np.ndarray, k: np.ndarray, threads: int | None = None) -> np.ndarray:
    """Separable correlation over axes 0 and 1 with zeros outside the image
    (bit-identical to ``ndimage.correlate1d`` along axis 0, then axis 1)."""
    return correlate_jobs([(x, k, None, 0)], threads)[0]


# ----------------------------------------------------------------------------
# Normalised convolution
# ----------------------------------------------------------------------------

def separable_weights(h: int, w: int, k: np.ndarray) -> np.ndarray:
    """Sum of the 2-D separable kernel's weights inside an ``h`` x ``w`` image, per pixel.

    With every pixel valid the 2-D sum is the product of the 1-D border sums.
    """
    wy = ndimage.correlate1d(np.ones(h), k, mode="constant", cval=0.0)
    wx = ndimage.correlate1d(np.ones(w), k, mode="constant", cval=0.0)
    return np.multiply.outer(wy, wx)


def mask_weights(mask: np.ndarray, k: np.ndarray, full: bool) -> np.ndarray:
    """Sum of the kernel weights over valid pixels, W(p) = sum_q m_q K(p - q).

    ``full``: every pixel of ``mask`` is valid (the cheaper
    :func:`separable_weights`, bit-identical).
    """
    h, w = mask.shape
    if full:
        return separable_weights(h, w, k)
    return corr2(mask.astype(np.float64), k)


def safe_div(num: np.ndarray, den: np.ndarray) -> np.ndarray:
    """``num / den`` where ``den > 0``, else 0 (float64, broadcast shape)."""
    out = np.zeros(np.broadcast_shapes(num.shape, den.shape))
    np.divide(num, den, out=out, where=den > 0)
    return out
