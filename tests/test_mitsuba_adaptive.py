"""Issue 7 must-show: adaptive runs on Mitsuba's Cornell box beat uniform box at equal spp.

Full size (MCRECON_FULL=1): 128x128, 32 spp average, reference 2048 spp.
CI: 64x64, 32 spp, reference 1024 spp.  The reference is the per-pixel mean
of jittered bridge samples with an independent seed (what the methods
estimate); its own relative MSE at 1024 spp is ~32x below box's at 32 spp,
so it does not decide the comparisons.
"""

import os
import warnings

import pytest

from mcrecon.driver import adapt
from mcrecon.methods import available_methods, get_method
from mcrecon.metrics import relative_mse
from mcrecon.mitsuba_bridge import MitsubaRenderer, mitsuba_available, render_reference

_OK, _REASON = mitsuba_available()
pytestmark = [pytest.mark.mitsuba, pytest.mark.slow,
              pytest.mark.skipif(not _OK, reason=f"Mitsuba bridge unavailable: {_REASON}")]

#: Measured, not tuned away (docs/methods/awr.md "Why AWR can lose"): the paper's AWR loses to
#: uniform box on the Cornell box even with the exact variance: soft thresholding (Eq. 11) spreads
#: the light's real rim variance into the dim ceiling beside it (per-pixel relative error 10-30),
#: and 64-sample level-0 pops chosen from 4-sample contrasts allocate worse than uniform.
#: 64^2: awr 0.0538 vs box 0.0101; 128^2: 0.0244 vs 0.0085.
KNOWN_LOSSES = {"awr": "paper's AWR loses to uniform box on the Cornell box's emitter rim "
                       "(thresholding, Eq. 11) and by its coarse pops; see docs/methods/awr.md"}

ADAPTIVE = [pytest.param(m, marks=pytest.mark.xfail(strict=True, reason=KNOWN_LOSSES[m]))
            if m in KNOWN_LOSSES else m
            for m in available_methods() if get_method(m).adaptive]


@pytest.fixture(scope="module")
def setup():
    full = os.environ.get("MCRECON_FULL", "") not in ("", "0")
    size = 128 if full else 64
    ref = render_reference(None, width=size, height=size, spp=2048 if full else 1024, seed=12345)
    renderer = MitsubaRenderer(None, width=size, height=size)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        box = adapt(renderer, "box", spp=32, seed=1, progress=False, track_error=False)
    return renderer, ref, relative_mse(box.image, ref)


@pytest.mark.parametrize("method", ADAPTIVE)
def test_adaptive_method_beats_uniform_box_on_cornell_box(setup, method):
    renderer, ref, box_err = setup
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = adapt(renderer, method, spp=32, seed=1, progress=False, track_error=False)
    assert res.stats.n_samples <= renderer.width * renderer.height * 32
    err = relative_mse(res.image, ref)
    print(f"{method}: relative MSE {err:.5g} vs uniform box {box_err:.5g}")
    assert err < box_err
