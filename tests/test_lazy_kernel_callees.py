"""Lazy numba kernels (mcrecon.core.samples.lazy_njit) that call other lazy kernels, and numba code that calls
a lazy kernel through its dispatcher."""

from __future__ import annotations

import numba

from mcrecon.core.samples import dispatcher, lazy_njit


@lazy_njit(inline="always")
def _twice(x):
    return 2 * x


@lazy_njit
def _twice_plus_one(x):
    return _twice(x) + 1


def test_a_lazy_kernel_calls_another_by_its_global_name():
    assert _twice_plus_one(3) == 7
    assert globals()["_twice"] is dispatcher(_twice)  # the callee's dispatcher now stands in its place


@lazy_njit
def _square(x):
    return x * x


def test_numba_code_calls_a_lazy_kernel_through_its_dispatcher():
    kernel = _square
    sq = dispatcher(kernel)
    assert dispatcher(sq) is sq  # a dispatcher already made is its own

    @numba.njit
    def square_plus_one(x):
        return sq(x) + 1

    assert square_plus_one(4) == 17
