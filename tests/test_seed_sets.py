"""Seed sets: K renders of one frame with different seeds as pixel statistics, half buffers and features."""

import numpy as np
import pytest

import mcrecon
from mcrecon import InputError
from mcrecon.core.metrics import relative_mse
from mcrecon.io import read_seed_set

from helpers import run_cli

H, W = 5, 6


def _write(path, channels: dict, header: dict | None = None):
    import OpenEXR

    head = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage, **(header or {})}
    with OpenEXR.File(head, {k: np.ascontiguousarray(v, np.float32) for k, v in channels.items()}) as f:
        f.write(str(path))
    return path


def renders(tmp_path, k, *, spp=4, seed=0, name="shot.seed{}.exr", albedo=True):
    """K means-only renders (R,G,B + Albedo.R/G/B, header spp): their values as float32 stored."""
    rng = np.random.default_rng(seed)
    means, albedos = [], []
    for i in range(k):
        m = rng.uniform(0.0, 2.0, (H, W, 3)).astype(np.float32)
        a = rng.uniform(0.0, 1.0, (H, W, 3)).astype(np.float32)
        ch = {c: m[..., j] for j, c in enumerate("RGB")}
        if albedo:
            ch.update({f"Albedo.{c}": a[..., j] for j, c in enumerate("RGB")})
        _write(tmp_path / name.format(i), ch, {"spp": spp} if spp is not None else {})
        means.append(m.astype(np.float64))
        albedos.append(a.astype(np.float64))
    return np.stack(means), np.stack(albedos)


