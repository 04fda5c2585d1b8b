"""ci's per-round shortcuts (issue 15): every plan asks for exactly what the full rule asks for.

The reference below is the plan as it was before the shortcuts: the
intervals of every pixel recomputed from the statistics at every round.
The method's plan keeps the widths of the last round and evaluates again
only the pixels whose samples changed (and their 3 x 3 neighbours, for the
borrowed variance), and skips the intervals while no pixel can have
converged; its requests and diagnostic maps must equal the reference's bit
for bit, sequential and pipelined, on a scene with zero-variance pixels
that borrow (hdr) and without.
"""

from __future__ import annotations

import numpy as np
import pytest

from mcrecon.adaptive.run import adapt
from mcrecon.methods import get_method
from mcrecon.methods.ci.method import CIMethod, borrow_neighbour_variance
from mcrecon.methods.base import uniform_counts
from mcrecon.renderers.scenes import SceneRenderer


def _reference_plan(method, st, state):
    """(need counts or None, diagnostics) of the full rule (the plan before the shortcuts)."""
    rule = method.rule
    n = st.count
    pending = state.pending if state.pending is not None else 0
    own_var = st.sample_variance(undefined=np.nan)
    var = own_var
    if method.params["zero_variance"] == "neighbours":
        var = borrow_neighbour_variance(own_var, n, st.mean)
    widths = rule.widths(st.mean, var, n)
    done = (np.all(widths <= 2.0 * rule.tolerance, axis=-1) & (n >= rule.min_spp)) | (n + pending >= rule.max_spp)
    ratio = np.max(widths, axis=-1) / (2.0 * rule.tolerance)
    finite = np.isfinite(ratio)
    ratio = np.where(finite, ratio, float(ratio[finite].max()) if finite.any() else 0.0)
    diag = {"spp": n.astype(np.float64), "converged": done.astype(np.float64), "width_ratio": ratio}
    if state.remaining <= 0 or done.all():
        return None, diag
    have = n + pending
    need = np.where(have < rule.min_spp, rule.min_spp - have, rule.step)
    need = np.where(done, 0, np.minimum(need, rule.max_spp - have)).astype(np.int64)
    if state.pending is not None:
        need[(n < rule.min_spp) & (have > n)] = 0  # pipelined: a pixel waits for its initial pass to be seen
        if not need.any():
            return "wait", diag
    if int(need.sum()) <= state.remaining:
        return need, diag
    if n.max() == 0:
        return uniform_counts(state.width, state.height, state.remaining, state.rng), diag
    if var is not own_var:
        ratio = np.max(rule.widths(st.mean, own_var, n), axis=-1) / (2.0 * rule.tolerance)
        ratio = np.where(np.isfinite(ratio), ratio, 0.0)
    key = np.where(n.ravel() < 2, np.inf, ratio.ravel())
    order = np.argsort(-key, kind="stable")
    flat_need = need.ravel()
    order = order[flat_need[order] > 0]
    cum = np.cumsum(flat_need[order])
    k = int(np.searchsorted(cum, state.remaining, side="right"))
    counts = np.zeros_like(flat_need)
    counts[order[:k]] = flat_need[order[:k]]
    left = state.remaining - (int(cum[k - 1]) if k else 0)
    if left > 0 and k < order.size:
        counts[order[k]] = left
    return counts.reshape(n.shape), diag


class _Checked(CIMethod):
    """ci that checks every plan against the reference (on a copy of the decision RNG)."""

    name = "ci"

    def plan(self, run, state):
        import copy

        ref_state = copy.copy(state)
        object.__setattr__(ref_state, "rng", copy.deepcopy(state.rng))
        req = super().plan(run, state)
        need, diag = _reference_plan(self, state.stats, ref_state)
        got = self.diagnostics(run)
        for name in ("spp", "converged", "width_ratio"):
            np.testing.assert_array_equal(got[name], diag[name], err_msg=f"round {state.round_index}: {name}")
        if need is None:
            assert req is None
        elif isinstance(need, str):
            assert req is not None and req.total == 0  # asks for nothing: waits for the round in flight
            run.waited += 1
        else:
            np.testing.assert_array_equal(req.counts, need, err_msg=f"round {state.round_index}")
        run.checked += 1
        c = run.cache
        if c is not None:  # what the cache held: partial updates, pixels that borrowed
            run.partial |= 0 < np.mean(state.stats.count != run.last_count) < 1 if run.last_count is not None else False
            run.last_count = state.stats.count.copy()
            run.borrowed |= c["zero"] is not None and bool(c["zero"].any())
        return req

    def start(self, *a, **kw):
        run = super().start(*a, **kw)
        run.checked, run.partial, run.borrowed, run.last_count, run.waited = 0, False, False, None, 0
        return run


@pytest.mark.parametrize("scene, spp, opts", [("hdr", 48, {"min_spp": 4, "step_spp": 4}),
                                              ("flat", 24, {"min_spp": 4, "step_spp": 2, "tolerance": 0.1}),
                                              ("soft_shadow", 40, {"tolerance": 0.02, "zero_variance": "stop"})])
@pytest.mark.parametrize("pipeline", [False, True])
def test_every_plan_equals_the_full_rule(scene, spp, opts, pipeline):
    m = _Checked(**opts)
    res = adapt(SceneRenderer(scene, width=40, height=28, seed=1), m, spp=spp, seed=3, pipeline=pipeline,
                track_error=False)
    assert res.run.checked >= 3 and len(res.rounds) >= 4
    assert res.run.partial  # some plan re-evaluated only part of the image
    assert res.run.borrowed == (scene == "hdr")  # black background pixels: zero variance, borrowed
    plain = adapt(SceneRenderer(scene, width=40, height=28, seed=1), get_method("ci", **opts), spp=spp, seed=3,
                  pipeline=pipeline, track_error=False)
    np.testing.assert_array_equal(plain.image, res.image)
