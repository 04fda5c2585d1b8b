"""The first run compiles once per install: numba's cache, filled by a first run, serves every later one.

Each check runs fresh interpreters on an empty ``NUMBA_CACHE_DIR`` (a clean
install) and counts real compilations with numba's event API
(``numba:compile`` fires for a compilation, never for a load from the
cache): the second run must compile nothing.  benchmarks/bench_first_run.py
measures the seconds.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]

# Runs the code of argv[2] after a numba:compile listener; prints the compiled kernels as JSON on the last line.
_COUNTING = r"""
import json, sys
from numba.core import event as ev
compiled = []
class _L(ev.Listener):
    def on_start(self, event):
        pass
    def on_end(self, event):
        f = event.data["dispatcher"].py_func
        compiled.append(f.__module__ + "." + f.__qualname__)
ev.register("numba:compile", _L())
exec(sys.argv[1])
print(json.dumps(compiled))
"""


def _run(code: str, cache: Path) -> list[str]:
    """The kernels a fresh interpreter running ``code`` compiled, with numba's cache at ``cache``."""
    env = dict(os.environ)
    env["NUMBA_CACHE_DIR"] = str(cache)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT)] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
    r = subprocess.run([sys.executable, "-c", _COUNTING, code], capture_output=True, text=True, env=env, cwd=ROOT,
                       timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    return json.loads(r.stdout.strip().splitlines()[-1])


@pytest.mark.slow
def test_a_second_demo_compiles_nothing(tmp_path, full_run):
    """From a clean cache, the demo leaves every kernel the next demo runs in numba's cache: the first
    run compiles (the scenes' kernels, the pixel statistics' ``_accumulate``), the second loads them all.
    Reduced form (CI's, about 10 CPU s): box alone, one process.  MCRECON_FULL=1: every method, the last
    ones compiled by the second process (about 40 CPU s)."""
    methods = ", '--methods', 'box'" if not full_run else ""
    code = ("import mcrecon.cli.builtins as b\n"
            + ("b._two_process_split = lambda costs, shared: len(costs) - 1\n" if full_run else "")
            + "from mcrecon.cli import main\n"
            f"assert main(['demo', '--size', '24x20', '--spp', '2', '--out', {str(tmp_path / 'd')!r}{methods}]) == 0\n")
    first = _run(code, tmp_path / "cache")
    assert any(k.startswith("mcrecon.renderers.scenes") for k in first)
    assert "mcrecon.core.merge._accumulate" in first  # an empty cache: compiled
    assert _run(code, tmp_path / "cache") == []       # the same cache: loaded, nothing compiled


def test_two_process_split_balances_and_keeps_the_order():
    from mcrecon.cli.builtins import _two_process_split

    # this process takes the prefix, the second interpreter (1 s to start) the suffix
    assert _two_process_split([1, 1, 4, 8], shared=6) == 3      # max(6 + 6, 6 + 1 + 8) = 15 < 20
    assert _two_process_split([1, 1, 1, 1], shared=1) == 4      # 5 s in all: not worth a second process
    assert _two_process_split([10, 10], shared=0) == 1
    assert _two_process_split([20], shared=5) == 1               # one method: nothing to split


def test_demo_with_a_second_compiler_gives_the_same_images(tmp_path, monkeypatch, capsys):
    from mcrecon.cli import builtins, main
    from mcrecon.io import read_exr

    started = []
    real = builtins._warm_up_child

    def recording(*a):
        p = real(*a)
        started.append((a[2], p))
        return p

    args = ["demo", "--size", "24x20", "--spp", "2", "--methods", "box,gem,ci"]
    assert main(args + ["--out", str(tmp_path / "one")]) == 0
    monkeypatch.setattr(builtins, "_warm_up_child", recording)
    monkeypatch.setattr(builtins, "_two_process_split", lambda costs, shared: 1)  # gem and ci: the second one
    monkeypatch.setattr("mcrecon.cli._common.numba_cache_cold", lambda parts: True)  # as on a clean install
    assert main(args + ["--out", str(tmp_path / "two")]) == 0
    capsys.readouterr()
    assert len(started) == 1 and started[0][0] and started[0][1].returncode == 0  # it ran and finished
    for name in ("box", "gem", "ci"):
        a, _ = read_exr(tmp_path / "one" / f"soft_shadow_{name}.exr")
        b, _ = read_exr(tmp_path / "two" / f"soft_shadow_{name}.exr")
        assert np.array_equal(a, b)
