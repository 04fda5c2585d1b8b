"""The specs an outsider follows, made executable (issue 13, item 2).

``data_tools/c`` holds a sample-log writer and an out-of-process renderer
written in C from ``docs/sample-log-format.md`` and
``docs/renderer-protocol.md`` alone.  They are compiled once per session
(skipped, with the reason, without gcc or the HDF5 C headers) and checked
against mcrecon: ``info``, ``denoise`` and ``adapt`` with box, awr and gem.
The other tests pin the points of the specs a C author had to guess at;
they need no compiler.
"""

from __future__ import annotations

import json
import shlex
import shutil
import subprocess
from pathlib import Path

import h5py
import numpy as np
import pytest

from mcrecon import InputError, RendererError
from mcrecon.io import append_log, read_exr, read_log
from mcrecon.io.logformat import cast_positions
from mcrecon.renderers.command import read_request, write_request
from mcrecon.core.requests import SampleRequest, validate_reply


REPO = Path(__file__).parents[1]
C_DIR = REPO / "data_tools" / "c"
PROGRAMS = ("mcrecon_log_writer", "mcrecon_c_renderer")


# ------------------------------------------------------------------ building the C tools
def _hdf5_flags() -> tuple[list[str] | None, str]:
    """Compiler flags for the HDF5 C library, or None and why not."""
    if shutil.which("pkg-config"):
        out = subprocess.run(["pkg-config", "--cflags", "--libs", "hdf5"], capture_output=True, text=True)
        if out.returncode == 0 and out.stdout.strip():
            return shlex.split(out.stdout), ""
    for inc, lib in (("/usr/include/hdf5/serial", "/usr/lib/x86_64-linux-gnu/hdf5/serial"), ("/usr/include", None)):
        if Path(inc, "hdf5.h").exists():
            return [f"-I{inc}"] + ([f"-L{lib}"] if lib else []) + ["-lhdf5"], ""
    return None, ("the HDF5 C headers (hdf5.h) were not found and pkg-config knows no hdf5: "
                  "apt-get install libhdf5-dev pkg-config")


@pytest.fixture(scope="module")
def c_tools(tmp_path_factory) -> dict[str, Path]:
    """The two C programs, compiled once into a directory whose name holds a space."""
    cc = shutil.which("gcc") or shutil.which("cc")
    if cc is None:
        pytest.skip("no C compiler (gcc) on this machine: apt-get install gcc")
    flags, why = _hdf5_flags()
    if flags is None:
        pytest.skip(why)
    out = tmp_path_factory.mktemp("c") / "c tools"  # a space: --renderer-cmd must quote it (shlex)
    out.mkdir()
    built = {}
    for name in PROGRAMS:
        exe = out / name
        proc = subprocess.run([cc, "-O2", "-Wall", "-Wextra", "-Werror", "-o", str(exe), str(C_DIR / f"{name}.c"),
                               *flags, "-lm"], capture_output=True, text=True)
        if proc.returncode != 0 and "hdf5.h" in proc.stderr and "No such file" in proc.stderr:
            pytest.skip(f"the HDF5 C headers are missing ({proc.stderr.strip().splitlines()[0]}): "
                        "apt-get install libhdf5-dev pkg-config")
        assert proc.returncode == 0, f"{name}.c does not compile:\n{proc.stderr}"
        built[name] = exe
    return built


def _run(*args, **kw):
    return subprocess.run([str(a) for a in args], check=True, capture_output=True, text=True, **kw)


# ------------------------------------------------------------------ the C sample-log writer
W, H = 24, 16


