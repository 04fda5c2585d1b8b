"""A round's per-sample passes on the filters' thread pool, bit for bit as on one thread.

A pass that adds samples into per-pixel sums (the image, the statistics) runs
in bands of image rows: each thread follows every sample in order and adds
only into its own rows, so every pixel receives the same terms in the same
order as from one thread, whatever the bands.  A pass that writes one value
per sample runs on ranges of the samples.  Threads: the filters' setting
(:func:`mcrecon.filters.engine.n_threads`, ``$MCRECON_THREADS``).
"""

from __future__ import annotations

import numpy as np

from ...filters.engine import n_threads, parallel_calls

#: Passes over fewer samples run on the calling thread: a band costs its thread a pass over every
#: sample's position, and a task on the pool.
BAND_MIN = 1 << 16


def _parts(n_samples: int, threads: int | None) -> int:
    return n_threads(threads) if n_samples >= BAND_MIN else 1


def row_bands(row_work, n: int) -> list[tuple[int, int]]:
    """At most ``n`` bands of consecutive rows ``(j0, j1)`` covering the film, of about equal
    ``row_work`` (the work of each row, e.g. its samples; its length is the film's height)."""
    row_work = np.asarray(row_work, dtype=np.float64)
    h = row_work.shape[0]
    cum = np.cumsum(row_work)
    if n <= 1 or h <= 1 or not cum[-1] > 0.0:
        return [(0, h)]
    cuts = np.searchsorted(cum, cum[-1] * np.arange(1, n) / n, side="left") + 1
    edges = np.unique(np.concatenate([[0], np.clip(cuts, 1, h - 1), [h]]))
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:])]


def in_bands(kernel, args, n_samples: int, height: int, *, row_work=None, bands=None,
             threads: int | None = None) -> list:
    """``kernel(*args, j0, j1)`` for bands of rows covering a film of ``height`` rows, on the pool:
    ``bands`` as given, else one per thread (:func:`row_bands` of ``row_work``, else of equal rows).
    Returns the results in band order."""
    if bands is None:
        bands = row_bands(np.ones(height) if row_work is None else row_work, _parts(n_samples, threads))
    return parallel_calls(kernel, [tuple(args) + (j0, j1) for j0, j1 in bands], threads)


def in_ranges(kernel, args, n_samples: int, *, threads: int | None = None) -> list:
    """``kernel(*args, k0, k1)`` for consecutive ranges of the samples, one per thread (one below
    :data:`BAND_MIN`), on the pool: for a pass that writes one value per sample.  Returns the results in
    range order."""
    n = _parts(n_samples, threads)
    return parallel_calls(kernel, [tuple(args) + (n_samples * t // n, n_samples * (t + 1) // n) for t in range(n)],
                          threads)
