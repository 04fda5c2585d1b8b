"""Shared test settings and fixtures.

``MCRECON_FULL=1`` runs the statistical tests marked ``slow`` at full size;
by default they run in a reduced form that keeps the whole suite within
CI's time.  The command-line runners and the jittered test renderer live in
``tests/helpers.py``; ``cli`` and ``cli_process`` are them as fixtures.

The suite runs on every CPU this process may use when pytest-xdist (the
``test`` extra) is installed: one worker per CPU, so the README's plain
``python -m pytest -q -rs`` is the parallel run.  ``-n 0`` (or ``-p
no:xdist``, or a venv without xdist) runs it in one process; ``--pdb``,
``--trace``, ``-s`` and ``--collect-only`` do too, as they need one.  Each
worker builds the module-scoped fixtures of the modules it runs tests of
(a Dask cluster, a browser, compiled C tools) in its own temporary
directory: no test shares a file, a port or a working directory with the
other worker's.  xdist's ``loadgroup`` (one worker per group) is not used:
with pytest 9 its groups are silently ignored (xdist 3.8 renames a test
through ``Item._nodeid``, which pytest 9 no longer reads).
"""

import os

import numpy as np
import pytest

import helpers

FULL = os.environ.get("MCRECON_FULL", "") not in ("", "0")


def _cpus() -> int:
    """The CPUs this process may run on (its affinity, not the machine's count: a container's share)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # no affinity API (macOS)
        return os.cpu_count() or 1


@pytest.hookimpl(tryfirst=True)
def pytest_cmdline_main(config):
    """One xdist worker per CPU unless the command line chose (``-n``, ``--dist``) or needs one process.

    Runs before xdist's own hook, which turns ``numprocesses`` into workers.
    """
    opt = config.option
    if not config.pluginmanager.hasplugin("xdist") or os.environ.get("PYTEST_XDIST_WORKER"):
        return
    if opt.numprocesses is not None or opt.dist != "no" or opt.tx:
        return
    if opt.usepdb or opt.trace or opt.capture == "no" or opt.collectonly:
        return
    workers = _cpus()
    if workers > 1:
        opt.numprocesses, opt.dist = workers, "load"


#: Where the xdist workers of one run share the built-in scenes' reference images (set by the controller).
_REFERENCES_ENV = "MCRECON_TEST_SHARED_REFERENCES"


def pytest_configure(config):
    """With xdist, the workers share each built-in scene's reference image through one temporary directory.

    A 128^2 reference takes a few CPU seconds (32^2 quadrature points a pixel) and both workers need
    most of the same ones; each process keeps its own in memory (``scenes._reference_cached``), so
    without this every reference is computed once a worker.  The first worker to need a reference
    computes it under a lock file and writes it; the other reads it (the same bits: ``np.save``).
    """
    worker = os.environ.get("PYTEST_XDIST_WORKER")
    if not worker:
        if getattr(config.option, "numprocesses", None) and not os.environ.get(_REFERENCES_ENV):
            import tempfile

            config._shared_references = tempfile.mkdtemp(prefix="mcrecon-test-references-")
            os.environ[_REFERENCES_ENV] = config._shared_references
        return
    root = os.environ.get(_REFERENCES_ENV)
    if root and os.path.isdir(root):
        helpers.share_references(root)


def pytest_unconfigure(config):
    root = getattr(config, "_shared_references", None)
    if root:
        import shutil

        shutil.rmtree(root, ignore_errors=True)
        os.environ.pop(_REFERENCES_ENV, None)


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