def test_c_writer_log_passes_info_and_denoise(c_tools, tmp_path, cli):
    """The C writer's log through ``mcrecon info`` and ``denoise`` (in this process: the same readers as a
    child's; the other tests here run the command line in children)."""
    log = tmp_path / "c.h5"
    _run(c_tools["mcrecon_log_writer"], log, W, H, 4, 7)
    code, out, err = cli(["info", "--json", log])
    assert code == 0, err
    info = json.loads(out)
    assert (info["width"], info["height"], info["channels"]) == (W, H, ["R", "G", "B"])
    assert info["samples"] == info["finite_samples"] == W * H * 4 and info["rounds"] == 1
    assert info["spp_min"] == info["spp_max"] == 4 and info["features"] == ["depth"]
    assert info["metadata"]["renderer"] == "mcrecon_log_writer.c"
    with h5py.File(log, "r") as f:  # checksummed and growable, like mcrecon's own logs
        for name in ("positions", "values", "round", "rounds/end", "features/depth"):
            d = f[name]
            assert d.fletcher32 and d.maxshape[0] is None, name
        assert f["rounds/end"][...].tolist() == [W * H * 4]
        assert h5py.check_string_dtype(f.attrs.get_id("channels").dtype).encoding == "utf-8"
    for method in ("box", "gem"):
        out = tmp_path / f"{method}.exr"
        code, stdout, err = cli(["denoise", log, "-o", out, "--method", method])
        assert code == 0, err
        assert f"{W * H * 4} samples" in stdout
        img, channels = read_exr(out)
        assert img.shape == (H, W, 3) and channels == ("R", "G", "B") and np.isfinite(img).all()
        assert 0.1 < float(img[H // 2, W // 2, 0]) < 2.0  # the disc's centre: 1 times noise of mean 1


def test_c_writer_appends_rounds_extending_features_and_discarding_uncommitted_rows(c_tools, tmp_path, cli):
    """Points 1 and 3: an append extends /features/* too; H5Dset_extent discards rows past n_committed
    (left here as an interrupted append would: junk samples and a /rounds/end row past the count);
    the next round is numbered by the committed rounds."""
    log = tmp_path / "grow.h5"
    writer = c_tools["mcrecon_log_writer"]
    _run(writer, log, W, H, 2)
    n = W * H * 2
    with h5py.File(log, "r+") as f:  # an append that died before its commit
        for name in ("positions", "values", "round", "features/depth"):
            f[name].resize(n + 5, axis=0)
        f["positions"][n:] = 0.5
        f["round"][n:] = 9
        f["rounds/end"].resize(2, axis=0)
        f["rounds/end"][1] = n + 5
    assert read_log(log).n_rounds == 1 and read_log(log).n_samples == n  # trailing rows: not a contradiction
    out = _run(writer, "--append", log, 3, 11)
    assert "appended round 1 (label 1)" in out.stdout
    m = W * H * 3
    got = read_log(log)
    assert got.n_samples == n + m and got.round_slices() == [(0, n), (n, n + m)]
    assert got.read_feature("depth").shape == (n + m,)
    with h5py.File(log, "r") as f:
        assert f["positions"].shape[0] == f["features/depth"].shape[0] == n + m  # the junk rows are gone
        assert f["rounds/end"][...].tolist() == [n, n + m]
        assert np.unique(f["round"][n:]).tolist() == [1]
    depth = got.read_feature("depth")
    np.testing.assert_allclose(depth, 1 + np.asarray(got.read_all().positions[:, 1], np.float64) / H, rtol=1e-6)
    # mcrecon appends to the C writer's log, and the C writer to mcrecon's append
    append_log(log, np.full((4, 2), 0.5, np.float32), np.ones((4, 3), np.float32),
               features={"depth": np.ones(4, np.float32)})
    _run(writer, "--append", log, 1)
    got = read_log(log)
    assert got.n_rounds == 4 and got.n_samples == n + m + 4 + W * H
    assert got.read_all().round[-1] == 3
    code, _, err = cli(["denoise", got.path, "-o", tmp_path / "g.exr", "--method", "box"])
    assert code == 0, err


# ------------------------------------------------------------------ the C renderer
def _check_c_features(log, w, h):
    """The C renderer's surfaces, recomputed here: a hemisphere over the disc, a plane behind it."""
    pos = np.asarray(log.read_all().positions, np.float64)
    dx, dy = pos[:, 0] / w - 0.5, pos[:, 1] / h - 0.5
    r2 = (dx ** 2 + dy ** 2) / 0.09
    disc = r2 < 1
    assert disc.any() and (~disc).any()
    nz = np.sqrt(np.clip(1 - r2, 0, None))
    albedo = np.where(disc[:, None], [0.8, 0.5, 0.2], 0.5)
    normal = np.where(disc[:, None], np.stack([dx / 0.3, dy / 0.3, nz], axis=1), [0.0, 0.0, 1.0])
    depth = np.where(disc, 1 - 0.3 * nz, 1 + pos[:, 1] / h)
    np.testing.assert_allclose(log.read_feature("albedo"), albedo, rtol=1e-6)
    # atol: nz = sqrt(1 - r2) amplifies the positions' rounding near the rim (1e-6 -> 2e-6 at nz 0.03)
    np.testing.assert_allclose(log.read_feature("normal"), normal, rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(np.linalg.norm(log.read_feature("normal"), axis=1), 1.0, rtol=1e-5)
    np.testing.assert_allclose(log.read_feature("depth"), depth, rtol=1e-6, atol=1e-5)


def _adapt(cli, c_tools, tmp_path, method, *extra, w=16, h=12, spp=6):
    """``mcrecon adapt`` driving the C renderer (a child process per round; the command itself runs here)."""
    log = tmp_path / f"{method}.h5"
    # The binary's path holds a space: quoted for shlex, never through a shell.
    cmd = f"{shlex.quote(str(c_tools['mcrecon_c_renderer']))} {{request}} {{reply}}"
    code, _, err = cli(["adapt", "--renderer-cmd", cmd, "--size", f"{w}x{h}", "--spp", spp, "--method", method,
                        "--seed", 5, "-o", tmp_path / f"{method}.exr", "--log", log, "--quiet", *extra])
    assert code == 0, err
    return log


@pytest.mark.parametrize("method", ["box", "awr", "gem"])
def test_c_renderer_drives_an_adaptive_run(c_tools, tmp_path, method, cli):
    """box sends counts every round; awr and gem send positions after the first (counted) round."""
    log = _adapt(cli, c_tools, tmp_path, method, *(() if method == "box" else ("--initial-spp", 2)))
    got = read_log(log)
    assert got.n_samples == 16 * 12 * 6 and got.n_rounds >= 2
    assert got.run_settings["renderer_spec"]["argv"][0] == str(c_tools["mcrecon_c_renderer"])
    assert got.run_settings["sampler"] == "sobol"  # its replies declare the per-pixel Sobol sequence
    # the reply's features reach the log, every round (HDF5 lists them by name)
    assert got.feature_names == ("albedo", "depth", "normal")
    _check_c_features(got, 16, 12)
    img, _ = read_exr(tmp_path / f"{method}.exr")
    assert img.shape == (12, 16, 3) and np.isfinite(img).all()
    assert sum(r["samples"] for r in got.round_records) == got.n_samples


def test_c_renderer_answers_counts_and_positions_together_and_either_string_type(c_tools, tmp_path):
    """A request with both parts (a method may send both), written once by mcrecon (variable-length
    UTF-8 strings) and once by hand with fixed-length ASCII strings and int32 integers."""
    counts = np.zeros((3, 5), np.int64)
    counts[0, 0], counts[2, 4] = 2, 3
    pos = np.array([[4.999999999, 2.999999999], [0.0, 0.0], [2.5, 1.25]])
    req = SampleRequest(5, 3, counts=counts, positions=pos, round_index=2, seed=2**64 - 1)
    a = write_request(tmp_path / "a.request.h5", req, channels=("R", "G", "B", "A"))
    b = tmp_path / "b.request.h5"
    with h5py.File(b, "w") as f:
        f.attrs["format"] = np.bytes_(b"mcrecon-request")
        for key, v in (("format_version", 1), ("width", 5), ("height", 3), ("round", 2), ("n_total", req.total)):
            f.attrs[key] = np.int32(v)
        f.attrs["seed"] = np.uint64(2**64 - 1)
        f.attrs["channels"] = np.array([b"R", b"G", b"B", b"A"], dtype="S1")
        f["counts"] = counts.astype(np.int32)
        f["positions"] = pos
    replies = []
    for request in (a, b):
        assert read_request(request).total == req.total
        reply = request.with_name(request.name.replace("request", "reply"))
        _run(c_tools["mcrecon_c_renderer"], request, reply)
        log = read_log(reply)  # fixed-length ASCII strings in the reply
        with h5py.File(reply, "r") as f:
            assert h5py.check_string_dtype(f.attrs.get_id("channels").dtype).length == 1
        assert log.channels == ("R", "G", "B", "A") and log.feature_names == ("albedo", "depth", "normal")
        data = log.read_all()
        batch = validate_reply(req, (data.positions, data.values), n_channels=4, renderer="c")
        np.testing.assert_array_equal(batch.positions[5:], pos)
        replies.append(data)
    np.testing.assert_array_equal(replies[0].values, replies[1].values)  # same request, same seed: same samples


def test_c_renderer_refuses_a_request_whose_n_total_disagrees(c_tools, tmp_path):
    req = write_request(tmp_path / "r.h5", SampleRequest(2, 2, counts=np.ones((2, 2), np.int64)), channels=("Y",))
    with h5py.File(req, "r+") as f:
        f.attrs["n_total"] = np.int64(5)
    proc = subprocess.run([c_tools["mcrecon_c_renderer"], req, tmp_path / "reply.h5"], capture_output=True, text=True)
    assert proc.returncode != 0 and "n_total" in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
    with pytest.raises(InputError, match=r"attribute n_total: got 5, expected sum\(counts\) \+ M = 4"):
        read_request(req)


def _c_reply(c_tools, tmp_path, req: SampleRequest, name: str):
    """The C renderer's reply to ``req`` (one channel, Y): positions and values as read back."""
    path = write_request(tmp_path / f"{name}.request.h5", req, channels=("Y",))
    reply = tmp_path / f"{name}.reply.h5"
    _run(c_tools["mcrecon_c_renderer"], path, reply)
    data = read_log(reply).read_all()
    return validate_reply(req, (data.positions, data.values), n_channels=1, renderer="c")


def _c_shade(x, y, w, h, noise):
    """The C renderer's channel 0 at film position (x, y) for a noise factor (its shade())."""
    dx, dy = x / w - 0.5, y / h - 0.5
    return np.where(np.sqrt(dx * dx + dy * dy) < 0.3, 1.0, 0.2 * x / w) * noise


def test_c_renderer_continues_each_pixels_sobol_sequence_across_rounds(c_tools, tmp_path):
    """Four requests of 8 samples per pixel, each starting at the pixel's first_index, are sample for
    sample one request of 32; the points are those of the built-in scenes' Sobol sampler (seed 0)."""
    from mcrecon.core.requests import sample_indices
    from mcrecon.renderers.scenes.sobol import sobol_points

    w, h = 6, 5
    one = _c_reply(c_tools, tmp_path, SampleRequest(w, h, counts=np.full((h, w), 32, np.int64)), "one")
    rounds = [_c_reply(c_tools, tmp_path, SampleRequest(w, h, counts=np.full((h, w), 8, np.int64), round_index=r,
                                                       seed=1000 + r, first_index=np.full((h, w), 8 * r, np.int64)),
                       f"r{r}") for r in range(4)]
    # the reply lists pixel by pixel in row order: pixel p's 32 samples, against its 8 of each round
    pos = np.concatenate([b.positions.reshape(w * h, 1, 8, 2) for b in rounds], axis=1).reshape(-1, 2)
    val = np.concatenate([b.values.reshape(w * h, 1, 8, 1) for b in rounds], axis=1).reshape(-1, 1)
    np.testing.assert_array_equal(pos, one.positions)
    np.testing.assert_array_equal(val, one.values)
    req = SampleRequest(w, h, counts=np.full((h, w), 32, np.int64))
    pix = np.repeat(np.arange(w * h), 32)
    u = sobol_points(pix, sample_indices(req), 3, seed=0)
    np.testing.assert_array_equal(one.positions, np.stack([pix % w + u[:, 0], pix // w + u[:, 1]], axis=1))
    np.testing.assert_allclose(one.values[:, 0], _c_shade(one.positions[:, 0], one.positions[:, 1], w, h,
                                                          0.5 + u[:, 2]), rtol=1e-6)


def test_c_renderer_stratified_error_beats_independent_samples(c_tools, tmp_path):
    """32 samples of each pixel's scrambled Sobol sequence against the exact pixel integral: a smaller
    error than 32 independent samples of the same per-sample variance would have."""
    w, h, n = 16, 16, 32
    batch = _c_reply(c_tools, tmp_path, SampleRequest(w, h, counts=np.full((h, w), n, np.int64)), "s")
    v = batch.values[:, 0].astype(np.float64).reshape(w * h, n)
    # the pixel integral: a fine grid over the pixel (the noise factor's mean is 1)
    g = (np.arange(64) + 0.5) / 64
    gx, gy = np.meshgrid(g, g)
    cols, rows = np.arange(w * h) % w, np.arange(w * h) // w
    exact = np.array([_c_shade(c + gx, r + gy, w, h, 1.0).mean() for c, r in zip(cols, rows)])
    mse = np.mean((v.mean(axis=1) - exact) ** 2)
    independent = np.mean(v.var(axis=1, ddof=1) / n)
    assert mse < 0.3 * independent, (mse, independent)


def test_c_renderer_gives_a_requested_position_the_next_index_of_its_pixel(c_tools, tmp_path):
    """After a pixel's counted samples, a requested position there takes the next index of its sequence:
    its noise is dimension 2 of that index."""
    from mcrecon.renderers.scenes.sobol import sobol_points

    w, h = 4, 3
    counts = np.zeros((h, w), np.int64)
    counts[1, 2] = 2
    first = np.full((h, w), 5, np.int64)
    pos = np.array([[2.25, 1.75], [0.5, 0.5], [2.75, 1.25]])
    b = _c_reply(c_tools, tmp_path, SampleRequest(w, h, counts=counts, positions=pos, first_index=first), "p")
    # pixel (2, 1) = 6: counted indices 5, 6, then its positions 7 and 8; pixel 0's position index 5
    u = sobol_points(np.array([6, 6, 6, 0, 6]), np.array([5, 6, 7, 5, 8]), 3, seed=0)
    np.testing.assert_array_equal(b.positions[:2], np.stack([2 + u[:2, 0], 1 + u[:2, 1]], axis=1))
    np.testing.assert_array_equal(b.positions[2:], pos)
    noise = 0.5 + u[:, 2]
    np.testing.assert_allclose(b.values[:, 0], _c_shade(b.positions[:, 0], b.positions[:, 1], w, h, noise), rtol=1e-6)


# ------------------------------------------------------------------ spec points, no compiler needed
def _log(path, *, strings="vlen", rounds=None, ends=None, positions=None):
    """A log written with h5py as another writer would: ``strings`` 'vlen' (UTF-8) or 'fixed' (ASCII)."""
    n = 6 if positions is None else len(positions)
    with h5py.File(path, "w") as f:
        if strings == "fixed":
            f.attrs["format"] = np.bytes_(b"mcrecon-sample-log")
            f.attrs["channels"] = np.array([b"R", b"G", b"B"], dtype="S1")
            f.attrs["metadata_json"] = np.bytes_(b'{"renderer": "fixed"}')
        else:
            f.attrs["format"] = "mcrecon-sample-log"
            f.attrs["channels"] = np.array(["R", "G", "B"], dtype=h5py.string_dtype("utf-8"))
            f.attrs["metadata_json"] = '{"renderer": "vlen \u00e9"}'
        f.attrs["format_version"] = np.int32(1)
        f.attrs["width"], f.attrs["height"] = np.int16(3), np.uint8(2)
        f["positions"] = np.full((n, 2), 0.5, np.float32) if positions is None else positions
        f["values"] = np.ones((n, 3), np.float32)
        if rounds is not None:
            f["round"] = np.asarray(rounds, np.int32)
        if ends is not None:
            f.create_dataset("rounds/end", data=np.asarray(ends, np.int64), maxshape=(None,), chunks=(16,))
    return path


@pytest.mark.parametrize("strings", ["vlen", "fixed"])
def test_string_attributes_of_either_type_are_read(tmp_path, strings):
    """Point 4: format, channels, metadata_json as variable-length UTF-8 or fixed-length ASCII."""
    log = read_log(_log(tmp_path / "s.h5", strings=strings))
    assert log.channels == ("R", "G", "B") and (log.width, log.height) == (3, 2)
    assert log.metadata["renderer"] == ("fixed" if strings == "fixed" else "vlen \u00e9")
    assert append_log(log.path, np.full((2, 2), 0.5), np.ones((2, 3))) == 8  # and appended to


def test_round_and_rounds_end_must_agree(tmp_path, cli):
    """Point 2: a /rounds/end that contradicts /round is refused in one line naming file, dataset and fix;
    rows past the committed count are not a contradiction."""
    ok = read_log(_log(tmp_path / "ok.h5", rounds=[0, 0, 1, 1, 4, 4], ends=[2, 4, 6]))
    assert ok.round_slices() == [(0, 2), (2, 4), (4, 6)]
    for rounds, ends, where in (([0, 0, 0, 1, 1, 1], [2, 4, 6], "round 1 (rows 2-3 by /rounds/end)"),
                                ([0, 0, 1, 1, 1, 1], [2, 4, 6], "round 2 (rows 4-5 by /rounds/end)"),
                                ([0, 0, 0, 1, 1, 1], [6], "round 0 (rows 0-5 by /rounds/end)")):
        path = _log(tmp_path / "bad.h5", rounds=rounds, ends=ends)
        with pytest.raises(InputError) as exc:
            read_log(path)
        msg = str(exc.value)
        assert msg.startswith(f"{path}: dataset /rounds/end: {where} contradicts /round") and "\n" not in msg
        assert "rewrite /rounds/end" in msg and "or delete it" in msg
        code, _, err = cli(["info", path])
        assert code == 2 and "contradicts /round" in err
    # An interrupted append: rows past n_committed in every dataset, /rounds/end rows past it or
    # a fill-value 0 a full disk left.
    path = _log(tmp_path / "tail.h5", rounds=[0, 0, 1, 1, 7, 7], ends=[2, 4, 6, 0])
    with h5py.File(path, "r+") as f:
        f.attrs["n_committed"] = np.int64(4)
    log = read_log(path)
    assert log.n_samples == 4 and log.round_slices() == [(0, 2), (2, 4)]
    append_log(path, np.full((1, 2), 0.5), np.ones((1, 3)))  # numbered 2: the committed rounds
    log = read_log(path)
    assert log.round_slices() == [(0, 2), (2, 4), (4, 5)] and log.read_all().round.tolist() == [0, 0, 1, 1, 2]


def test_append_numbers_rounds_above_the_last_label(tmp_path):
    """Point 3: the next round's label is the committed round count, or more when labels have gaps;
    a smaller explicit label is refused (it would contradict /rounds/end)."""
    path = _log(tmp_path / "gaps.h5", rounds=[0, 0, 5, 5, 5, 5], ends=[2, 6])
    append_log(path, np.full((1, 2), 0.5), np.ones((1, 3)))
    assert read_log(path).read_all().round.tolist()[-1] == 6
    with pytest.raises(InputError, match=r"round_index: 6, but the last committed round's label in /round is 6"):
        append_log(path, np.full((1, 2), 0.5), np.ones((1, 3)), round_index=6)
    # A log without /round whose /rounds/end has rounds gets /round labelled by them on the first append.
    path = _log(tmp_path / "noround.h5", ends=[2, 6])
    append_log(path, np.full((1, 2), 0.5), np.ones((1, 3)))
    log = read_log(path)
    assert log.round_slices() == [(0, 2), (2, 6), (6, 7)] and log.read_all().round.tolist() == [0, 0, 1, 1, 1, 1, 2]


def test_positions_on_pixel_edges(tmp_path, cli):
    """Point 11: a position exactly on the far edge of the film is off it (refused in one line); the
    largest float32 below the edge is inside; a counted sample on i + 1 belongs to the next pixel."""
    edge = np.float32(3.0)
    below = np.nextafter(edge, np.float32(0))
    code, _, err = cli(["info", _log(tmp_path / "edge.h5", positions=np.array([[0.5, 0.5], [edge, 1.5]], np.float32))])
    assert code == 2 and "first at row 1: [3.0, 1.5]" in err
    assert len(err.strip().splitlines()) == 1
    ok = read_log(_log(tmp_path / "in.h5", positions=np.array([[0.5, 0.5], [below, 1.5]], np.float32)))
    assert ok.n_samples == 2 and cli(["info", ok.path])[0] == 0
    req = SampleRequest(3, 2, counts=np.array([[1, 0, 0], [0, 0, 0]]))
    with pytest.raises(RendererError, match="per-pixel sample counts differ"):
        validate_reply(req, (np.array([[1.0, 0.5]], np.float32), np.ones((1, 3))), n_channels=3)
    # float32 storage of i + u clamps to the pixel, as the docs tell a writer to
    x = np.array([[1023.99999999, 0.5]])
    assert np.float32(x[0, 0]) == 1024  # the naive cast leaves the film
    assert cast_positions(x, np.float32)[0, 0] == np.nextafter(np.float32(1024), np.float32(0))


def test_request_fields_have_the_documented_types(tmp_path):
    """Point 5 (and 4 for the request): what write_request writes; read_request takes any integer type."""
    req = SampleRequest(4, 2, counts=np.ones((2, 4), np.int64), positions=np.array([[1.5, 0.5]]),
                        round_index=3, seed=2**63 + 1)
    path = write_request(tmp_path / "r.h5", req, channels=("R", "G", "B"))
    with h5py.File(path, "r") as f:
        a = f.attrs
        for key in ("format_version", "width", "height", "round", "n_total"):
            assert a.get_id(key).dtype == np.int64, key
        assert a.get_id("seed").dtype == np.uint64 and int(a["seed"]) == 2**63 + 1
        assert int(a["n_total"]) == req.total == 9  # sum(counts) + M
        for key in ("format", "channels"):
            assert h5py.check_string_dtype(a.get_id(key).dtype).encoding == "utf-8", key
        assert f["counts"].dtype == np.int64 and f["positions"].dtype == np.float64
    with h5py.File(path, "r+") as f:  # another writer's types
        for key in ("width", "height", "round"):
            v = int(f.attrs[key])
            del f.attrs[key]
            f.attrs[key] = np.uint16(v)
        f.attrs["format"] = np.bytes_(b"mcrecon-request")
        f.attrs["channels"] = np.array([b"R", b"G", b"B"], dtype="S1")
    back = read_request(path)
    assert (back.width, back.height, back.round_index, back.seed, back.total) == (4, 2, 3, 2**63 + 1, 9)
