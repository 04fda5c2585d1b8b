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
import pytest

import test_auto_emitter_rim as emitter_rim
from mcrecon.methods.auto.features import Candidate
from mcrecon.methods.auto.method import _all_samples_box
from mcrecon.methods.auto.rim import rim_box
from mcrecon.methods.auto.selection import ONE_SAMPLE, _global_prior, _lowered


def _rim(rim_value, sd, *, others=None):
    """:func:`test_auto_emitter_rim._rim`'s field (a flat 0.5, an emitter of 50 beside P = (4, 4), P's mean 0.65
    carried by ``sd``, the plain choice 0.45 at P, P's 3 x 3 sample maximum 100: the vote leaves it out) with the
    global default keeping P's mean, and candidate 3, OIDN + albedo + normal on the halves: ``rim_value`` at P,
    ``others`` (or the mean) elsewhere."""
    cands, raw, y, v, count, bounds, plain = emitter_rim._rim(0.65, sd)
    img = y.copy() if others is None else np.full(y.shape, others)
    img[4, 4] = rim_value
    cands.append(Candidate("oidn_aux_halves", img, np.full(y.shape, 0.02)))
    raw.append(cands[3].mse.mean(axis=2) / 0.26)
    return cands, raw, y, v, count, bounds, plain


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
    assert _prior(0.5, 0.65)[0][4, 4] != 3     # below the mean, above the plain choice (0.45)
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


_SD_ONE = 0.65                              # one sample among 32: standard error = the mean
_SD_NEAR = 0.99 * ONE_SAMPLE * 0.65         # just under ONE_SAMPLE times the mean: not one sample


@pytest.mark.parametrize("value, sds, expected", [
    ([0.3, 0.3, 0.3], [_SD_ONE] * 3, True),
    ([0.3, 0.3, 0.7], [_SD_ONE] * 3, False),               # one channel above the mean
    ([0.3, 0.3, 0.5], [_SD_ONE] * 3, False),               # one channel above the plain choice (0.45)
    ([0.3, 0.3, 0.3], [_SD_NEAR, _SD_NEAR, _SD_ONE], True),  # one channel carried by one sample is enough
    ([0.3, 0.3, 0.3], [_SD_NEAR] * 3, False),
    ([0.3, np.nan, 0.3], [_SD_ONE] * 3, False),            # NaN is not lower
])
def test_lowered_needs_one_sample_and_every_channel_lowered(value, sds, expected):
    cands, _, y, v, _, _, plain = _rim(0.3, 0.65)
    cands[3].image[4, 4] = value
    v[4, 4] = np.square(sds)
    where = np.zeros(y.shape[:2], bool)
    where[4, 4] = where[0, 0] = True     # (0, 0): many samples, the candidate at the mean
    got = _lowered(cands, 3, plain, y, v, where)
    assert got[4, 4] == expected and not got[0, 0] and not got[~where].any()


def test_the_rim_candidate_is_oidn_aux_on_the_halves_only_without_colour_only_oidn_on_all_the_samples():
    c = [Candidate(n, np.zeros((1, 1, 3)), np.zeros((1, 1, 3)))
         for n in ("box", "oidn_halves", "oidn_aux", "oidn_aux_halves")]
    assert rim_box(c) == 3 and _all_samples_box(c) is None
    c.append(Candidate("oidn", np.zeros((1, 1, 3)), np.zeros((1, 1, 3))))
    assert rim_box(c) is None and _all_samples_box(c) == 4
    assert rim_box(c[:3]) is None
