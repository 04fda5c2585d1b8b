"""auto's global prior at a firefly pixel: a default that keeps the pixel's own firefly does not hold it.

A pixel whose mean one rare huge sample carries (a glossy highlight's firefly) has a patch like no other,
so NL-means keeps its mean there; where the sample is 10-30x the mean the vote's own test (30x) does not
leave the pixel out, and on the corpus's glossy HDR scene that one pixel put auto at 1.40x its best single
candidate.  Such a pixel is judged as the pixels the vote leaves out: the default holds it only where its
value lies no farther than the per-pixel choice's from the median of the 8 neighbours' means.
"""

import numpy as np

from mcrecon.methods.auto.features import Candidate
from mcrecon.methods.auto.selection import HEAVY_TAIL, Z_FIREFLY, _firefly, _global_prior


def _firefly_brute(y, v, hi, scale=None):
    yr, vr = (y, v) if scale is None else (y / scale, v / scale ** 2)
    h, w, c = y.shape
    out = np.zeros((h, w), bool)
    for i in range(h):
        for j in range(w):
            for ch in range(c):
                # the 8 neighbours, edges repeated (the pixel's own index stands for a missing row/column)
                at = [(min(max(a, 0), h - 1), min(max(b, 0), w - 1))
                      for a in range(i - 1, i + 2) for b in range(j - 1, j + 2) if (a, b) != (i, j)]
                med = np.median([yr[p][ch] for p in at])
                sd = np.sqrt(np.median([vr[p][ch] for p in at]))
                if (yr[i, j, ch] > 0 and hi[i, j, ch] > HEAVY_TAIL * y[i, j, ch] and yr[i, j, ch] > HEAVY_TAIL * med
                        and yr[i, j, ch] - med > Z_FIREFLY * sd):
                    out[i, j] = True
    return out


def test_firefly_matches_its_definition_on_random_heavy_tailed_means():
    rng = np.random.default_rng(3)
    h, w = 13, 11
    y = rng.exponential(1.0, (h, w, 3)) ** 3          # heavy-tailed means: some pixels 10x their neighbours
    hi = y * rng.choice([2.0, 40.0], size=(h, w, 3))   # the 3 x 3 maximum: near the mean or far above it
    v = (y * rng.uniform(0.0, 0.5, (h, w, 3))) ** 2   # some neighbourhoods too noisy for a 10-sigma excess
    scale = rng.uniform(0.05, 1.0, (h, w, 3))
    for sc in (None, scale):
        got, want = _firefly(y, v, hi, sc), _firefly_brute(y, v, hi, sc)
        assert want.any() and not want.all()
        np.testing.assert_array_equal(got, want)


def _scene(g_value, hi_factor):
    """A flat 0.5 field; P = (4, 4) caught one huge sample: mean 6.75, standard error 5.7.

    Candidates: 0 the mean, 1 the plain choice at P (2.3 there), 2 the global default (``g_value`` at P,
    least estimate everywhere); P's 3 x 3 sample maximum is ``hi_factor`` times its mean."""
    y = np.full((10, 10, 3), 0.5)
    y[4, 4] = 6.75
    v = np.where(y > 1.0, 5.7 ** 2, 0.01)
    # the images: the mean, then the plain choice and the default, which differ from it at P only
    images = [y.copy()]
    for at_p in (2.3, g_value):
        images.append(y.copy())
        images[-1][4, 4] = at_p
    cands = [Candidate(n, x, np.full(y.shape, m)) for n, x, m in zip(("box", "gauss1", "nlm"), images,
                                                                        (0.0, 0.004, 0.001))]
    cands[0] = Candidate("box", y.copy(), v.copy())
    raw = [c.mse.mean(axis=2) / 0.26 for c in cands]
    hi = y * 3.0
    hi[4, 4] = hi_factor * 6.75
    plain = np.zeros((10, 10), np.int64)
    plain[4, 4] = 1
    return cands, raw, y, v, (y * 0.2, hi), plain


def _prior(g_value, hi_factor):
    cands, raw, y, v, bounds, plain = _scene(g_value, hi_factor)
    count = np.full(y.shape[:2], 32)
    got, _ = _global_prior(cands, raw.__getitem__, np.stack(raw), plain, y, v, count, bounds, 2.0, 3.0, 4.0)
    return got


def test_a_default_that_keeps_the_pixels_firefly_gives_it_to_the_plain_choice():
    # 27x: under the vote's 30x, so the vote counted P and the default held it with its firefly
    got = _prior(6.75, 27.0)
    assert got[4, 4] == 1
    assert (np.delete(got.ravel(), 4 * 10 + 4) == 2).all()   # every other pixel keeps the default


def test_the_default_keeps_a_firefly_pixel_it_brings_nearer_the_neighbours_and_one_without_a_huge_sample():
    assert _prior(0.6, 27.0)[4, 4] == 2    # the default removes the firefly: nearer the neighbours' median
    assert _prior(6.75, 5.0)[4, 4] == 2    # no sample 10x the mean around: not a firefly
