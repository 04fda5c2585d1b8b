"""Channel lists and variances from moments, shared by :mod:`.pixel_exr` and :mod:`.pixel_exr_features`.

Both read channels of a pixel-statistics EXR: the colour's and the features'.  What both need lives
here, below them, so that the feature module never imports the reader that imports it.
"""

from __future__ import annotations

import warnings

import numpy as np

from ..errors import InputError, McreconWarning


def _split(text, field) -> tuple[str, ...] | None:
    if text is None:
        return None
    if isinstance(text, str):
        parts = tuple(p.strip() for p in text.split(","))
    else:
        parts = tuple(str(p).strip() for p in text)
    if not parts or any(not p for p in parts):
        raise InputError(f"--{field.replace('_', '-')}", field, f"{text!r}: expected comma-separated channel "
                         "names, e.g. R,G,B")
    if field == "mean" and len(set(parts)) != len(parts):  # they name the output channels
        # (a variance or moment channel may serve several mean channels)
        dup = next(p for p in parts if parts.count(p) > 1)
        raise InputError(f"--{field.replace('_', '-')}", field, f"{text!r} names channel {dup!r} twice; "
                         "each output channel needs its own, e.g. R,G,B")
    return parts


#: Unit roundoff of float32, in which renderers accumulate a film's moments.
_F32_U = 2.0 ** -24


def _variance_from_moments(exr, names, m1, m2, n, half=False) -> np.ndarray:
    """The variance of the samples from the first and second moments (clamped at 0, times n / (n - 1)).

    A second moment below the squared mean by more than float rounding is
    damage (or moments of different samples), warned with its pixel count.
    The bound is the worst case of a float32 film's accumulation over n
    weighted samples plus the storage's rounding, relative to
    max(E[x^2], mean^2): ``6 (n + 1) 2^-24 + 3 u`` (u: 2^-24 for float32
    channels, 2^-11 for half floats); a constant pixel lands within it.
    """
    n_arr = np.asarray(n, dtype=np.float64)
    sampled = np.broadcast_to(n_arr > 0, m1.shape[:2])[..., None]
    neg = sampled & (m2 < 0)
    if neg.any():
        per = [names[c] for c in range(m2.shape[2]) if neg[..., c].any()]
        raise InputError(str(exr.path), ",".join(per), f"{int(neg.any(axis=2).sum())} sampled pixel(s) with a "
                         "negative second moment E[x^2]; it is >= 0")
    sq = m1 * m1
    nn = n_arr if n_arr.ndim == 0 else n_arr[..., None]
    u = 2.0 ** -11 if half else _F32_U
    tol = 6.0 * (nn + 1.0) * _F32_U + 3.0 * u
    damaged = sampled & (sq - m2 > tol * np.maximum(sq, m2))
    if damaged.any():
        per = [names[c] for c in range(m2.shape[2]) if damaged[..., c].any()]
        n_max = float(np.max(n_arr))
        warnings.warn(f"{exr.path}: {','.join(per)}: {int(damaged.any(axis=2).sum())} sampled pixel(s) with a "
                      "second moment below the squared mean by more than float rounding (relative "
                      f"6 (n + 1) 2^-24 + 3 u = {6.0 * (n_max + 1.0) * _F32_U + 3.0 * u:.2g} at n = {n_max:g}); "
                      "their variance is set to 0: the moments are damaged or not of the same samples",
                      McreconWarning, stacklevel=4)
    pop = np.maximum(m2 - sq, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(nn > 1, pop * nn / np.maximum(nn - 1.0, 1.0), 0.0)
