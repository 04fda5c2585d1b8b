"""The global prior reads each candidate's leave-one-out estimate where it needs it: never the (K, H, W) stack
of all of them (0.3 GB at 1920 x 1080 with auto's 19 candidates); the choice's bits are pinned (test_pinned_outputs)."""

from __future__ import annotations

import numpy as np

from mcrecon.methods.auto import selection
from mcrecon.methods.auto.features import Candidate


def _inputs(h=20, w=22, k=6, seed=2):
    rng = np.random.default_rng(seed)
    y = rng.uniform(0.4, 0.6, size=(h, w, 3))
    v = rng.uniform(0.005, 0.02, size=(h, w, 3))
    count = np.full((h, w), 16)
    cands = [Candidate("box", y.copy(), v.copy())]
    for j in range(1, k):
        img = y + rng.normal(0.0, 0.02 / j, size=y.shape)
        cands.append(Candidate(f"c{j}", img, v * rng.uniform(0.1, 1.0, size=y.shape) / j))
    cands[3].mse[2, 3, 1] = np.nan   # undefined at one pixel: that pixel does not vote
    raw = [c.mse.mean(axis=2) / 0.25 for c in cands]
    return cands, raw, y, v, count, (y - 0.2, y + 0.2)


def test_no_estimate_stack_of_every_candidate(monkeypatch):
    cands, raw, y, v, count, bounds = _inputs()
    real = selection._means
    shapes = []

    def recording(arrays, *a, **kw):
        out = real(arrays, *a, **kw)
        shapes.append(out.shape)
        return out

    monkeypatch.setattr(selection, "_means", recording)
    plain = np.zeros(y.shape[:2], np.int64)
    got, held = selection._global_prior(cands, raw.__getitem__, np.stack(raw), plain, y, v, count, bounds, 2.0, 3.0,
                                        3.0)
    assert shapes and all(s[0] == 1 for s in shapes)
    assert held.any()   # the prior applied: its default is not the pixel mean
