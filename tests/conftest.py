"""Shared test settings.

``MCRECON_FULL=1`` runs the statistical tests marked ``slow`` at full size
(the numbers quoted in issue notes); by default they run in a reduced form
that keeps the whole suite within CI's time.
"""

import os

import numpy as np
import pytest

FULL = os.environ.get("MCRECON_FULL", "") not in ("", "0")


@pytest.fixture
def full_run() -> bool:
    """True when the full-size statistical experiments are requested."""
    return FULL


@pytest.fixture
def rng():
    return np.random.default_rng(12345)
