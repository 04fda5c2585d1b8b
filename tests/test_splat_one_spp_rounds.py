"""``splat``'s default on a log written one round per sample index (as Cycles' sample subsets are).

The outlier test judges a sample only once its 3x3 window holds
``MIN_POOL`` samples, and the progressive scheme never revisits a round: a
firefly in one of the first rounds of one sample per pixel used to stay in
its pixel whatever its brightness.  Offline, the default merges the leading
rounds into the first round of its own adaptive run (8 spp at 16) and
replays the later ones as they are.
"""

from __future__ import annotations

import numpy as np

import mcrecon
from mcrecon.core.samples import SampleSet
from mcrecon.methods.splat import ProgressiveSplatter, SplatMethod

W = 24
SPP = 32
FIREFLY = (11, 13)  # (row, column)


def _one_spp_rounds(seed: int = 3):
    """A dim noisy field (0.05 U[0, 2)) with 32 rounds of one sample per pixel; one sample of round 0
    worth 5000 (a firefly) in pixel FIREFLY.  Returns (SampleSet, index of the firefly)."""
    rng = np.random.default_rng(seed)
    ys, xs = np.mgrid[0:W, 0:W]
    pos, val, rnd = [], [], []
    for r in range(SPP):
        p = np.stack([xs.ravel() + rng.random(W * W), ys.ravel() + rng.random(W * W)], axis=1)
        v = 0.05 * 2 * rng.random(W * W)
        pos.append(p)
        val.append(v)
        rnd.append(np.full(W * W, r))
    k = FIREFLY[0] * W + FIREFLY[1]  # round 0's sample of that pixel
    val[0][k] = 5000.0
    v = np.concatenate(val)[:, None] * np.array([1.0, 0.9, 0.8])
    return SampleSet(np.concatenate(pos), v, width=W, height=W, rounds=np.concatenate(rnd)), k


def test_a_firefly_in_a_first_one_spp_round_is_spread():
    src, _ = _one_spp_rounds()
    img = mcrecon.reconstruct(src, method="splat")
    mean = src.values.reshape(SPP, W, W, 3).mean(axis=0)
    r, c = FIREFLY
    # the firefly adds 5000 / 32 = 156 to its pixel's mean; spread, its pixel keeps a small part of it
    assert mean[r, c, 0] > 150
    assert img[r, c, 0] < 0.5 * mean[r, c, 0]
    # energy is exact: what left the pixel landed around it
    np.testing.assert_allclose(img.sum(axis=(0, 1)), mean.sum(axis=(0, 1)), rtol=1e-9)
    ref = np.full((W, W, 3), 0.05) * np.array([1.0, 0.9, 0.8])
    err = lambda x: float((((x - ref) ** 2) / (ref ** 2 + 0.01)).mean())  # noqa: E731
    assert err(img) < 0.5 * err(mean)


def test_the_leading_one_spp_rounds_replay_as_the_first_round_of_the_methods_own_run():
    """The first group holds (N_0 + 1) // 2 spp of the source (N_0 = min(initial_spp, spp)); every later
    round is replayed as it is.  A source whose first round is that large already keeps its rounds."""
    src, _ = _one_spp_rounds()
    rounds = list(range(SPP))
    m = SplatMethod()
    assert m._replay_rounds(src, rounds) == [list(range(8))] + [[r] for r in range(8, SPP)]
    assert SplatMethod(initial_spp=4)._replay_rounds(src, rounds) == [[0, 1]] + [[r] for r in range(2, SPP)]
    assert SplatMethod(initial_spp=1)._replay_rounds(src, rounds) == [[r] for r in rounds]
    # an 8-spp source: N_0 = 8, a first round of 4 (the driver's split initial pass at that budget)
    short = SampleSet(src.positions[:8 * W * W], src.values[:8 * W * W], width=W, height=W,
                      rounds=np.repeat(np.arange(8), W * W))
    assert m._replay_rounds(short, list(range(8))) == [[0, 1, 2, 3], [4], [5], [6], [7]]
    # under one sample per pixel (N_0 = 0) every round replays as it is, with no empty round before them
    sparse = SampleSet(src.positions[:W * W // 2], src.values[:W * W // 2], width=W, height=W,
                       rounds=np.repeat(np.arange(4), W * W // 8))
    assert m._replay_rounds(sparse, list(range(4))) == [[0], [1], [2], [3]]
    # the replayed rounds: 25 of them, the first one judged (8 spp: 72 samples in a 3x3 window)
    run = m.start(W, W)
    m.reconstruct_run(run, mcrecon.methods.base.MethodInputs(stats=None, samples=src))
    sp: ProgressiveSplatter = run.splatter
    assert len(sp.rounds) == 25
    assert sp.rounds[0]["outliers"] >= 1
