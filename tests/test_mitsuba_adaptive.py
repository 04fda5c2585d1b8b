"""Issue 7 must-show: adaptive runs on Mitsuba's Cornell box beat uniform box at equal spp.

Full size (MCRECON_FULL=1): 128x128, 32 spp average, reference 2048 spp.
CI: 64x64, 32 spp, reference 1024 spp.  The reference is the per-pixel mean
of jittered bridge samples with an independent seed (what the methods
estimate); its own relative MSE at 1024 spp is ~32x below box's at 32 spp,
so it does not decide the comparisons.
"""

import os
import warnings

import numpy as np
import pytest

from mcrecon.adaptive.run import adapt
from mcrecon.methods import available_methods, get_method
from mcrecon.core.metrics import relative_mse
from mcrecon.renderers.mitsuba import MitsubaRenderer, mitsuba_available, render_reference

_OK, _REASON = mitsuba_available()
pytestmark = [pytest.mark.mitsuba, pytest.mark.slow,
              pytest.mark.skipif(not _OK, reason=f"Mitsuba bridge unavailable: {_REASON}")]

#: Measured limits are rows of ``benchmarks/bench_mitsuba_adaptive.py`` and sentences in the
#: method's docs, never strict xfails (a test must not fail because a method got better).  The
#: paper's AWR loses to uniform box on the Cornell box (64^2: 0.0538 vs 0.0101; 128^2: 0.0244 vs
#: 0.0085; docs/methods/awr.md); the defaults here are the robust variants, and none loses today
#: (robust AWR 64^2: 0.0048 vs 0.0101).
MEASURED_LOSSES: set[str] = set()

ADAPTIVE = [m for m in available_methods() if get_method(m).adaptive]


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
    assert np.isfinite(res.image).all()
    err = relative_mse(res.image, ref)
    print(f"{method}: relative MSE {err:.5g} vs uniform box {box_err:.5g}")
    if method not in MEASURED_LOSSES:
        assert err < box_err
