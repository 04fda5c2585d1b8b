"""auto keeps an OIDN candidate's value where OIDN is the global default, outside the safeguard's bounds.

The safeguard (the clamp into ``y +- k sd`` and the 3 x 3 sample range, and the heavy-tail rule) caps
what OIDN can give: light OIDN spreads correctly onto pixels none of whose samples saw it lies outside
both bounds.  Where OIDN holds the global default its summed estimate beat every plain candidate's by
``Z_BLACKBOX`` standard errors; there its value stands.
"""

import numpy as np

import mcrecon
from mcrecon.core.fill import mean_variance_policy
from mcrecon.core.stats import PixelStats
from mcrecon.methods.auto.features import Candidate
from mcrecon.methods.auto.method import AutoRun


def _flat(h=16, w=16, spp=16):
    """Every pixel: 8 samples at 0.45 and 8 at 0.55 (mean 0.5, the same variance everywhere)."""
    pix = np.repeat(np.arange(h * w), spp)
    pos = np.stack([pix % w + 0.5, pix // w + 0.5], axis=1)
    vals = np.where(np.arange(pix.size) % 2 == 0, 0.45, 0.55)[:, None].repeat(3, axis=1)
    return PixelStats.from_samples(pos, vals, width=w, height=h)


def _select(name, x):
    """auto's selection on the flat field with candidates box, a Gaussian and ``name`` (least estimate
    everywhere: the global default) whose value at (8, 8) is ``x``."""
    st = _flat()
    y, count = st.mean, st.count
    v = mean_variance_policy(st)
    img = np.full_like(y, 0.5)
    img[8, 8] = x
    cands = [Candidate("box", y.copy(), v.copy()), Candidate("gauss2", np.full_like(y, 0.5), v / 8),
             Candidate(name, img, np.full_like(y, 1e-8))]
    m = mcrecon.get_method("auto")
    m.__dict__["_candidates"] = lambda *a: (cands, y, v, count)
    run = AutoRun(y.shape[1], y.shape[0], 3)
    out, _ = m._select(run, st, None)
    return out[8, 8], run.candidate_names[int(run.diagnostics["choice"][8, 8])], float(np.sqrt(v[8, 8, 0]))


def test_an_oidn_default_keeps_its_value_beyond_the_sample_range_and_4_standard_errors():
    sd = _select("oidn", 0.5)[2]
    x = 0.5 + 4.5 * sd            # above the samples' 0.55 and 4 sd, within the 5 sd of the bias test
    assert x > 0.55 and x > 0.5 + 4 * sd
    got, chosen, _ = _select("oidn", x)
    assert chosen == "oidn"
    np.testing.assert_allclose(got, x)


def test_any_other_default_is_still_clamped_there():
    sd = _select("nlm", 0.5)[2]
    got, chosen, _ = _select("nlm", 0.5 + 4.5 * sd)
    assert chosen == "nlm"
    assert (got <= 0.55 + 1e-12).all()
