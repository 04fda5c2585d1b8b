"""The README's plain ``python -m pytest`` runs the suite on one xdist worker per CPU of this process.

``tests/conftest.py`` sets the worker count before xdist reads it, from the CPUs this process may use
(its affinity: a container's share, not the machine's count), and leaves a command line that chose
(``-n``, ``--dist``) or needs one process (``--pdb``, ``-s``) as it is.
"""

from __future__ import annotations

import os
from types import SimpleNamespace

import pytest

import conftest


def _config(*, xdist=True, **options):
    opt = dict(numprocesses=None, dist="no", tx=[], usepdb=False, trace=False, capture="fd", collectonly=False)
    opt.update(options)
    return SimpleNamespace(option=SimpleNamespace(**opt),
                           pluginmanager=SimpleNamespace(hasplugin=lambda name: xdist and name == "xdist"))


@pytest.fixture
def controller(monkeypatch):
    """As in the process pytest starts (an xdist worker leaves the count to its controller)."""
    monkeypatch.delenv("PYTEST_XDIST_WORKER", raising=False)


def test_one_worker_per_cpu_of_this_process(controller, monkeypatch):
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 3, 5}, raising=False)
    config = _config()
    conftest.pytest_cmdline_main(config)
    assert (config.option.numprocesses, config.option.dist) == (3, "load")


def test_one_cpu_runs_in_one_process(controller, monkeypatch):
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {2}, raising=False)
    config = _config()
    conftest.pytest_cmdline_main(config)
    assert (config.option.numprocesses, config.option.dist) == (None, "no")


@pytest.mark.parametrize("options", [dict(numprocesses=0), dict(numprocesses=4), dict(dist="loadfile"),
                                     dict(usepdb=True), dict(trace=True), dict(capture="no"),
                                     dict(collectonly=True)])
def test_a_command_line_that_chose_or_needs_one_process_is_left_alone(options, controller, monkeypatch):
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1}, raising=False)
    config = _config(**options)
    before = dict(vars(config.option))
    conftest.pytest_cmdline_main(config)
    assert vars(config.option) == before


def test_without_xdist_or_inside_a_worker_nothing_changes(monkeypatch):
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1}, raising=False)
    monkeypatch.delenv("PYTEST_XDIST_WORKER", raising=False)
    config = _config(xdist=False)
    conftest.pytest_cmdline_main(config)
    assert config.option.numprocesses is None
    monkeypatch.setenv("PYTEST_XDIST_WORKER", "gw0")
    config = _config()
    conftest.pytest_cmdline_main(config)
    assert config.option.numprocesses is None
