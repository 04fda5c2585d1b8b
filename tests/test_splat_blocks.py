"""The scatter of a large batch: fixed blocks on the thread pool, added in block order."""

import numpy as np

from mcrecon.methods.splat import kernels
from mcrecon.methods.splat.kernels import splat


def _batch(n=5000, seed=3):
    rng = np.random.default_rng(seed)
    pos = rng.uniform(0.0, 1.0, (n, 2)) * [24, 17]
    val = rng.exponential(1.0, (n, 3))
    widths = rng.uniform(0.5, 4.0, n)
    return pos, val, widths


def test_blocked_scatter_does_not_depend_on_threads_and_equals_one_loop_to_round_off(monkeypatch):
    pos, val, widths = _batch()
    one = splat(pos, val, widths, width=24, height=17)
    monkeypatch.setattr(kernels, "_PARALLEL_MIN", 1)
    got = []
    for t in ("1", "2"):
        monkeypatch.setenv("MCRECON_THREADS", t)
        got.append(splat(pos, val, widths, width=24, height=17))
    np.testing.assert_array_equal(got[0], got[1])
    # two partial sums added: the same energy, other rounding
    np.testing.assert_allclose(got[0], one, rtol=1e-12, atol=0)
    assert np.isclose(got[0].sum(), val.sum(), rtol=1e-12)  # mirror boundary keeps every sample's energy
