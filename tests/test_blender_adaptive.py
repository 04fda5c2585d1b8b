"""Adaptive rounds through Blender Cycles (``mcrecon adapt --blender``): each round continues every
pixel's own Cycles sample pattern, and a killed run resumes from its log alone.

The scene is the asymmetric one of test_blender.py, built in a subprocess (bpy stays out of the test
process), rendered at 32x24 on 2 threads.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

from helpers import MCRECON, cli_env, run_cli_process
from mcrecon.cli import main
from mcrecon.io import read_log
from mcrecon.renderers import blender as bl
from mcrecon.renderers.spec import check_spec
from mcrecon.renderers.spec_format import blender_spec
from test_blender import EDGE, SCENE

NEEDS_BPY = pytest.mark.skipif(not bl.bpy_available(), reason="needs bpy: pip install 'mcrecon[blender]'")
W, H = 32, 24


@pytest.fixture(scope="module")
def blend(tmp_path_factory):
    d = tmp_path_factory.mktemp("cycles_adapt")
    path = d / "edge.blend"
    subprocess.run([sys.executable, "-c", SCENE, "64", "48", str(EDGE), str(path)], check=True,
                   capture_output=True, env=cli_env(), timeout=300)
    return path


def _adapt(*args, check=True):
    r = run_cli_process(["adapt", *args], timeout=600)
    assert not check or r.returncode == 0, r.stderr
    return r


def _by_pixel(log):
    """Each pixel's samples in the order the log holds them: (positions, values) sorted by pixel, stably."""
    c = log.read_all()
    pix = np.floor(c.positions[:, 1]).astype(int) * log.width + np.floor(c.positions[:, 0]).astype(int)
    order = np.argsort(pix, kind="stable")
    return pix[order], c.positions[order], c.values[order]


# requests answered by the renderer in a subprocess: one of n samples per pixel, or two that split them
REQUESTS = textwrap.dedent("""
    import sys, numpy as np
    from mcrecon.core.requests import SampleRequest
    from mcrecon.renderers.blender import BlenderRenderer
    blend, w, h, n, out, split = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]), sys.argv[5], sys.argv[6]
    r = BlenderRenderer(blend, width=w, height=h, threads=2, features="all")
    if split == "no":
        b = r.render(SampleRequest(w, h, counts=np.full((h, w), n, np.int64)))
        np.savez(out, positions=b.positions, values=b.values, renders=r.renders)
        raise SystemExit
    # pixel p: 1 + p % 3 samples first (an uneven round), the rest of n in the second request
    c1 = (1 + np.arange(w * h) % 3).reshape(h, w)
    b1 = r.render(SampleRequest(w, h, counts=c1))
    renders1, rendered1 = r.renders, r.samples_rendered
    b2 = r.render(SampleRequest(w, h, counts=n - c1, first_index=c1, round_index=1, seed=7))
    np.savez(out, p1=b1.positions, v1=b1.values, p2=b2.positions, v2=b2.values, c1=c1, renders1=renders1,
             rendered1=rendered1, renders=r.renders, rendered=r.samples_rendered, delivered=r.samples_delivered)
""")


def _requests(blend, tmp_path, n, split):
    out = tmp_path / f"{split}.npz"
    subprocess.run([sys.executable, "-c", REQUESTS, str(blend), str(W), str(H), str(n), str(out), split],
                   check=True, capture_output=True, env=cli_env(), timeout=300)
    return np.load(out)


@NEEDS_BPY
def test_rounds_continue_each_pixels_cycles_pattern(blend, tmp_path):
    """A box run of 8 spp in doubling rounds holds, pixel by pixel, the samples 0..7 of one request
    for 8 (Cycles' own samples: the same film positions; values within Cycles' render-to-render
    differences), and the log records the spec that reopens the same file."""
    log = tmp_path / "run.h5"
    _adapt("--blender", blend, "--size", f"{W}x{H}", "--spp", 8, "--features", "none", "--log", log,
           "-o", tmp_path / "out.exr", "--quiet")
    got = read_log(log)
    assert got.n_rounds >= 3 and got.n_samples == 8 * W * H
    spec = got.run_settings["renderer_spec"]
    assert spec["kind"] == "blender" and spec["scene"] == str(blend) and (spec["width"], spec["height"]) == (W, H)
    assert spec["features"] == "none" and spec["camera"] == "cam"
    one = _requests(blend, tmp_path, 8, "no")
    assert int(one["renders"]) == 16  # 8 colour renders and their 8 probes, nothing else
    pix, pos, val = _by_pixel(got)
    np.testing.assert_array_equal(pix, np.repeat(np.arange(W * H), 8))
    np.testing.assert_array_equal(pos, one["positions"])
    np.testing.assert_allclose(val, one["values"], atol=1e-3)


@NEEDS_BPY
def test_uneven_rounds_keep_what_a_box_renders_beyond_the_request(blend, tmp_path):
    """A round of 1-3 samples per pixel renders indices 0-2 over the film: the samples a pixel needs
    only in the next round are kept and given then (not rendered again), and the two rounds are,
    pixel by pixel, one request of 6."""
    one, two = _requests(blend, tmp_path, 6, "no"), _requests(blend, tmp_path, 6, "split")
    c1 = two["c1"].ravel()
    assert int(two["renders1"]) == 6 and int(two["rendered1"]) == 3 * W * H  # 3 colour + 3 probe renders
    assert int(two["delivered"]) == 6 * W * H
    # the second round renders indices 3-5 alone: indices 1 and 2 come from the first round's renders
    assert int(two["renders"]) == 12 and int(two["rendered"]) == 6 * W * H
    pos, val = [], []
    for p in range(W * H):
        a0, b0 = int(c1[:p].sum()), int((6 - c1[:p]).sum())
        pos.append(np.concatenate([two["p1"][a0:a0 + c1[p]], two["p2"][b0:b0 + 6 - c1[p]]]))
        val.append(np.concatenate([two["v1"][a0:a0 + c1[p]], two["v2"][b0:b0 + 6 - c1[p]]]))
    np.testing.assert_array_equal(np.concatenate(pos), one["positions"])
    np.testing.assert_allclose(np.concatenate(val), one["values"], atol=1e-3)


