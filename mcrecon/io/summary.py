"""What a sample log holds, in one streaming pass: :func:`summarize_log`."""

from __future__ import annotations

import numpy as np

from ..core.samples import check_memory, check_samples, pixel_index
from .logformat import FORMAT_VERSION
from .reader import SampleLog, read_log
from .lock import live_writer

__all__ = ["summarize_log"]


def summarize_log(log) -> dict:
    """Size, channels, sample counts and value problems of a sample log.

    The samples are streamed once, in chunks (memory bounded by the
    image); positions are validated as every reader validates them.

    Parameters
    ----------
    log : path-like or SampleLog

    Returns
    -------
    dict
        ``file``, ``format_version``, ``width``, ``height``, ``channels``,
        ``samples`` (committed: what the renderer delivered, NaN/Inf
        included; the count an adaptive run's budget and round records
        use), ``finite_samples`` (those a reconstruction keeps under the
        default ``drop`` policy), ``rounds``; per-pixel counts of the
        samples a reconstruction uses (NaN/Inf samples dropped):
        ``spp_min``, ``spp_mean``, ``spp_max``, ``empty_pixels``,
        ``pixels_with_one_sample``; ``nonfinite_samples`` (a NaN or Inf
        in any channel), ``negative_samples`` (a finite channel below 0),
        ``value_dtype``, ``features``, ``reference`` (whether the log
        stores one), ``metadata`` and ``writer_pid`` (the process of a
        live run appending to the log, else None: the counts are those of
        the rounds it had committed when the summary started).

    Raises
    ------
    InputError
        A malformed log, or positions off the film.
    """
    if not isinstance(log, SampleLog):
        log = read_log(log)
    w, h, nch = log.width, log.height, len(log.channels)
    check_memory(str(log.path), "width/height", 16.0 * w * h, f"counting the samples of a {w}x{h} film per pixel",
                 "use a machine with more memory")  # the counts and one chunk's bincount
    counts = np.zeros(w * h, np.int64)
    n_nonfinite = 0
    n_negative = 0
    for chunk in log.iter_chunks(with_round=False):
        pos, val, nonfinite = check_samples(chunk.positions, chunk.values, width=w, height=h, n_channels=nch,
                                            where=str(log.path), channels=log.channels)
        if nonfinite:
            finite = np.isfinite(val)
            keep = finite.all(axis=1)
            n_nonfinite += int(nonfinite)
            n_negative += int((np.where(finite, val, 0) < 0).any(axis=1).sum())
            pos, val = pos[keep], val[keep]
        else:
            n_negative += int((val < 0).any(axis=1).sum())
        counts += np.bincount(pixel_index(pos, w), minlength=w * h)
    return {
        "file": str(log.path), "format_version": FORMAT_VERSION, "width": w, "height": h,
        "channels": list(log.channels), "samples": log.n_samples, "finite_samples": log.n_samples - n_nonfinite,
        "rounds": log.n_rounds,
        "spp_min": int(counts.min()), "spp_mean": float(counts.mean()), "spp_max": int(counts.max()),
        "empty_pixels": int((counts == 0).sum()), "pixels_with_one_sample": int((counts == 1).sum()),
        "nonfinite_samples": n_nonfinite, "negative_samples": n_negative,
        "value_dtype": str(log.value_dtype), "features": list(log.feature_names),
        "reference": log.has_reference, "metadata": log.metadata, "writer_pid": live_writer(log.path),
    }
