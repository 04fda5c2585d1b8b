"""Start-up: ``import mcrecon``, ``mcrecon --help`` and ``mcrecon info`` load only what they use.

Module-set assertions (what a fresh interpreter imported, from
``-X importtime``), never wall-time ones: benchmarks/bench_startup.py
measures the time.
"""

from __future__ import annotations

import io
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]

#: Never imported by `import mcrecon`, `mcrecon --help` or `mcrecon info`.
HEAVY = ("scipy", "numba", "llvmlite", "skimage", "matplotlib", "pywt", "dask", "distributed", "mitsuba", "drjit")


def _imported(*args) -> tuple[set[str], subprocess.CompletedProcess]:
    """Top-level packages a fresh ``python -X importtime ARGS`` imported, and the finished process."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT)] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
    r = subprocess.run([sys.executable, "-X", "importtime", *map(str, args)], capture_output=True, text=True,
                       env=env, cwd=ROOT, timeout=300)
    mods = {line.rsplit("|", 1)[1].strip().split(".")[0] for line in r.stderr.splitlines()
            if line.startswith("import time:") and "|" in line}
    mods.discard("package")  # the header line
    return mods, r


@pytest.fixture(scope="module")
def tiny_log(tmp_path_factory):
    from mcrecon.io import write_log

    path = tmp_path_factory.mktemp("startup") / "tiny.h5"
    rng = np.random.default_rng(0)
    pos = rng.random((6 * 5 * 3, 2)) * [6, 5]
    write_log(path, pos, rng.random((90, 3)), width=6, height=5)
    return path


def test_import_mcrecon_loads_no_heavy_package():
    mods, r = _imported("-c", "import mcrecon")
    assert r.returncode == 0, r.stderr[-2000:]
    assert not mods & set(HEAVY + ("numpy", "h5py")), sorted(mods & set(HEAVY + ("numpy", "h5py")))


def test_help_loads_no_heavy_package_nor_any_method():
    mods, r = _imported("-m", "mcrecon", "--help")
    assert r.returncode == 0, r.stderr[-2000:]
    assert "denoise" in r.stdout and "info" in r.stdout and "batch" in r.stdout
    assert not mods & set(HEAVY + ("numpy", "h5py")), sorted(mods & set(HEAVY + ("numpy", "h5py")))
    loaded = {line.rsplit("|", 1)[1].strip() for line in r.stderr.splitlines() if "| " in line}
    assert not {m for m in loaded if m.startswith("mcrecon.methods")}, "the method classes were imported"


def test_info_loads_no_heavy_package(tiny_log):
    mods, r = _imported("-m", "mcrecon", "info", tiny_log)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "samples                  90" in r.stdout
    assert not mods & set(HEAVY), sorted(mods & set(HEAVY))


def test_denoise_help_still_lists_the_method_flags():
    from mcrecon.cli import main

    out = io.StringIO()
    old, sys.stdout = sys.stdout, out
    try:
        with pytest.raises(SystemExit) as exc:
            main(["denoise", "--help"])
    finally:
        sys.stdout = old
    assert exc.value.code == 0
    text = out.getvalue()
    assert "gem options" in text and "--gamma" in text and "--method NAME" in text


def test_only_the_chosen_command_gets_method_flags():
    from mcrecon.cli import build_parser

    def flags_of(parser, name):
        sub = parser._subparsers._group_actions[0].choices[name]
        return set(sub._option_string_actions)

    light = build_parser("info")
    assert "--gamma" not in flags_of(light, "denoise") and "--method" not in flags_of(light, "batch")
    assert "--json" in flags_of(light, "info")
    full = build_parser()
    for name in ("denoise", "adapt", "batch"):
        assert {"--method", "--gamma"} <= flags_of(full, name), name
    assert flags_of(light, "bias") < flags_of(full, "bias")  # method ci's flags: with bias only
    assert flags_of(build_parser("denoise"), "denoise") == flags_of(full, "denoise")


def test_every_public_name_resolves():
    import mcrecon

    for name in mcrecon.__all__:
        assert getattr(mcrecon, name) is not None, name
    assert set(mcrecon.__all__) <= set(dir(mcrecon))
    assert mcrecon.reconstruct.__module__ == "mcrecon.offline.reconstruction"
    assert mcrecon.write_log.__module__ == "mcrecon.io.writer"
    assert callable(mcrecon.adapt) and isinstance(mcrecon.__version__, str)
    # sub-modules as attributes, as before the names were lazy
    assert mcrecon.io.reader.read_log is mcrecon.read_log
    assert callable(mcrecon.adaptive.run.resume) and callable(mcrecon.restoration.gem)
    with pytest.raises(AttributeError):
        mcrecon.no_such_name  # noqa: B018
    from mcrecon.methods.ci import analysis
    from mcrecon import io as mio

    for mod in (mio, analysis):
        for name in mod.__all__:
            assert getattr(mod, name) is not None, (mod.__name__, name)
        assert set(mod.__all__) <= set(dir(mod))
        with pytest.raises(AttributeError):
            mod.no_such_name  # noqa: B018


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_numpy_screen_equals_the_kernel(dtype):
    """Small batches are checked in NumPy (no numba at start-up): the same counts as the kernel."""
    from mcrecon.core import samples

    w, h = 7, 3
    rng = np.random.default_rng(1)
    pos = (rng.random((50, 2)) * [w, h]).astype(dtype)
    val = rng.random((50, 2)).astype(dtype)
    cases = [(pos, val)]
    for k, bad in ((3, [np.nan, 1.0]), (5, [w, 0.5]), (7, [-0.0, 0.0]), (9, [-1e-30, 0.5]), (11, [0.5, h]),
                   (13, [np.inf, 0.0]), (15, [np.nextafter(dtype(w), dtype(0)), np.nextafter(dtype(h), dtype(0))])):
        p = pos.copy()
        p[k] = bad
        cases.append((p, val))
    v = val.copy()
    v[[2, 4], 1] = [np.nan, -np.inf]
    cases.append((pos, v))
    for p, v in cases:
        got = samples._scan_numpy(p, v, w, h)
        want = samples._scan(np.ascontiguousarray(p), np.ascontiguousarray(v), w, h)
        assert tuple(int(x) for x in got) == tuple(int(x) for x in want)


def test_lazy_kernel_becomes_the_numba_dispatcher():
    from mcrecon.core import merge, stats

    stats.PixelStats.from_samples(np.array([[0.5, 0.5]]), np.ones((1, 1)), width=1, height=1, channels=("Y",))
    assert type(merge._accumulate).__name__ == "CPUDispatcher"  # replaced in its module at the first call


class _Terminal(io.StringIO):
    def isatty(self):
        return True


def test_jit_notice_only_on_a_terminal_with_a_cold_cache(monkeypatch, tmp_path):
    from mcrecon.cli import _common

    monkeypatch.setattr(_common, "numba_cache_cold", lambda parts: True)
    pipe, tty = io.StringIO(), _Terminal()
    assert not _common.jit_notice(("methods",), stream=pipe) and pipe.getvalue() == ""
    assert _common.jit_notice(("methods",), seconds=30, stream=tty)
    assert tty.getvalue() == "mcrecon: compiling kernels (first run only, ~30 s)\n"
    monkeypatch.setattr(_common, "numba_cache_cold", lambda parts: False)
    assert not _common.jit_notice(("methods",), stream=_Terminal())


def test_cold_cache_detection(monkeypatch, tmp_path):
    from mcrecon.cli import _common

    monkeypatch.setattr(_common, "_PACKAGE", tmp_path)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "home-cache"))
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    src = tmp_path / "kern.py"
    src.write_text("@numba.njit(cache=True)\ndef f(x):\n    return x\n")
    (tmp_path / "plain.py").write_text("x = 1\n")
    assert _common.numba_cache_cold(("kern.py", "plain.py"))
    cache = tmp_path / "__pycache__"
    cache.mkdir()
    nbi = cache / f"kern.f-1.py{sys.version_info[0]}{sys.version_info[1]}.nbi"
    nbi.write_bytes(b"")
    os.utime(nbi, (src.stat().st_mtime + 10,) * 2)
    assert not _common.numba_cache_cold(("kern.py", "plain.py"))
    os.utime(src, (nbi.stat().st_mtime + 10,) * 2)  # the source edited since: compiled again
    assert _common.numba_cache_cold((".",))
    (tmp_path / "other.py").write_text("@numba.njit(cache=True)\ndef g(x):\n    return x\n")
    os.utime(src, (nbi.stat().st_mtime - 10,) * 2)
    assert not _common.numba_cache_cold((".",))  # a directory: compiled once any of its files is
    assert _common.numba_cache_cold(("other.py",))


def test_method_kernels_name_the_feature_filters_for_inputs_with_features():
    # a first `denoise --method auto` of a log with features compiled the regression for 14 s without a
    # notice: the method's own package was cached (the demo's colour-only scene) and nothing else was asked
    from mcrecon.cli import _common
    from mcrecon.methods import get_method

    auto, gem = get_method("auto"), get_method("gem")
    assert _common.method_kernels(auto) == ("methods/auto",)
    with_features = _common.method_kernels(auto, features=True)
    assert with_features[0] == "methods/auto" and set(_common.FEATURE_KERNELS) <= set(with_features)
    assert _common.method_kernels(gem, features=True) == ("methods/gem",)  # gem reads no features
    for part in _common.FEATURE_KERNELS:  # each a file of the package that defines cached kernels
        assert _common._kernel_files(part)
