"""What many test files share: one way to run the command line, one jittered test renderer and a built-in
scene that records its requests.

``tests/conftest.py`` imports this module and wraps :func:`run_cli` in the
``cli`` fixture; a test file imports from it by name (``from helpers import
run_cli``), as pytest puts ``tests/`` on the path.
"""

from __future__ import annotations

import json
import os
import select
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np

from mcrecon import SampleSet
from mcrecon.renderers.scenes import SceneRenderer

ROOT = Path(__file__).resolve().parents[1]

#: ``python -m mcrecon`` of this interpreter: the head of a command line for ``subprocess.Popen``.
MCRECON = (sys.executable, "-m", "mcrecon")


def run_cli(argv, capsys=None):
    """``mcrecon ARGV`` in this process: ``(exit code, stdout, stderr)``.

    An argument may be any object with a ``str`` (paths).  The parser's own
    refusals end in ``SystemExit``; its code is returned like any other, so a
    test reads one exit code whichever layer refused.  Without ``capsys`` (a
    module-scoped fixture has none) the output is left to pytest's capture
    and both texts are empty.
    """
    from mcrecon.cli import main

    try:
        code = main([str(a) for a in argv])
    except SystemExit as exc:
        code = exc.code
    if capsys is None:
        return code, "", ""
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


#: One CLI command per line of stdin (a JSON list), its exit code and stderr per line of stdout; an address-space
#: limit (bytes, formatted in) turns an allocation bomb into a failure instead of the test run's death.
_WORKER = textwrap.dedent("""
    import contextlib, io, json, resource, sys, traceback
    limit = {limit}
    if limit:
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    from mcrecon.cli import main
    for line in sys.stdin:
        argv = json.loads(line)
        out, err = io.StringIO(), io.StringIO()
        try:
            with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
                code = main(argv)
        except SystemExit as exc:
            code = exc.code
        except BaseException:
            code = "traceback"
            err.write(traceback.format_exc())
        print(json.dumps({{"code": code, "err": err.getvalue()}}), flush=True)
""")


class CliWorker:
    """A persistent ``mcrecon`` process running one CLI command per request (no start-up per command), so
    a crash of a library shows as a failure (``"crash"``) and a hang as ``"hang"`` instead of killing the run.

    ``memory_limit``: bytes of address space the worker may map (0: no limit)."""

    def __init__(self, *, memory_limit: int = 0, timeout: float = 60.0):
        self.script = _WORKER.format(limit=int(memory_limit))
        self.timeout = timeout
        self.proc = None

    def run(self, argv, timeout: float | None = None) -> dict:
        """``{"code": exit code | "traceback" | "hang" | "crash", "err": stderr}`` of one command."""
        if self.proc is None or self.proc.poll() is not None:
            self.proc = subprocess.Popen([sys.executable, "-c", self.script], stdin=subprocess.PIPE,
                                         stdout=subprocess.PIPE, text=True, env=cli_env())
        self.proc.stdin.write(json.dumps([str(a) for a in argv]) + "\n")
        self.proc.stdin.flush()
        wait = self.timeout if timeout is None else timeout
        ready, _, _ = select.select([self.proc.stdout], [], [], wait)
        if not ready:
            self.close()
            return {"code": "hang", "err": f"no answer within {wait} s"}
        line = self.proc.stdout.readline()
        if not line:
            code = self.proc.wait()
            self.proc = None
            return {"code": "crash", "err": f"the worker died (status {code})"}
        return json.loads(line)

    def close(self):
        if self.proc is not None:
            self.proc.kill()
            self.proc.wait()
            self.proc.stdin.close()
            self.proc.stdout.close()
            self.proc = None


class RecordingScene(SceneRenderer):
    """A built-in scene that keeps every request it answers (``seen``)."""

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.seen = []

    def render(self, request):
        self.seen.append(request)
        return super().render(request)


def feature_samples(n, seed, *, width, height):
    """``(positions, values, features)`` of ``n`` random samples on a ``width`` x ``height`` film: gamma
    values and an albedo, normal and depth per sample, drawn in that order from ``seed``."""
    rng = np.random.default_rng(seed)
    pos = rng.uniform(0, [width, height], size=(n, 2))
    val = rng.gamma(2.0, 1.0, size=(n, 3))
    feats = {"albedo": rng.uniform(0, 1, size=(n, 3)), "normal": rng.normal(size=(n, 3)),
             "depth": rng.exponential(4.0, size=n)}
    return pos, val, feats


def spotlit_checker(h=48, w=48, n=32, p=1 / 60, seed=0):
    """A 4-pixel checker whose samples are the truth times (1 + B / p) / 2, B ~ Bernoulli(p): most samples
    miss the light that carries half of every pixel's value."""
    rng = np.random.default_rng(seed)
    pix = np.repeat(np.arange(h * w), n)
    pos = np.stack([pix % w, pix // w], 1) + rng.uniform(size=(pix.size, 2))
    yy, xx = np.mgrid[0:h, 0:w]
    truth = np.where(((yy // 4) + (xx // 4)) % 2 == 0, 0.5, 2.0)
    vals = truth.ravel()[pix][:, None] * (1.0 + (rng.random((pix.size, 1)) < p) / p) / 2
    ss = SampleSet(pos, np.repeat(vals, 3, axis=1), width=w, height=h)
    return ss, np.repeat(truth[..., None], 3, axis=2)


def checker_wall_halves(n, seed, spp=8):
    """The built-in checker_wall at n x n with its features, split into the two half buffers."""
    from mcrecon.core.halves import split_halves
    from mcrecon.renderers import scenes

    b = scenes.render_uniform("checker_wall", width=n, height=n, spp=spp, seed=seed, features=True)
    ss = SampleSet(b.positions, b.values, width=n, height=n, features=b.features)
    return split_halves(ss, features=tuple(ss.features))


def share_references(root) -> None:
    """Built-in scenes' reference images computed once for every process of a test run, through ``root``.

    Wraps ``mcrecon.renderers.scenes._averaged`` (what the per-process cache ``_reference_cached`` calls)
    for the registered built-in scenes only: the key is the scene's name, parameters, size, quadrature and
    whether features are asked for, so a user's own Scene subclass is computed as before.  A lock file per
    key lets one process compute while the others wait and then read its ``.npy`` (the same bits).
    """
    import fcntl
    import hashlib

    import mcrecon.renderers.scenes as S

    inner = S._averaged

    def averaged(sc, width, height, quadrature, features):
        if S.SCENES.get(sc.name) is not type(sc):
            return inner(sc, width, height, quadrature, features)
        key = hashlib.sha1(repr((sc.name, sc.param_key, width, height, quadrature, bool(features)))
                           .encode()).hexdigest()[:20]
        path = Path(root) / f"{key}.npy"
        with open(Path(root) / f"{key}.lock", "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            if path.exists():
                return np.load(path)
            out = inner(sc, width, height, quadrature, features)
            tmp = path.with_suffix(f".{os.getpid()}.tmp.npy")
            np.save(tmp, out)
            os.replace(tmp, path)
            return out

    S._averaged = averaged
