"""An emitter's rim: the pixels whose mean one rare sample carries (:data:`ONE_SAMPLE`), which the global
prior (:func:`.selection._global_prior`) neither lifts further (:func:`_lifted`) nor, on a frame with features,
leaves at their mean where OIDN + albedo + normal on the halves lowers them (:func:`_lowered`, :func:`rim_box`;
docs/methods/auto.md, "Selection rule", step 3a).
"""

from __future__ import annotations

import numpy as np

__all__ = ["ONE_SAMPLE", "rim_box"]

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
