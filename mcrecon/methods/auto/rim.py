"""An emitter's rim: the pixels whose mean one rare sample carries (:data:`ONE_SAMPLE`), which the global
prior (:func:`.selection._global_prior`) neither lifts further (:func:`_lifted`) nor, on a frame with features,
leaves at their mean where OIDN + albedo + normal on the halves lowers them (:func:`_lowered`, :func:`rim_box`;
docs/methods/auto.md, "Selection rule", step 3a).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

__all__ = ["FOUND", "ONE_SAMPLE", "OWN_LIFT", "TAIL", "Z_OWN", "own_interval", "rim_box"]

#: A pixel's mean counts as carried by one sample where its standard error is at least this fraction of it
#: (one non-zero sample among n: exactly 1; two equal ones: 0.71).
ONE_SAMPLE = 0.9


def _lifted(cands, g, choice, y, v, where):
    """Per pixel of ``where``: candidate ``g`` above both the pixel mean ``y`` and the chosen candidate's
    value in some channel (False elsewhere, and where a value is NaN).

    Under rare huge samples a pixel's mean is right-skewed: a pixel that caught one of them (at an
    emitter's rim, one sample in 32 on the emitter) has a mean above its truth, often far above, and a
    default that lifts it further adds its neighbours' light to a pixel that already over-counts its
    own.  The median of its 8 neighbours' means (:func:`.selection._nearer_the_neighbours`) cannot see this when
    those neighbours lie on the emitter: the lifted value is then "nearer the neighbours".  A pixel
    whose samples missed a light its neighbours found keeps the plain choice when that lifts it at
    least as far (``y`` low, the chosen value the larger bound)."""
    out = np.zeros(y.shape[:2], bool)
    if not where.any():
        return out
    ii, jj, xg, xc, yw, one = _one_sample_values(cands, g, choice, y, v, where)
    with np.errstate(invalid="ignore"):
        out[ii, jj] = ((xg > np.maximum(yw, xc)) & one).any(axis=-1)
    return out


def _lowered(cands, g, choice, y, v, where):
    """Per pixel of ``where``: a mean carried by one sample in some channel (:data:`ONE_SAMPLE`) and candidate
    ``g`` below the pixel mean ``y`` and no higher than the chosen candidate's value in every channel (False
    elsewhere, and where a value is NaN): :func:`_lifted`'s mirror, the pixels an emitter's rim rule lowers
    (``_global_prior(rim=)``)."""
    out = np.zeros(y.shape[:2], bool)
    if not where.any():
        return out
    ii, jj, xg, xc, yw, one = _one_sample_values(cands, g, choice, y, v, where)
    with np.errstate(invalid="ignore"):
        out[ii, jj] = one.any(axis=-1) & ((xg < yw) & (xg <= xc)).all(axis=-1)
    return out


def _one_sample_values(cands, g, choice, y, v, where):
    """At the pixels of ``where`` (``ii``, ``jj``): candidate ``g``'s values, the chosen candidate's, the means
    and which channels' means one sample carries (standard error at least :data:`ONE_SAMPLE` of a positive
    mean), each (P, C)."""
    ii, jj = np.nonzero(where)
    xg = cands[g].image[ii, jj]
    xc = np.empty_like(xg)
    ks = choice[ii, jj]
    for k in np.unique(ks):
        sel = ks == k
        xc[sel] = cands[k].image[ii[sel], jj[sel]]
    yw = y[ii, jj]
    with np.errstate(invalid="ignore"):
        one = (yw > 0) & (np.sqrt(v[ii, jj]) >= ONE_SAMPLE * yw)
    return ii, jj, xg, xc, yw, one


def rim_box(cands):
    """The index of OIDN with the albedo and normal on the halves (``oidn_aux_halves``) where colour-only OIDN on
    all the samples (``oidn``, ``_global_prior(rare=)``) is not a candidate, None otherwise: the global prior's
    candidate at the one-sample pixels rare huge samples surround that it lowers (``_global_prior(rim=)``)."""
    names = [c.name for c in cands]
    return names.index("oidn_aux_halves") if "oidn_aux_halves" in names and "oidn" not in names else None


#: Standard errors of its own mean (:func:`own_interval`) beyond which a black-box default's value at a pixel
#: counts as spread into it.
Z_OWN = 5.0
#: ... and the multiple of the pixel's own mean by which it must depart as well: a light its samples missed lifts a
#: pixel a few times its mean, the emitter's spread hundreds of times (tuning hdr-9 with seed + 1000: 1 here
#: 0.60 of the pixel mean's error, 10 0.79, 30 2.1).
OWN_LIFT = 10.0
#: A 3 x 3 neighbour's light counts as found by many of its samples where its mean's standard error is at most this
#: fraction of it (one sample in 32 carrying it: 1; 10 of 32: 0.28).
FOUND = 0.3
#: ... and the departure counts as the tail of a blur where it is below this fraction of that neighbour's mean (a
#: light the pixel's samples missed lifts it to about its neighbours' level: tuning checker_spot-13, 0.2 beside 0.8;
#: the emitter's spread on hdr-9 with seed + 1000, 5 beside 5000).
TAIL = 0.03


def own_interval(img, y, v, where):
    """``img`` (written in place) with the pixel mean ``y`` at the pixels of ``where`` whose value departs from it
    by more than :data:`Z_OWN` standard errors of their own (``sqrt(v)``, no neighbourhood's) and more than
    :data:`OWN_LIFT` times ``|y|`` in some channel whose mean is not 0, but by less than :data:`TAIL` times the mean
    of a 3 x 3 neighbour that many of its samples carry (:data:`FOUND`) in that channel.

    Why: a black-box default's pixels are clamped on a wide interval, from the 5 x 5 neighbourhood's variance and
    sample range (for a pixel whose samples missed a rare light its neighbours found, each by one sample or two).
    Beside a large emitter, which its neighbours' samples find again and again, that interval is thousands wide,
    and OIDN + albedo + normal spreads the emitter into dark pixels whose 32 samples agree: tuning hdr-9 rendered
    with its seed + 1000, truth 0.025, mean 0.024 (sd 0.0009), output 5.3, auto 88.6 times the pixel mean's error.
    Without the neighbour test (the spotlit checkers, whose light one sample in 60 finds: a pixel that missed it
    lies 10 to 40 times below its truth) tuning checker_spot-2 is 0.196 of the pixel mean's error instead of 0.009;
    without :data:`TAIL` checker_spot-2/-7/-9/-13 1.2 to 1.4 times theirs.  A pixel whose samples all read 0
    keeps the black box's value (they may have missed a caustic on black)."""
    with np.errstate(invalid="ignore"):
        sd = np.sqrt(v)
        lit = np.where((y > 0) & (sd <= FOUND * y), y, 0.0)
        nb = ndimage.maximum_filter(lit, size=(3, 3, 1), mode="nearest")
        d = np.abs(img - y)
        far = (d > Z_OWN * sd) & (d > OWN_LIFT * np.abs(y)) & (y != 0) & (d < TAIL * nb)
        at = where & far.any(axis=-1)
    img[at] = y[at]
    return img
