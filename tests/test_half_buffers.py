"""Half-buffer pairs: two independent halves of the samples (dual buffers) in place of the samples.

The halves here are exactly the split ``auto`` makes of the samples
(:func:`mcrecon.core.halves.split_halves`), so a pair built from them must
give auto's image of the samples.  Two things differ when the pair comes
through EXRs, and each is tested on its own:

* the EXR holds float32 means and variances (no float64 EXR channels);
* statistics read from an EXR carry no per-pixel sample range
  (``has_range`` False), so auto's safeguard bounds each pixel by its
  neighbours' means instead of their samples' range.

With ``safeguard=None`` only the float32 rounding remains; with the
default safeguard the EXR pair equals the exact pair with its ranges
dropped, to the same rounding.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import mcrecon
from mcrecon import InputError, PixelStats, SampleSet
from mcrecon.core.halves import split_halves
from mcrecon.io import read_exr
from mcrecon.io.pixel_exr import read_half_buffer_exrs, xyz_from_rgb_matrix
from mcrecon.methods import get_method
from mcrecon.methods.base import MethodInputs
from mcrecon.core.halves import merge_halves

from helpers import run_cli

H, W = 20, 28
EPS64 = np.finfo(np.float64).eps
EPS32 = float(np.finfo(np.float32).eps)


def one_line_error(capsys, args):
    code, _, err = run_cli(args, capsys)
    assert code == 2 and err.count("\n") == 1 and err.startswith("mcrecon: error:"), err
    return err


def write_channels(path, channels: dict, **attrs):
    import OpenEXR

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage, **attrs}
    data = {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in channels.items()}
    with OpenEXR.File(header, data) as f:
        f.write(str(path))
    return path


def sample_set(spp, seed=0, channels=("R", "G", "B"), h=H, w=W):
    """Jittered samples of a smooth image with an edge and heavy-tailed noise; every pixel ``spp`` samples."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w]
    base = np.stack([0.5 + 0.4 * np.sin(xx / 3.0), 0.3 + 0.2 * yy / h, 0.2 + 0.6 * (xx > w // 2)], axis=-1)
    vals = base[:, :, None, :] * rng.gamma(3.0, 1 / 3.0, (h, w, spp, 3))
    px = xx[:, :, None] + rng.random((h, w, spp))
    py = yy[:, :, None] + rng.random((h, w, spp))
    pos = np.stack([px, py], axis=-1).reshape(-1, 2)
    order = rng.permutation(pos.shape[0])  # stream order mixes pixels (the split is per pixel, in order)
    return SampleSet(pos[order], vals.reshape(-1, 3)[order], width=w, height=h, channels=channels)


def moments(st: PixelStats):
    """(mean, variance of the samples, count) as a renderer writes them (variance 0 below 2 samples)."""
    return st.mean, st.sample_variance(ddof=1, undefined=0.0), st.count


def without_range(st: PixelStats) -> PixelStats:
    """The statistics an EXR can hold: no per-pixel sample range."""
    out = st.copy()
    out.has_range = False
    out.min[...] = np.where((out.count > 0)[..., None], np.nan, np.inf)
    out.max[...] = np.where((out.count > 0)[..., None], np.nan, -np.inf)
    return out


def quiet(fn, *a, **k):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return fn(*a, **k)


# ------------------------------------------------------------------ the split auto makes: same image
@pytest.mark.parametrize("spp", [8, 7])  # 7: every pixel's halves differ by one sample
def test_pair_of_autos_own_split_gives_the_image_of_the_samples(spp):
    ss = sample_set(spp, seed=spp)
    full = mcrecon.reconstruct(ss, method="auto", full=True)
    h = split_halves(ss)
    assert not np.array_equal(h.a.count, h.b.count) if spp % 2 else np.array_equal(h.a.count, h.b.count)
    pair = mcrecon.reconstruct((h.a, h.b), method="auto", full=True)
    # from samples the reader splits them once and merges the halves into the statistics of
    # all the samples (Chan), exactly as from the pair: the same image, bit for bit
    np.testing.assert_array_equal(pair.diagnostics()["choice"], full.diagnostics()["choice"])
    np.testing.assert_array_equal(pair.image, full.image)
    np.testing.assert_array_equal(mcrecon.restoration.auto((h.a, h.b)), full.image)
    np.testing.assert_array_equal(get_method("auto").reconstruct(MethodInputs(None, halves=[h.a, h.b])), full.image)
    assert pair.inputs.halves is not None and pair.inputs.stats.n_samples == ss.n_samples
    assert full.inputs.halves is not None and full.inputs.samples is not None
    np.testing.assert_array_equal(full.inputs.stats.mean, merge_halves(h.a, h.b).mean)
    # the halves are not modified by the merge
    assert h.a.n_samples + h.b.n_samples == ss.n_samples


def test_merged_statistics_equal_the_statistics_of_all_samples():
    """Chan's merge of the halves vs one Welford pass over every sample, to rounding.

    Both are sums of O(n) operations on values |x| <= M, each rounding by
    at most eps relative, so |d mean| <= c n eps M and, as m2 is a sum of
    squared deviations (|x - mean| <= 2M) whose first-order dependence on
    the mean vanishes, |d m2| <= c n eps (2M)^2; c = 8 is generous.
    """
    ss = sample_set(9, seed=3)
    h = split_halves(ss)
    merged = merge_halves(h.a, h.b)
    ref = PixelStats.from_source(ss)
    n, m = int(ref.count.max()), float(np.abs(ss.values).max())
    np.testing.assert_array_equal(merged.count, ref.count)
    np.testing.assert_allclose(merged.mean, ref.mean, rtol=0, atol=8 * n * EPS64 * m)
    np.testing.assert_allclose(merged.m2, ref.m2, rtol=0, atol=8 * n * EPS64 * (2 * m) ** 2)
    np.testing.assert_array_equal(merged.min, ref.min)
    np.testing.assert_array_equal(merged.max, ref.max)
    assert merged.has_range and merged.n_samples == ss.n_samples


# ------------------------------------------------------------------ EXR pairs
def pbrt_half(path, st: PixelStats):
    """A pbrt-v4 GBufferFilm-like EXR of one half: the samples are XYZ (pbrt's default sensor), the file
    holds the mean in sRGB and the variances of X, Y, Z; the count is the header's samplesPerPixel."""
    mean, var, count = moments(st)
    assert (count == count.flat[0]).all()  # pbrt writes one samplesPerPixel per file
    rgb = mean @ np.linalg.inv(xyz_from_rgb_matrix()).T
    ch = {c: rgb[..., i] for i, c in enumerate("RGB")}
    ch.update({f"Variance.{c}": var[..., i] for i, c in enumerate("RGB")})
    return write_channels(path, ch, samplesPerPixel=int(count.flat[0]))


def explicit_half(path, st: PixelStats):
    """An EXR with mean, variance-of-the-samples and per-pixel count channels (explicit mapping)."""
    mean, var, count = moments(st)
    ch = {f"C.{c}": mean[..., i] for i, c in enumerate("rgb")}
    ch.update({f"V.{c}": var[..., i] for i, c in enumerate("rgb")})
    ch["N"] = count.astype(np.float32)
    return write_channels(path, ch)


EXPLICIT = ["--mean", "C.r,C.g,C.b", "--variance-channels", "V.r,V.g,V.b", "--count", "N"]
CASES = {  # layout: (spp, channels of the samples, writer, flags, output conversion of an image of the samples)
    "pbrt-v4": (8, ("X", "Y", "Z"), pbrt_half, ["--layout", "pbrt-v4"],
                lambda img: img @ np.linalg.inv(xyz_from_rgb_matrix()).T),
    "explicit": (7, ("C.r", "C.g", "C.b"), explicit_half, EXPLICIT, lambda img: img),
}


def _read_options(flags):
    if flags[0] == "--layout":
        return {"layout": flags[1]}
    return {"mean": flags[1], "variance": flags[3], "count": flags[5]}


@pytest.mark.parametrize("layout", list(CASES))
def test_exr_pair_through_cli_and_python_gives_autos_image_of_the_samples(tmp_path, capsys, layout):
    spp, channels, writer, flags, to_out = CASES[layout]
    ss = sample_set(spp, seed=11, channels=channels)
    h = split_halves(ss)
    a, b = writer(tmp_path / "a.exr", h.a), writer(tmp_path / "b.exr", h.b)
    pa, pb = read_half_buffer_exrs(a, b, **_read_options(flags))
    # float32 storage of the moments (and pbrt's XYZ -> RGB -> XYZ round trip): relative ~ eps32
    m = float(np.abs(ss.values).max())
    tol32 = 16 * EPS32 * m
    for got, exact in ((pa.stats, h.a), (pb.stats, h.b)):
        np.testing.assert_array_equal(got.count, exact.count)
        np.testing.assert_allclose(got.mean, exact.mean, rtol=0, atol=tol32)

    for safeguard in ("none", None):  # None: the default (4.0)
        opts = {} if safeguard is None else {"safeguard": None}
        flag = [] if safeguard is None else ["--safeguard", "none"]
        out = tmp_path / f"out_{safeguard}.exr"
        code, stdout, err = run_cli(["denoise", a, "--half-buffer", b, "-o", out, "--method", "auto", *flags, *flag],
                                    capsys)
        assert code == 0, err
        assert "half-buffer pair" in err and "half-buffer pair" in stdout and f"{ss.n_samples} samples" in stdout
        img, names = read_exr(out)
        api = mcrecon.reconstruct((pa.stats, pb.stats), method="auto", full=True, **opts)
        # the command writes exactly the Python API's image of the pair, in the file's colours
        np.testing.assert_allclose(img, pa.output_image(api.image).astype(np.float32), rtol=1e-6, atol=1e-7)
        np.testing.assert_allclose(quiet(mcrecon.restoration.auto, (pa.stats, pb.stats), **opts), api.image,
                                   rtol=0, atol=0)
        if safeguard == "none":
            # no range used: the image of the samples, to the float32 rounding of the moments
            expect = mcrecon.reconstruct(ss, method="auto", full=True, **opts)
        else:
            # the safeguard's range comes from the neighbours' means (no sample range in an EXR)
            expect = mcrecon.reconstruct((without_range(h.a), without_range(h.b)), method="auto", full=True)
        np.testing.assert_array_equal(api.diagnostics()["choice"], expect.diagnostics()["choice"])
        # every candidate is a normalised weighted mean of the pixel means (weights from means and
        # variances perturbed by ~eps32 relative): a few eps32 of the value range, times a margin
        np.testing.assert_allclose(api.image, expect.image, rtol=0, atol=64 * EPS32 * m)
        np.testing.assert_allclose(img, to_out(expect.image), rtol=0, atol=256 * EPS32 * m)


def test_default_safeguard_with_sample_ranges_differs_only_by_the_range():
    """Why the EXR comparison above drops the range: with ranges the pair gives the samples' image
    exactly (first test); without, the clamp bounds move and some pixels change."""
    ss = sample_set(8, seed=11)
    h = split_halves(ss)
    with_range = mcrecon.reconstruct((h.a, h.b), method="auto")
    no_range = mcrecon.reconstruct((without_range(h.a), without_range(h.b)), method="auto")
    safe_off = [mcrecon.reconstruct(p, method="auto", safeguard=None)
                for p in ((h.a, h.b), (without_range(h.a), without_range(h.b)))]
    np.testing.assert_array_equal(safe_off[0], safe_off[1])  # nothing else reads the range
    assert not np.array_equal(with_range, no_range)


# ------------------------------------------------------------------ one EXR: auto's SURE candidates
def test_auto_on_one_exr_uses_its_sure_candidates_and_suggests_the_pair(tmp_path, capsys):
    ss = sample_set(8, seed=5, channels=("X", "Y", "Z"))
    st = PixelStats.from_source(ss)
    a = pbrt_half(tmp_path / "all.exr", st)
    out = tmp_path / "o.exr"
    code, _, err = run_cli(["denoise", a, "-o", out, "--method", "auto"], capsys)
    assert code == 0, err
    assert "--candidates box,gauss" in err and "--half-buffer" in err  # chosen for the user, and said so
    pix = mcrecon.io.read_pixel_stats_exr(a)
    expect = pix.output_image(mcrecon.reconstruct(pix.stats, method="auto", candidates="box,gauss"))
    np.testing.assert_allclose(read_exr(out)[0], expect.astype(np.float32), rtol=1e-6, atol=1e-7)
    # dual-buffer candidates asked for explicitly: refused, naming both ways out
    err = one_line_error(capsys, ["denoise", a, "-o", out, "--method", "auto", "--candidates", "box,nlm"])
    assert "--half-buffer" in err and "--candidates box,gauss" in err
    # the Python API makes the caller choose (no silent fallback)
    with pytest.raises(InputError, match="half-buffer pair"):
        mcrecon.reconstruct(pix.stats, method="auto")
    with pytest.raises(InputError, match=r"half-buffer pair \(stats_a, stats_b\); or candidates='box,gauss'"):
        mcrecon.restoration.auto(pix.stats)
    with pytest.raises(InputError, match="MethodInputs.halves"):
        get_method("auto").reconstruct(MethodInputs(pix.stats))


# ------------------------------------------------------------------ refusals
def test_methods_without_half_buffers_refuse_the_pair(tmp_path, capsys):
    ss = sample_set(8, seed=2, channels=("X", "Y", "Z"))
    h = split_halves(ss)
    a, b = pbrt_half(tmp_path / "a.exr", h.a), pbrt_half(tmp_path / "b.exr", h.b)
    for method in ("box", "gem"):
        err = one_line_error(capsys, ["denoise", a, "--half-buffer", b, "-o", tmp_path / "o.exr", "--method",
                                      method])
        assert f"{method} does not use half buffers" in err and "methods that do: auto" in err
    for call in (lambda: mcrecon.reconstruct((h.a, h.b), method="box"),
                 lambda: mcrecon.restoration.box((h.a, h.b))):
        with pytest.raises(InputError, match="does not use half buffers.*auto"):
            call()
    # below the registry a method names where the list is
    with pytest.raises(InputError, match="does not use half buffers.*half_buffer_methods"):
        get_method("gem").reconstruct(MethodInputs(None, halves=(h.a, h.b)))
    # a sample log holds the samples: --half-buffer does not apply
    code, _, err = run_cli(["render-log", "--scene", "soft_shadow", "--spp", "2", "--size", "8x8", "-o",
                            tmp_path / "l.h5"], capsys)
    assert code == 0, err
    err = one_line_error(capsys, ["denoise", tmp_path / "l.h5", "--half-buffer", b, "-o", tmp_path / "o.exr",
                                  "--method", "auto"])
    assert "--half-buffer" in err and ".exr" in err
    err = one_line_error(capsys, ["denoise", a, "--half-buffer", tmp_path / "l.h5", "-o", tmp_path / "o.exr",
                                  "--method", "auto"])
    assert "--half-buffer" in err and ".exr" in err


def test_mismatched_pairs_are_refused_in_one_line(tmp_path, capsys):
    ss = sample_set(8, seed=4, channels=("X", "Y", "Z"))
    h = split_halves(ss)
    small = split_halves(sample_set(8, seed=4, channels=("X", "Y", "Z"), h=H - 2, w=W))
    a = pbrt_half(tmp_path / "a.exr", h.a)
    b_small = pbrt_half(tmp_path / "b_small.exr", small.b)
    err = one_line_error(capsys, ["denoise", a, "--half-buffer", b_small, "-o", tmp_path / "o.exr",
                                  "--method", "auto"])
    assert "shape" in err and f"{W}x{H} vs {W}x{H - 2}" in err and "b_small.exr" in err
    # another layout (explicit-mapping channels, read as pbrt-v4): the missing channels are named
    e = explicit_half(tmp_path / "e.exr", h.b)
    err = one_line_error(capsys, ["denoise", a, "--half-buffer", e, "-o", tmp_path / "o.exr", "--method", "auto"])
    assert "e.exr" in err and ("layout" in err or "missing" in err)
    # Python: each field named
    other = PixelStats.from_moments(*moments(h.b), channels=("R", "G", "B"))
    cases = [((h.a, small.b), "shape"), ((h.a, other), "channels"), ((h.a, h.b, h.b), "halves"),
             ((h.a, "b.exr"), r"halves\[1\]"), ((h.a,), "halves"),
             ((h.a, PixelStats.from_source(ss, subpixels=4)), "subpixels")]
    for pair, field in cases:
        for call in (lambda: mcrecon.reconstruct(pair, method="auto"), lambda: mcrecon.restoration.auto(pair),
                     lambda: get_method("auto").reconstruct(MethodInputs(None, halves=pair))):
            with pytest.raises(InputError, match=field) as exc:
                call()
            assert "\n" not in str(exc.value)


def test_method_inputs_contract():
    ss = sample_set(6, seed=8)
    h = split_halves(ss)
    m = get_method("auto")
    assert m.requires.half_buffers and m.requires.samples
    assert get_method("auto", candidates="box,gauss").requires.half_buffers
    assert not get_method("box").requires.half_buffers
    with pytest.raises(InputError, match="not both"):
        m.reconstruct(MethodInputs(None, ss, halves=(h.a, h.b)))
    with pytest.raises(InputError, match="merge of the two halves"):
        m.reconstruct(MethodInputs(h.a, None, halves=(h.a, h.b)))
    inputs = MethodInputs(None, None, halves=(h.a, h.b))
    assert inputs.shape == (H, W, 3) and inputs.channels == ("R", "G", "B")
    # statistics given with the pair: used as they are (they must be the merge)
    merged = merge_halves(h.a, h.b)
    np.testing.assert_array_equal(m.reconstruct(MethodInputs(merged, None, halves=(h.a, h.b))),
                                  m.reconstruct(MethodInputs(None, halves=(h.a, h.b))))
    # SURE candidates on a pair: the merged statistics
    np.testing.assert_array_equal(mcrecon.reconstruct((h.a, h.b), method="auto", candidates="box,gauss"),
                                  mcrecon.reconstruct(merged, method="auto", candidates="box,gauss"))


def test_methods_command_lists_the_half_buffer_input(capsys):
    code, out, _ = run_cli(["methods", "auto"], capsys)
    assert code == 0 and "half-buffer pair" in out and "in place of the samples" in out
    code, out, _ = run_cli(["methods", "box"], capsys)
    assert code == 0 and "half-buffer pair" in out


# ------------------------------------------------------------------ the reader's one pass for auto
def test_every_path_to_the_same_samples_gives_auto_the_same_image(tmp_path):
    """An adaptive run's image, the image of its log, of the same samples in a SampleSet and
    through mcrecon.restoration: bit for bit (every path builds the halves and merges them)."""
    from mcrecon.adaptive.run import adapt
    from mcrecon.io import read_log
    from mcrecon.renderers.scenes import SceneRenderer

    log = tmp_path / "run.h5"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = adapt(SceneRenderer("caustic", width=24, height=20, seed=0), get_method("auto"), spp=12, seed=3,
                    log=log, progress=False)
        from_log = mcrecon.reconstruct(log, method="auto")
        lg = read_log(log)
        c = lg.read_all()
        ss = SampleSet(c.positions, c.values, width=lg.width, height=lg.height, channels=lg.channels)
        from_set = mcrecon.reconstruct(ss, method="auto")
        from_restoration = mcrecon.restoration.auto(ss)
    np.testing.assert_array_equal(res.image, from_log)
    np.testing.assert_array_equal(from_set, from_log)
    np.testing.assert_array_equal(from_restoration, from_log)


def test_samples_with_a_pair_not_split_from_them_are_refused():
    ss, other = sample_set(8, seed=1), sample_set(8, seed=2)
    h = split_halves(other)
    m = get_method("auto")
    with pytest.raises(InputError, match="not both"):
        m.reconstruct(MethodInputs(merge_halves(h.a, h.b), ss, None, "drop", (h.a, h.b)))


@pytest.mark.parametrize("policy", ["drop", "zero", "raise"])
def test_nonfinite_samples_through_the_one_pass_split_are_reported_once_with_the_file(tmp_path, policy):
    """auto reads a log through the split: the policy applies to all the samples, the one warning
    (or error) names the file and the total, the counts match gem's reader, and a bad sample still
    takes its turn in its pixel (the halves of the good samples do not depend on the bad ones)."""
    from mcrecon.io import write_log

    ss = sample_set(8, seed=5)
    val = np.array(ss.values, copy=True)
    rows = np.array([3, 40, 41, 700, 1201])
    val[rows, 0] = np.nan
    val[rows[:2], 1] = np.inf
    path = write_log(tmp_path / "bad.h5", ss.positions, val, width=W, height=H, channels=ss.channels)
    if policy == "raise":
        for method in ("auto", "gem"):
            with pytest.raises(InputError, match=r"bad\.h5: values: 5 sample"):
                mcrecon.reconstruct(path, method=method, nonfinite="raise")
        return
    got = {}
    for method in ("auto", "gem"):
        with warnings.catch_warnings(record=True) as w:
            warnings.simplefilter("always")
            got[method] = mcrecon.reconstruct(path, method=method, nonfinite=policy, full=True)
        msgs = [str(x.message) for x in w if "NaN or Inf" in str(x.message)]
        assert len(msgs) == 1 and msgs[0].startswith(str(path)) and ": values: 5 sample(s)" in msgs[0], msgs
    for field in ("n_dropped", "n_zeroed", "n_samples"):
        assert getattr(got["auto"].inputs.stats, field) == getattr(got["gem"].inputs.stats, field)
    if policy == "drop":
        h = got["auto"].inputs.halves
        ref = split_halves(ss)  # the same stream with good values: the same labels
        bad_pix = set((ss.positions[rows, 1].astype(int) * W + ss.positions[rows, 0].astype(int)).tolist())
        keep = np.ones(H * W, bool)
        keep[list(bad_pix)] = False
        for got_half, ref_half in ((h[0], ref.a), (h[1], ref.b)):
            np.testing.assert_array_equal(got_half.mean.reshape(H * W, -1)[keep],
                                          ref_half.mean.reshape(H * W, -1)[keep])
