"""auto's global prior at an emitter's rim on a frame with features: a pixel the vote leaves out whose mean one
rare sample carries takes OIDN + albedo + normal on the halves where that lowers it below its mean and the plain
choice (``_global_prior(rim=)``, :func:`_lowered`).

Such a pixel's mean lies far above its truth as often as below, and the relative metric charges the first far
more: on the corpus's held-out hdr scene with features one rim pixel (truth 0.56, one emitter sample of 417 in
32, mean 13.05) carried 0.90 of the pixel mean's error, and every other candidate kept its mean there.  A frame
without features has colour-only OIDN on all the samples for every such pixel (``rare``); with features that
candidate does not run.
"""

import numpy as np

from mcrecon.methods.auto.features import Candidate
from mcrecon.methods.auto.method import _all_samples_box, _rim_box
from mcrecon.methods.auto.selection import ONE_SAMPLE, _global_prior, _lowered


def _rim(rim_value, sd, *, others=None):
    """A flat 0.5 field, an emitter (50) on the four pixels above and left of P = (4, 4), and P's mean 0.65.

    Candidates: 0 the mean, 1 the plain choice (0.6 at P), 2 the global default (NL-means: the least estimate
    everywhere, P's mean kept), 3 OIDN + albedo + normal on the halves (``rim_value`` at P, ``others`` or the
    mean elsewhere); P's 3 x 3 sample maximum is 100 (rare huge samples around: the vote leaves it out)."""
    h, w = 10, 10
    y = np.full((h, w, 3), 0.5)
    for p in [(3, 3), (3, 4), (3, 5), (4, 3)]:
        y[p] = 50.0
    y[4, 4] = 0.65
    v = np.full((h, w, 3), 0.01)
    v[4, 4] = sd ** 2
    count = np.full((h, w), 32)
    plain_img = y.copy()
    plain_img[4, 4] = 0.6
    rim_img = y.copy() if others is None else np.full((h, w, 3), others)
    rim_img[4, 4] = rim_value
    cands = [Candidate("box", y.copy(), v.copy()),
             Candidate("gauss1", plain_img, np.full((h, w, 3), 0.004)),
             Candidate("nlm", y.copy(), np.full((h, w, 3), 0.001)),
             Candidate("oidn_aux_halves", rim_img, np.full((h, w, 3), 0.02))]
    raw = [c.mse.mean(axis=2) / 0.26 for c in cands]
    hi = y.copy()
    hi[4, 4] = 100.0
    plain = np.zeros((h, w), np.int64)
    plain[4, 4] = 1
    return cands, raw, y, v, count, (y.copy(), hi), plain


def _prior(rim_value, sd, *, rim=3, others=None):
    cands, raw, y, v, count, bounds, plain = _rim(rim_value, sd, others=others)
    info = {}
    got, held = _global_prior(cands, raw.__getitem__, np.stack(raw), plain, y, v, count, bounds, 2.0, 3.0, 4.0,
                              steady=[3], rim=rim, info=info)
    return got, held, info


def test_a_one_sample_rim_pixel_takes_the_rim_candidate_where_it_lowers_it():
    got, held, info = _prior(0.3, 0.65)
    assert info["g"] == 2
    assert got[4, 4] == 3 and held[4, 4]
    np.testing.assert_array_equal(info["rare"], got == 3)
    assert (got[got != 3] == 2).all()
    got, _, _ = _prior(0.3, 0.65, rim=None)  # without it the pixel keeps the default or the plain choice
    assert got[4, 4] != 3


def test_the_rim_candidate_does_not_take_a_pixel_it_lifts_or_one_many_samples_carry():
    assert _prior(0.62, 0.65)[0][4, 4] != 3    # below the mean, above the plain choice (0.6)
    assert _prior(0.9, 0.65)[0][4, 4] != 3     # lifted
    assert _prior(0.3, 0.1)[0][4, 4] != 3      # lowered, but many samples carry the mean


def test_the_rim_candidate_leaves_the_pixels_the_vote_keeps_and_agreeing_dark_pixels_beside_the_emitter():
    """Only the pixels the vote leaves out: a candidate lower than every voter's mean takes none of them; nor
    the pixels whose samples agree beside the emitter (a standard error of 0: not one sample), where OIDN +
    albedo + normal spreads the emitter's light."""
    got, _, info = _prior(0.3, 0.65, others=0.1)
    assert got[4, 4] == 3 and (got == 3).sum() == 1
    cands, raw, y, v, count, bounds, plain = _rim(0.3, 0.65)
    v[4, 4] = 0.0
    got, _ = _global_prior(cands, raw.__getitem__, np.stack(raw), plain, y, v, count, bounds, 2.0, 3.0, 4.0,
                           steady=[3], rim=3)
    assert got[4, 4] != 3


def test_lowered_needs_one_sample_and_every_channel_lowered():
    cands, _, y, v, _, _, plain = _rim(0.3, 0.65)
    where = np.zeros(y.shape[:2], bool)
    where[4, 4] = where[0, 0] = True
    got = _lowered(cands, 3, plain, y, v, where)
    assert got[4, 4] and not got[0, 0] and got.sum() == 1
    # every channel lowered: one channel above the mean is not
    cands[3].image[4, 4] = [0.3, 0.3, 0.7]
    assert not _lowered(cands, 3, plain, y, v, where)[4, 4]
    # one channel's mean carried by one sample is enough; a standard error just under ONE_SAMPLE times it is not
    cands[3].image[4, 4] = 0.3
    v[4, 4] = [(0.99 * ONE_SAMPLE * 0.65) ** 2] * 2 + [0.65 ** 2]
    assert _lowered(cands, 3, plain, y, v, where)[4, 4]
    v[4, 4] = (0.99 * ONE_SAMPLE * 0.65) ** 2
    assert not _lowered(cands, 3, plain, y, v, where)[4, 4]
    # a NaN value is not lower
    v[4, 4] = 0.65 ** 2
    cands[3].image[4, 4, 1] = np.nan
    assert not _lowered(cands, 3, plain, y, v, where)[4, 4]


def test_the_rim_candidate_is_oidn_aux_on_the_halves_only_without_colour_only_oidn_on_all_the_samples():
    c = [Candidate(n, np.zeros((1, 1, 3)), np.zeros((1, 1, 3)))
         for n in ("box", "oidn_halves", "oidn_aux", "oidn_aux_halves")]
    assert _rim_box(c) == 3 and _all_samples_box(c) is None
    c.append(Candidate("oidn", np.zeros((1, 1, 3)), np.zeros((1, 1, 3))))
    assert _rim_box(c) is None and _all_samples_box(c) == 4
    assert _rim_box(c[:3]) is None