@NEEDS_BPY
def test_a_killed_run_resumes_from_its_log(blend, tmp_path):
    """SIGKILL once two rounds are committed; --resume reopens the .blend from the log's spec and ends
    with the uninterrupted run's samples (positions exact, values within render-to-render noise)."""
    log, full = tmp_path / "killed.h5", tmp_path / "full.h5"
    argv = ["--blender", str(blend), "--size", f"{W}x{H}", "--spp", "24", "--method", "box", "--features", "none",
            "--no-pipeline", "--quiet"]
    proc = subprocess.Popen([*MCRECON, "adapt", *argv, "--log", str(log), "-o",
                             str(tmp_path / "k.exr")], env=cli_env(), stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None:
        if log.exists():
            try:
                if read_log(log).n_rounds >= 2:
                    break
            except Exception:  # noqa: BLE001 - the log is being created
                pass
        time.sleep(0.05)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    killed_at = read_log(log).n_samples
    assert 0 < killed_at < 24 * W * H, "the run ended before it could be killed"
    r = _adapt("--resume", log, "-o", tmp_path / "resumed.exr")
    _adapt(*argv, "--log", full, "-o", tmp_path / "full.exr")
    a, b = read_log(log), read_log(full)
    assert a.n_samples == b.n_samples == 24 * W * H
    pa, posa, vala = _by_pixel(a)
    pb, posb, valb = _by_pixel(b)
    np.testing.assert_array_equal(posa, posb)
    np.testing.assert_allclose(vala, valb, atol=1e-3)


@NEEDS_BPY
def test_methods_with_spread_counts_are_refused_before_rendering(blend, tmp_path, cli):
    """gem in a child (its exit status and one line as a user sees them); awr and auto in this process (the
    refusal comes before Blender is started: bpy is not imported here)."""
    for method in ("gem", "awr", "auto"):
        argv = ["--blender", blend, "--size", f"{W}x{H}", "--spp", 4, "--method", method, "--log",
                tmp_path / f"{method}.h5", "-o", tmp_path / "o.exr"]
        if method == "gem":
            r = _adapt(*argv, check=False)
            code, err = r.returncode, r.stderr
        else:
            code, _, err = cli(["adapt", *argv])
        assert code == 2 and "a uniform log" in err and len(err.strip().splitlines()) == 1, err
        assert not (tmp_path / f"{method}.h5").exists() and not (tmp_path / "o.exr").exists()


@pytest.mark.parametrize("name, opts, refused", [("gem", {}, True), ("awr", {}, True), ("auto", {}, True),
                                                   ("auto", {"sampling": "uniform"}, False), ("box", {}, False)])
def test_the_spread_refusal_reads_auto_s_sampling(name, opts, refused):
    """auto --sampling uniform asks for the same samples in every pixel: not refused (the refusal's own advice);
    its default GEM placement is."""
    from mcrecon.cli.commands import _refuse_spread_methods
    from mcrecon.errors import InputError
    from mcrecon.methods import get_method

    if refused:
        with pytest.raises(InputError, match="auto --sampling uniform"):
            _refuse_spread_methods(get_method(name, **opts))
    else:
        assert _refuse_spread_methods(get_method(name, **opts)) is None   # no InputError


def test_missing_bpy_says_how_to_install(blend, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(bl, "bpy_available", lambda: False)
    assert main(["adapt", "--blender", str(blend), "--spp", "4", "-o", str(tmp_path / "o.exr")]) == 2
    assert "needs bpy: pip install 'mcrecon[blender]'" in capsys.readouterr().err


@pytest.mark.parametrize("args, where", [
    (["--blender", "scene.txt"], "scene.txt"),
    (["--blender", "X.blend", "--scene", "flat"], "renderer"),
    (["--scene", "flat", "--camera", "cam"], "--camera"),
    (["--blender", "X.blend", "--features", "colour"], "features"),
])
def test_bad_flags_are_one_line(tmp_path, capsys, monkeypatch, args, where):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "X.blend").write_bytes(b"BLENDER-v405")
    (tmp_path / "scene.txt").write_text("x")
    assert main(["adapt", *args, "--spp", "4", "-o", "o.exr"]) == 2
    err = capsys.readouterr().err.strip()
    assert where in err and len(err.splitlines()) == 1
    assert not (tmp_path / "o.exr").exists()


def test_blender_spec_is_checked(tmp_path):
    spec = blender_spec(tmp_path / "s.blend", width=8, height=4, features="albedo,depth")
    assert check_spec(spec) == spec and spec["scene"] == str(tmp_path / "s.blend") and spec["pattern_spp"] == 65536
    with pytest.raises(Exception, match="scene"):
        check_spec({**spec, "scene": "relative.blend"})
    with pytest.raises(Exception, match="features"):
        check_spec({**spec, "features": "colour"})
