"""Shared test settings and fixtures.

``MCRECON_FULL=1`` runs the statistical tests marked ``slow`` at full size;
by default they run in a reduced form that keeps the whole suite within
CI's time.  The command-line runners and the jittered test renderer live in
``tests/helpers.py``; ``cli`` and ``cli_process`` are them as fixtures.
"""

import os

import numpy as np
import pytest

import helpers

FULL = os.environ.get("MCRECON_FULL", "") not in ("", "0")


@pytest.fixture
def full_run() -> bool:
    """True when the full-size statistical experiments are requested."""
    return FULL


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


@pytest.fixture
def cli(capsys):
    """``cli(argv)``: ``mcrecon ARGV`` in this process, ``(exit code, stdout, stderr)`` (:func:`helpers.run_cli`)."""
    return lambda argv: helpers.run_cli(argv, capsys)


@pytest.fixture
def cli_process():
    """``cli_process(argv, **kw)``: ``python -m mcrecon ARGV`` as a child process (:func:`helpers.run_cli_process`)."""
    return helpers.run_cli_process
