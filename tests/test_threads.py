"""One setting for worker threads: threads= / MCRECON_THREADS, for the filter pool and numba's loops."""

import numba
import numpy as np
import pytest

from mcrecon.filters.engine import n_threads, numba_threads
from mcrecon.errors import InputError


def test_setting_order_and_validation(monkeypatch):
    monkeypatch.setenv("MCRECON_THREADS", "3")
    assert n_threads() == 3 and n_threads(1) == 1
    monkeypatch.setenv("MCRECON_THREADS", "zero")
    with pytest.raises(InputError, match="MCRECON_THREADS"):
        n_threads()
    with pytest.raises(InputError, match="positive integer"):
        n_threads(0)
    monkeypatch.delenv("MCRECON_THREADS")
    assert n_threads() >= 1


def test_numba_loops_follow_the_setting_and_restore_it(monkeypatch):
    before = numba.get_num_threads()
    monkeypatch.setenv("MCRECON_THREADS", "1")
    with numba_threads() as n:
        assert n == 1 and numba.get_num_threads() == 1
    assert numba.get_num_threads() == before


def test_parallel_results_do_not_depend_on_the_thread_count(monkeypatch):
    from mcrecon.methods.ci.analysis import bootstrap_bias
    from mcrecon.methods.ci.method import StoppingRule
    rng = np.random.default_rng(0)
    pos = np.column_stack([np.repeat(np.arange(6) + 0.5, 40), np.full(240, 0.5)])
    val = rng.exponential(1.0, (240, 3))
    rule = StoppingRule(tolerance=0.05, min_spp=4, max_spp=40)
    # blocks of one pixel on the pool at this size (a small image otherwise stays on the calling thread)
    monkeypatch.setattr("mcrecon.filters.engine._PARALLEL_MIN", 0)
    monkeypatch.setattr("mcrecon.filters.engine.ROW_BLOCK", 1)
    out = []
    for t in ("1", "2"):
        monkeypatch.setenv("MCRECON_THREADS", t)
        res = bootstrap_bias(pos, val, width=6, height=1, B=64, seed=3, rule=rule)
        out.append(res.maps())
    for k in out[0]:
        np.testing.assert_array_equal(out[0][k], out[1][k])
