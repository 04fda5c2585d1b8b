"""``auto``'s last step: the chosen image held to an interval about each pixel's mean (the safeguard).

The error estimates are noisy exactly where a rare bright sample sits; a candidate chosen on them may
still carry its light into exact dark pixels beside it (caustic: 1.6x the pixel mean without the clamp).
Clamping onto an interval that holds the true value with high probability never moves an estimate away
from it (the same safeguard as awr's robust default).  docs/methods/auto.md, "Selection rule", gives the
intervals and the heavy-tail rule.
"""

from __future__ import annotations

import numpy as np

from ...core.safeguard import confidence_clamp, empty_pixels_kept, sample_range_bounds, widened_range_bounds
from .blackbox import BLACK_BOXES
from .rim import own_interval
from .selection import _no_push_in_heavy_tails

__all__ = ["safeguarded"]


def safeguarded(img, cands, choice, stats, y, v, count, *, level, v_safe, v_wide, bounds, on_default, prior,
                scale) -> None:
    """Clamp ``img`` (H, W, C), the per-pixel ``choice`` among ``cands``, in place.

    ``y``, ``v``, ``count``: the pixel means, their variances and the sample counts; ``v_safe`` the variances
    floored by the neighbourhood's; ``level`` the safeguard's confidence level.  From the global prior
    (:func:`.selection._global_prior`): ``bounds`` (the samples' range bounds, or None), ``on_default`` (the
    pixels that hold the default), ``prior`` (its info: ``g`` the default's index, ``rare`` the pixels
    that took the rare-sample candidate) and ``v_wide`` (the wide variances where a black box is the
    default).  ``scale``: the albedo divisor of the heavy-tail rule, or None.
    """
    lo, hi = sample_range_bounds(stats) if bounds is None else bounds
    # a pixel without samples has no interval: it keeps the value filled in from its neighbours
    v_clamp, lo_c, hi_c = v_safe, lo, hi
    g = prior.get("g", -1)
    black = g >= 0 and on_default.any() and cands[g].name in BLACK_BOXES
    if black:  # the wide interval and range at the black box's pixels
        v_clamp = np.where(on_default[..., None], v_wide, v_safe)
        lo_c, hi_c = widened_range_bounds(stats, on_default, lo, hi)
    with empty_pixels_kept(img, count):
        confidence_clamp(img, y, v_clamp, level, lo_c, hi_c, out=img)
        # The heavy-tail rule judges a push by the median of the neighbours' means, which under a rarely
        # found light lies below the truth (the pixel means are right-skewed): a feature-guided value at
        # the truth of a pixel whose samples missed the light is then "further from the median" than its
        # dark mean, and the rule would put the hole back.  Pixels that chose a feature-guided candidate
        # keep its clamped value (its cost and gain per scene: docs/methods/auto.md, "Limits").
        guided = [k for k, c in enumerate(cands) if c.feature]
        keep = np.isin(choice, guided) if guided else None
        # So do the pixels with rare huge samples around that took the black box on all the samples (or,
        # with features, OIDN + albedo + normal on the halves at the rim) under another default: on the
        # median's interval, which the clamp holds them to (a black box default's wide interval leaves
        # that to the rule).
        rare = prior.get("rare")
        if rare is not None and not black:
            keep = rare if keep is None else keep | rare
        kept = img[keep] if keep is not None and keep.any() else None
        _no_push_in_heavy_tails(img, y, hi, out=img, scale=scale)
        if kept is not None:
            img[keep] = kept
    if black:  # nor a value far outside its own interval where a pixel's samples agree (rim.own_interval)
        own_interval(img, y, v, on_default)
