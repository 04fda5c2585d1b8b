"""auto's global prior at an emitter's rim: a pixel whose mean one rare sample carries is not lifted further.

At the rim of a small bright emitter a pixel that caught one emitter sample in 32 has a mean far above its
truth, and half of its 8 neighbours lie on the emitter, so their median lies far above it too.  The global
default (NL-means on a scene where it wins the summed estimate) lifts such a pixel towards the emitter; the
"nearer the neighbours' median" test alone lets it, and on the corpus's HDR scene that one rim pixel put
auto above the pixel mean.
"""

import numpy as np

from mcrecon.methods.auto.features import Candidate
from mcrecon.methods.auto.selection import ONE_SAMPLE, _global_prior, _lifted


def _rim(g_value, sd):
    """A flat 0.5 field, an emitter (50) on the four pixels above and left of P = (4, 4), and P's mean 0.65.

    Candidates: 0 the mean, 1 the plain choice at P (0.45 there), 2 the global default (``g_value`` at P,
    least estimate everywhere); P's 3 x 3 sample maximum is 100 (rare huge samples around)."""
    h, w = 10, 10
    y = np.full((h, w, 3), 0.5)
    emitter = [(3, 3), (3, 4), (3, 5), (4, 3)]
    for p in emitter:
        y[p] = 50.0
    y[4, 4] = 0.65
    v = np.full((h, w, 3), 0.01)
    v[4, 4] = sd ** 2
    count = np.full((h, w), 32)
    plain_img = y.copy()
    plain_img[4, 4] = 0.45
    g_img = y.copy()
    g_img[4, 4] = g_value
    cands = [Candidate("box", y.copy(), v.copy()),
             Candidate("gauss1", plain_img, np.full((h, w, 3), 0.004)),
             Candidate("nlm", g_img, np.full((h, w, 3), 0.001))]
    raw = [c.mse.mean(axis=2) / 0.26 for c in cands]
    hi = y.copy()
    hi[4, 4] = 100.0
    plain = np.zeros((h, w), np.int64)
    plain[4, 4] = 1
    return cands, raw, y, v, count, (y.copy(), hi), plain


def _prior(g_value, sd):
    cands, raw, y, v, count, bounds, plain = _rim(g_value, sd)
    got, _ = _global_prior(cands, raw.__getitem__, np.stack(raw), plain, y, v, count, bounds, 2.0, 3.0, 4.0)
    return got[4, 4]


def test_a_rim_pixel_carried_by_one_sample_keeps_the_plain_choice_when_the_default_would_lift_it():
    # the default's 0.9 lies nearer the neighbours' median (25.25) than the plain 0.45: without the
    # lift test the pixel took it
    assert _prior(0.9, 0.65) == 1


def test_the_default_still_takes_a_rim_pixel_it_lowers_or_one_whose_mean_many_samples_carry():
    assert _prior(0.6, 0.65) == 2      # lowered towards the plain choice: nearer, no lift
    assert _prior(0.9, 0.1) == 2       # lifted, but many samples carry the mean (a light its samples missed)


def test_lifted_compares_every_channel_with_the_mean_and_the_plain_choice():
    cands, _, y, v, _, _, plain = _rim(0.9, 0.65)
    where = np.zeros(y.shape[:2], bool)
    where[4, 4] = where[0, 0] = True
    got = _lifted(cands, 2, plain, y, v, where)
    assert got[4, 4] and not got[0, 0] and got.sum() == 1
    # one channel lifted is enough; a standard error just under ONE_SAMPLE times the mean is not one sample
    cands[2].image[4, 4] = [0.65, 0.65, 0.9]
    assert _lifted(cands, 2, plain, y, v, where)[4, 4]
    v[4, 4] = (0.99 * ONE_SAMPLE * 0.65) ** 2
    assert not _lifted(cands, 2, plain, y, v, where)[4, 4]
    # a pixel whose samples are all 0 (mean and standard error 0) is carried by none: a caustic's light
    # its samples missed may lift it
    y[4, 4], v[4, 4] = 0.0, 0.0
    assert not _lifted(cands, 2, plain, y, v, where)[4, 4]
