"""auto with a black box (OIDN) as the whole-image default beside a large emitter: the black box's light spread into
dark pixels whose samples all agree is not kept there (:func:`mcrecon.methods.auto.rim.own_interval`), though the
clamp's wide interval at a black box's pixels (the 5 x 5 neighbourhood's variance and range) holds it."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import mcrecon
from mcrecon.core.metrics import relative_mse
from mcrecon import SampleSet
from mcrecon.core.stats import PixelStats
from mcrecon.methods.auto import method as auto_method
from mcrecon.methods.auto.features import Candidate
from mcrecon.methods.auto.rim import OWN_LIFT, TAIL, Z_OWN, own_interval


def _emitter(h=32, w=32, n=32, seed=0):
    """A dark field (0.02; exponential samples, whose mean the black box beats, but within 1 % of it on the ring
    of pixels just outside the emitter) and an emitter (1000) on a 10 x 10 block whose rim pixels
    are half covered (each sample on it with probability 1/2); the samples, the truth and the ring."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w]
    inside = (yy >= 11) & (yy < 21) & (xx >= 11) & (xx < 21)
    rim = inside & ~((yy >= 12) & (yy < 20) & (xx >= 12) & (xx < 20))
    cover = np.where(rim, 0.5, inside.astype(float))
    truth = 0.02 + cover * 1000.0
    pix = np.repeat(np.arange(h * w), n)
    on = rng.random(pix.size) < cover.ravel()[pix]
    ring = ~inside & (yy >= 10) & (yy < 22) & (xx >= 10) & (xx < 22)
    dark = np.where(ring.ravel()[pix], 1 + 0.01 * rng.uniform(-1, 1, pix.size), rng.exponential(size=pix.size))
    vals = np.where(on, 1000.0, 0.02 * dark)
    pos = np.stack([pix % w, pix // w], 1) + rng.uniform(size=(pix.size, 2))
    ss = SampleSet(pos, np.repeat(vals[:, None], 3, axis=1), width=w, height=h)
    return ss, np.repeat(truth[..., None], 3, axis=2), ring


def test_a_black_box_default_does_not_spread_an_emitter_into_agreeing_dark_pixels(monkeypatch):
    """The black box is the truth but 5.0 on the ring (250 times its truth): without the rule the wide interval
    (thousands wide beside the rim) keeps 5.0 there and auto is hundreds of times the pixel mean's error; with
    it the ring keeps its means and auto stays below the pixel mean."""
    pytest.importorskip("pyoidn", reason="needs pyoidn (Intel OIDN), a dependency of mcrecon: pip install -e .")
    ss, ref, ring = _emitter()
    spread = np.where(ring[..., None], 5.0, ref)
    monkeypatch.setattr(auto_method, "oidn_candidate",
                        lambda name, *a, **kw: [Candidate(name, spread.copy(), np.zeros_like(ref))])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        img = np.asarray(mcrecon.reconstruct(ss, method="auto", candidates="box,oidn"))
    st = PixelStats.from_samples(ss.positions, ss.values, width=32, height=32)
    np.testing.assert_array_less(img[ring], 0.03)
    assert relative_mse(img, ref) < relative_mse(st.mean, ref)


def _case(lit=True):
    """One row: an emitter pixel whose samples agree (1000, sd 1: :data:`FOUND`) or one a single sample carries
    (1000, sd 1000), an agreeing dark pixel beside it (0.02), a noisy one (10, sd 5), one whose samples all read
    0, and an agreeing dark pixel 4 pixels from the emitter."""
    y = np.array([[[1000.0] * 3, [0.02] * 3, [10.0] * 3, [0.0] * 3, [0.02] * 3]])
    v = np.array([[[1.0 if lit else 1e6] * 3, [1e-8] * 3, [25.0] * 3, [0.0] * 3, [1e-8] * 3]])
    return y, v


@pytest.mark.parametrize("value, where, lit, kept", [
    (0.02 * (1 + OWN_LIFT) * 1.01, True, True, False),  # beyond its own interval, the lift, a lit neighbour: the mean
    (0.02 * (1 + OWN_LIFT) * 0.99, True, True, True),   # far outside its own interval, not lifted enough: kept
    (5.0, False, True, True),                          # not a pixel of ``where``: kept
    (5.0, True, False, True),                          # the bright neighbour's mean one sample carries: kept
    (1000.0 * TAIL * 1.01, True, True, True),          # lifted towards the neighbour's level (a light it missed): kept
    (1000.0 * TAIL * 0.99, True, True, False),         # a blur's tail of the neighbour's light: the mean
])
def test_own_interval_takes_the_mean_only_beyond_every_bound(value, where, lit, kept):
    y, v = _case(lit)
    img = y.copy()
    img[0, 1] = value
    img[0, 2] = 10.0 + 0.99 * Z_OWN * 5.0           # inside its own interval: kept
    img[0, 3] = 1.0                                 # samples all read 0: kept (they may have missed a caustic)
    img[0, 4] = 5.0                                 # no lit 3 x 3 neighbour: kept
    at = np.array([[True, where, True, True, True]])
    out = own_interval(img.copy(), y, v, at)
    np.testing.assert_array_equal(out[0, 1], img[0, 1] if kept else y[0, 1])
    np.testing.assert_array_equal(out[0, [0, 2, 3, 4]], img[0, [0, 2, 3, 4]])
