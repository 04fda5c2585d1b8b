"""What many test files share: one way to run the command line and one jittered test renderer.

``tests/conftest.py`` imports this module and wraps :func:`run_cli` in the
``cli`` fixture; a test file imports from it by name (``from helpers import
run_cli``), as pytest puts ``tests/`` on the path.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

#: ``python -m mcrecon`` of this interpreter: the head of a command line for ``subprocess.Popen``.
MCRECON = (sys.executable, "-m", "mcrecon")


def run_cli(argv, capsys):
    """``mcrecon ARGV`` in this process: ``(exit code, stdout, stderr)``.

    An argument may be any object with a ``str`` (paths).  The parser's own
    refusals end in ``SystemExit``; its code is returned like any other, so a
    test reads one exit code whichever layer refused.
    """
    from mcrecon.cli import main

    try:
        code = main([str(a) for a in argv])
    except SystemExit as exc:
        code = exc.code
    out = capsys.readouterr()
    return code, out.out, out.err


def cli_env(extra_env=None) -> dict:
    """The environment of a child ``mcrecon``: this checkout first on ``PYTHONPATH``, then ``extra_env``."""
    path = os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p)
    return {**os.environ, "PYTHONPATH": path, **(extra_env or {})}


def run_cli_process(argv, *, extra_env=None, prelude=None, check=False, **kw) -> subprocess.CompletedProcess:
    """``python -m mcrecon ARGV`` as a child process, its output captured as text.

    A child process is what a test needs for an exit at the interpreter's
    end (signals, HDF5's clean-up, closed streams), for a process holding a
    log, or for the module entry point itself.  ``prelude``: Python source
    run in the child before the command line (to patch a module there).
    ``check``: assert the exit code is 0, showing stderr otherwise.  Other
    keywords go to :func:`subprocess.run` (``cwd``, ``timeout``).
    """
    argv = [str(a) for a in argv]
    if prelude is None:
        cmd = [*MCRECON, *argv]
    else:
        script = f"{prelude}\nimport sys\nfrom mcrecon.cli import run\nsys.argv[1:] = {argv!r}\nrun()"
        cmd = [sys.executable, "-c", script]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=cli_env(extra_env), **kw)
    if check:
        assert proc.returncode == 0, proc.stderr
    return proc


def request_positions(req, rng) -> np.ndarray:
    """The film positions a request asks for: its counts jittered within their pixels, then its positions.

    Jittered positions are drawn from ``rng`` first, so what a renderer
    draws from ``rng`` after them is the same whether or not the request
    also lists positions.
    """
    from mcrecon.core.requests import jittered_positions

    pos = jittered_positions(req.counts, rng) if req.counts is not None else np.zeros((0, 2))
    if req.positions is not None:
        pos = np.concatenate([pos, req.positions])
    return pos


def jittered_renderer(shade, *, width, height, name=None, stream=None):
    """An in-process renderer of jittered samples whose values ``shade(positions, rng, request)`` gives.

    Each request draws from ``rng = np.random.default_rng(stream(request))``
    (``stream=None``: the request's own seed): the positions of
    :func:`request_positions`, then whatever ``shade`` draws, so a run is a
    function of its seeds.  ``shade`` returns the values ``(N, C)`` as an
    array, or the whole reply as it is to be sent: a
    :class:`~mcrecon.core.requests.SampleBatch` with features, or a faulty
    reply of any kind.
    """
    from mcrecon.core.requests import SampleBatch
    from mcrecon.renderers import CallableRenderer

    def render(req):
        rng = np.random.default_rng(req.seed if stream is None else stream(req))
        pos = request_positions(req, rng)
        out = shade(pos, rng, req)
        return SampleBatch(pos, out) if isinstance(out, np.ndarray) else out

    return CallableRenderer(render, width=width, height=height, name=name)