def test_mean_variance_count_and_halves_are_the_brute_force_ones(tmp_path):
    x, a = renders(tmp_path, 5)
    s = read_seed_set(str(tmp_path / "shot.seed*.exr"), mean="R,G,B")
    st = s.stats
    assert s.renders == 5 and s.count_source == "5 renders x header attribute spp = 4"
    assert (st.count == 5 * 4).all()
    np.testing.assert_allclose(st.mean, x.mean(0), rtol=1e-12, atol=1e-14)
    # the variance of the mean: the unbiased variance of the renders' means over K
    np.testing.assert_allclose(st.mean_variance(), x.var(0, ddof=1) / 5, rtol=1e-10, atol=1e-15)
    # halves: even renders (0, 2, 4: K odd, the first half has one more) and odd ones (1, 3)
    ha, hb = s.halves
    assert (ha.count == 3 * 4).all() and (hb.count == 2 * 4).all()
    np.testing.assert_allclose(ha.mean, x[0::2].mean(0), rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(hb.mean, x[1::2].mean(0), rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(ha.mean_variance(), x.var(0, ddof=1) / 3, rtol=1e-10, atol=1e-15)
    np.testing.assert_allclose(hb.mean_variance(), x.var(0, ddof=1) / 2, rtol=1e-10, atol=1e-15)
    # features: the average of the renders' AOVs, their variance across renders the same way
    fa = st.features["albedo"]
    np.testing.assert_allclose(fa.mean, a.mean(0), rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(fa.mean_variance(), a.var(0, ddof=1) / 5, rtol=1e-10, atol=1e-15)
    np.testing.assert_allclose(ha.features["albedo"].mean, a[0::2].mean(0), rtol=1e-12, atol=1e-14)


def test_a_list_and_a_glob_give_the_same_and_spp_may_be_given(tmp_path):
    renders(tmp_path, 4, spp=None)
    paths = [tmp_path / f"shot.seed{i}.exr" for i in range(4)]
    with pytest.raises(InputError, match="pass --spp N"):
        read_seed_set(paths, mean="R,G,B")
    a = read_seed_set(paths, mean="R,G,B", spp=2)
    b = read_seed_set(str(tmp_path / "shot.seed?.exr"), mean="R,G,B", spp=2)
    assert (a.stats.count == 8).all()
    np.testing.assert_array_equal(a.stats.mean, b.stats.mean)
    np.testing.assert_array_equal(a.stats.m2, b.stats.m2)
    # K = 4: two renders per half, equal counts
    assert (a.halves.a.count == 4).all() and (a.halves.b.count == 4).all()


def test_two_renders_of_one_sample_give_halves_without_a_variance(tmp_path):
    x, _ = renders(tmp_path, 2, spp=1, albedo=False)
    s = read_seed_set([tmp_path / "shot.seed0.exr", tmp_path / "shot.seed1.exr"], mean="R,G,B")
    np.testing.assert_allclose(s.stats.mean_variance(), x.var(0, ddof=1) / 2, rtol=1e-10, atol=1e-15)
    assert (s.halves.a.count == 1).all() and not s.halves.a.m2.any()


def test_reconstruct_takes_a_glob_or_a_list_in_python_and_on_the_command_line(tmp_path, capsys):
    x, _ = renders(tmp_path, 4)
    glob = str(tmp_path / "shot.seed*.exr")
    box = mcrecon.reconstruct(glob, method="box", exr_options={"mean": "R,G,B"})
    np.testing.assert_allclose(box, x.mean(0), rtol=1e-12, atol=1e-14)
    rec = mcrecon.reconstruct([tmp_path / f"shot.seed{i}.exr" for i in range(4)], method="auto", full=True,
                              exr_options={"mean": "R,G,B"})
    assert rec.inputs.halves is not None and rec.image.shape == (H, W, 3)
    out = tmp_path / "out" / "img.exr"
    code, stdout, err = run_cli(["reconstruct", glob, "--mean", "R,G,B", "-o", out, "--method", "gem"], capsys)
    assert code == 0, err
    assert "(4 renders)" in err and "4 renders x header attribute spp = 4" in err
    assert f"{W * H * 16} samples" in stdout and out.exists()


def _refused(tmp_path, capsys, source, match, *, file=None):
    with pytest.raises(InputError, match=match) as exc:
        mcrecon.reconstruct(source, method="gem", exr_options={"mean": "R,G,B"})
    if file is not None:
        assert str(exc.value).startswith(str(file))
    argv = [source] if isinstance(source, str) else None
    if argv is not None:  # the command line: one line, exit 2, no output written
        out = tmp_path / "refused.exr"
        code, _, err = run_cli(["reconstruct", *argv, "--mean", "R,G,B", "-o", out, "--method", "gem"], capsys)
        assert code == 2 and not out.exists() and err.count("\n") == 1 and "Traceback" not in err


def test_bad_seed_sets_are_one_line_naming_the_file_and_field(tmp_path, capsys):
    renders(tmp_path, 3)
    p = [tmp_path / f"shot.seed{i}.exr" for i in range(3)]
    _refused(tmp_path, capsys, str(tmp_path / "none*.exr"), "no file matches this glob")
    _refused(tmp_path, capsys, str(tmp_path / "shot.seed0*.exr"), "one render: a seed set is K >= 2", file=p[0])
    _refused(tmp_path, capsys, [p[0], p[1], p[0]], "seed set: the same file as", file=p[0])
    # the same seed twice: identical pixels
    (tmp_path / "shot.seed3.exr").write_bytes(p[1].read_bytes())
    _refused(tmp_path, capsys, [p[0], p[1], tmp_path / "shot.seed3.exr"], "same pixels as .*same seed",
             file=tmp_path / "shot.seed3.exr")
    (tmp_path / "shot.seed3.exr").unlink()
    # another size
    _write(tmp_path / "shot.seed3.exr", {c: np.ones((H + 1, W)) for c in "RGB"}, {"spp": 4})
    _refused(tmp_path, capsys, str(tmp_path / "shot.seed*.exr"), "shape: 6x6, but .* is 6x5",
             file=tmp_path / "shot.seed3.exr")
    # other passes (no albedo)
    _write(tmp_path / "shot.seed3.exr", {c: np.ones((H, W)) for c in "RGB"}, {"spp": 4})
    _refused(tmp_path, capsys, str(tmp_path / "shot.seed*.exr"), "channels: .*write the same passes",
             file=tmp_path / "shot.seed3.exr")
    # another count
    _write(tmp_path / "shot.seed3.exr", {**{c: np.ones((H, W)) for c in "RGB"},
                                         **{f"Albedo.{c}": np.ones((H, W)) for c in "RGB"}}, {"spp": 8})
    _refused(tmp_path, capsys, str(tmp_path / "shot.seed*.exr"), "count: .*same samples per pixel",
             file=tmp_path / "shot.seed3.exr")
    # NaN in one render
    bad = np.ones((H, W))
    bad[1, 2] = np.nan
    _write(tmp_path / "shot.seed3.exr", {"R": bad, "G": np.ones((H, W)), "B": np.ones((H, W)),
                                         **{f"Albedo.{c}": np.ones((H, W)) for c in "RGB"}}, {"spp": 4})
    _refused(tmp_path, capsys, str(tmp_path / "shot.seed*.exr"), "R: 1 sampled pixel\\(s\\) with NaN",
             file=tmp_path / "shot.seed3.exr")
    _refused(tmp_path, capsys, [p[0], p[1], "notes.txt"], "notes.txt is not an EXR path")


def test_two_renders_with_variances_stay_a_half_buffer_pair(tmp_path):
    """A tuple of two pbrt-v4 files (each with its own variance) is still a half-buffer pair; a glob of the
    same two is a seed set (the spread across renders)."""
    rng = np.random.default_rng(3)
    for i in range(2):
        ch = {c: rng.uniform(0.5, 1.0, (H, W)) for c in "RGB"}
        ch.update({f"Variance.{c}": np.full((H, W), 0.01) for c in "RGB"})
        _write(tmp_path / f"h{i}.exr", ch, {"samplesPerPixel": 8})
    pair = mcrecon.reconstruct((str(tmp_path / "h0.exr"), str(tmp_path / "h1.exr")), method="auto", full=True)
    assert len(pair.files) == 2
    seeds = mcrecon.reconstruct(str(tmp_path / "h?.exr"), method="auto", full=True)
    assert len(seeds.files) == 1 and seeds.files[0].renders == 2


def _scene_renders(tmp_path, scene, k, spp, size):
    """K renders of a built-in scene's pixel means at ``spp`` each, seeds 0..K-1, as EXRs (R,G,B, spp)."""
    from mcrecon import PixelStats
    from mcrecon.renderers.scenes import render_uniform

    for s in range(k):
        b = render_uniform(scene, width=size, height=size, spp=spp, seed=s)
        st = PixelStats.from_samples(b.positions, b.values, width=size, height=size)
        _write(tmp_path / f"{scene}.seed{s}.exr", {c: st.mean[..., j] for j, c in enumerate("RGB")}, {"spp": spp})


@pytest.mark.parametrize("method,scene,ratio", [("auto", "soft_shadow", 0.8), ("gem", "checker_spot", 0.9)])
def test_eight_seed_renders_of_a_scene_reconstruct_better_than_their_mean(tmp_path, method, scene, ratio):
    """8 renders at 8 spp each (seeds 0..7; 64x64): relative MSE of the method over that of the pixel mean
    measured 0.71 (auto, soft_shadow) and 0.83 (gem, checker_spot)."""
    from mcrecon.renderers.scenes import reference_image

    size = 64
    _scene_renders(tmp_path, scene, 8, 8, size)
    ref = reference_image(scene, size, size)
    glob = str(tmp_path / f"{scene}.seed*.exr")
    rec = mcrecon.reconstruct(glob, method=method, full=True, exr_options={"mean": "R,G,B"})
    mean = mcrecon.reconstruct(glob, method="box", exr_options={"mean": "R,G,B"})
    assert (rec.inputs.stats.count == 64).all()
    e_rec, e_mean = relative_mse(rec.image, ref), relative_mse(mean, ref)
    assert e_rec < ratio * e_mean, (e_rec, e_mean)


# ------------------------------------------------------------------ batch: frames that are seed sets
def test_seed_set_frames_group_renders_by_frame_number(tmp_path):
    from mcrecon.io.seed_sets import seed_set_frames

    for f in (1, 2, 10):
        renders(tmp_path, 3 if f != 10 else 2, seed=f, name=f"shot.{f:04d}.seed{{}}.exr")
    renders(tmp_path, 2, name="other.0001.seed{}.exr")
    frames = seed_set_frames(str(tmp_path / "shot.####.seed*.exr"))
    assert [fr.stem for fr in frames] == ["shot.0001", "shot.0002", "shot.0010"]
    assert [len(fr.files) for fr in frames] == [3, 3, 2]
    assert frames[0].pattern == str(tmp_path / "shot.0001.seed*.exr")
    for bad, match in (("shot.seed*.exr", "mark the frame number"), ("shot.####.seed0.exr", "no glob for the seeds"),
                       ("none.####.s*.exr", "no file matches")):
        with pytest.raises(InputError, match=match):
            seed_set_frames(str(tmp_path / bad))


def test_batch_reconstructs_each_frame_as_its_seed_set_like_reconstruct(tmp_path, capsys):
    pytest.importorskip("distributed", reason="needs the dask extra: pip install 'mcrecon[dask]'")
    from mcrecon.distributed import cluster as D_cluster
    from mcrecon.io import read_exr

    for f in (1, 2):
        renders(tmp_path, 3, seed=f, name=f"shot.{f:04d}.seed{{}}.exr")
    renders(tmp_path, 1, seed=9, name="shot.0003.seed{}.exr")  # one render: that frame fails, the others not
    out = tmp_path / "out"
    with D_cluster.local_client(1, threads=1) as c:
        argv = ["batch", "--seed-sets", tmp_path / "shot.####.seed*.exr", "--mean", "R,G,B", "--method", "gem",
                "--out-dir", out, "--scheduler", c.scheduler.address, "--quiet"]
        code, stdout, err = run_cli(argv, capsys)
        assert code == 2 and "2 reconstructed" in stdout and "1 failed" in stdout
        assert "one render: a seed set is K >= 2" in err
        assert sorted(p.name for p in out.glob("*.exr")) == ["shot.0001.exr", "shot.0002.exr"]
        one = mcrecon.reconstruct(str(tmp_path / "shot.0001.seed*.exr"), method="gem", exr_options={"mean": "R,G,B"})
        np.testing.assert_array_equal(read_exr(out / "shot.0001.exr")[0], one.astype(np.float32))
        code, stdout, _ = run_cli(argv, capsys)
        assert "2 up to date" in stdout
    code, _, err = run_cli(["batch", "--out-dir", out], capsys)
    assert code == 2 and "no frame given" in err


def test_one_file_of_means_alone_serves_box_and_refuses_the_others(tmp_path):
    x, _ = renders(tmp_path, 1)
    one = str(tmp_path / "shot.seed0.exr")
    np.testing.assert_allclose(mcrecon.reconstruct(one, method="box", exr_options={"mean": "R,G,B"}), x[0])
    with pytest.raises(InputError, match="means alone \\(mean= without a variance\\) hold .* no variance, which "
                                         "gem needs; render the frame K >= 2 times"):
        mcrecon.reconstruct(one, method="gem", exr_options={"mean": "R,G,B"})
