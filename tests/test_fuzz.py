"""Property-based fuzzing of the sample-log boundary (Hypothesis).

Mutated logs (random bytes, truncation, attributes of other types and
values, datasets of other shapes and dtypes, huge films) go through
``mcrecon info`` and ``mcrecon denoise`` in a worker process, so a crash of
the HDF5 library would show as a failure instead of killing the test run.
Each must end in exit 2 with one error line, or in success with a finite
image: never a traceback, a hang or a crash.

A fixed seed (derandomized) and a small example budget by default; set
``MCRECON_FULL=1`` for a larger budget (the ``slow`` test).
"""

import os
import shutil
import sys
import tempfile
import warnings
from pathlib import Path

import h5py
import numpy as np
import pytest

hypothesis = pytest.importorskip("hypothesis", reason="needs hypothesis, in the test extra: pip install -e '.[test]'")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from mcrecon.io import append_log, read_exr, write_log  # noqa: E402
from helpers import CliWorker  # noqa: E402

FULL = os.environ.get("MCRECON_FULL", "") not in ("", "0")

@pytest.fixture(scope="module")
def worker():
    w = CliWorker()
    yield w
    w.close()


@pytest.fixture(scope="module")
def base_log(tmp_path_factory):
    rng = np.random.default_rng(3)
    path = tmp_path_factory.mktemp("fuzz") / "base.h5"
    w, h, n = 8, 6, 600
    write_log(path, rng.random((n, 2)) * [w, h], rng.random((n, 3)).astype(np.float32), width=w, height=h,
              features={"depth": rng.random(n).astype(np.float32)}, reference=np.ones((h, w, 3)),
              metadata={"renderer": "fuzz"})
    append_log(path, rng.random((50, 2)) * [w, h], rng.random((50, 3)), features={"depth": np.ones(50)},
               round_record={"round": 1, "samples": 50, "note": "x"})
    return path


ATTRS = ("width", "height", "channels", "format_version", "format_minor", "n_committed", "metadata_json", "format")
ATTR_VALUES = st.one_of(
    st.integers(-2**63, 2**63 - 1), st.sampled_from([0, 1, -1, 10**9, 2**31, 2**62]),
    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=12),
    st.lists(st.text(max_size=4), max_size=4).map(lambda v: np.array(v, dtype=h5py.string_dtype())),
    st.lists(st.integers(-5, 5), min_size=0, max_size=3).map(np.array),
)
DATASETS = ("positions", "values", "round", "rounds/end", "features/depth", "reference", "run/round_records")
SHAPES = st.lists(st.integers(0, 700), min_size=0, max_size=3).map(tuple)
DTYPES = st.sampled_from(["f4", "f8", "i4", "u1", "bool", "S3"])


def _mutation():
    return st.one_of(
        st.tuples(st.just("bytes"), st.floats(0, 1), st.binary(min_size=1, max_size=64)),
        st.tuples(st.just("truncate"), st.floats(0, 1), st.just(b"")),
        st.tuples(st.just("attr"), st.sampled_from(ATTRS), ATTR_VALUES),
        st.tuples(st.just("dataset"), st.sampled_from(DATASETS), st.tuples(SHAPES, DTYPES)),
        st.tuples(st.just("huge"), st.sampled_from([(10**9, 10**9), (2**40, 1), (1, 2**33)]), st.just(None)),
    )


def _apply(path, mutation):
    kind, where, what = mutation
    if kind in ("bytes", "truncate"):
        size = path.stat().st_size
        if size == 0:
            return  # truncated to nothing already
        at = min(int(where * size), size - 1)
        with open(path, "r+b") as fh:
            if kind == "truncate":
                fh.truncate(at)
            else:
                fh.seek(at)
                fh.write(what)
        return
    with h5py.File(path, "r+") as f:
        if kind == "attr":
            f.attrs[where] = what
        elif kind == "huge":
            f.attrs["width"], f.attrs["height"] = where
        else:
            shape, dtype = what
            del f[where]
            f.create_dataset(where, data=np.ones(shape, dtype=dtype) if dtype != "S3" else np.full(shape, b"abc"))


def _check(worker, path, out_dir):
    for argv in (["info", path], ["denoise", path, "-o", out_dir / "o.exr", "--png", out_dir / "o.png"]):
        r = worker.run(argv)
        code, err = r["code"], r["err"]
        assert code in (0, 2), f"{argv[0]}: {code}: {err}"
        assert "Traceback" not in err, err
        errors = [ln for ln in err.splitlines() if "error" in ln]
        if code == 2:
            assert len(errors) == 1 and err.endswith("\n") and errors[0].startswith("mcrecon: error: "), err
        else:
            assert not errors, err
            if argv[0] == "denoise":
                img, _ = read_exr(out_dir / "o.exr")
                assert np.isfinite(img).all()


def _fuzz(worker, base_log, mutations):
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "m.h5"
        shutil.copyfile(base_log, path)
        for m in mutations:
            try:
                _apply(path, m)
            except (OSError, ValueError, TypeError, KeyError, RuntimeError):
                pass  # a mutation h5py refuses to make (or a file too damaged to mutate further)
        _check(worker, path, Path(tmp))


@settings(max_examples=25, derandomize=True, deadline=None, database=None,
          suppress_health_check=list(HealthCheck))
@given(mutations=st.lists(_mutation(), min_size=1, max_size=3))
def test_mutated_logs_give_one_line_or_a_finite_image(worker, base_log, mutations):
    _fuzz(worker, base_log, mutations)


@pytest.mark.slow
@settings(max_examples=400 if FULL else 60, derandomize=True, deadline=None, database=None,
          suppress_health_check=list(HealthCheck))
@given(mutations=st.lists(_mutation(), min_size=1, max_size=4))
def test_mutated_logs_larger_budget(worker, base_log, mutations):
    _fuzz(worker, base_log, mutations)


def test_the_untouched_base_log_succeeds(worker, base_log, tmp_path):
    _check(worker, base_log, tmp_path)


# ------------------------------------------------------------------ renderer replies (in process)
from mcrecon.errors import InputError, RendererError  # noqa: E402
from mcrecon.core.requests import SampleBatch, SampleRequest, validate_reply  # noqa: E402

W, H = 4, 3
COUNTS = np.array([[1, 0, 2, 1], [0, 3, 1, 0], [1, 1, 0, 2]], np.int64)
REQ_POS = np.array([[0.25, 0.5], [3.5, 2.75]])
_FLOATS = st.one_of(st.floats(-10, 10), st.sampled_from([np.nan, np.inf, -np.inf, 1e308, -0.0, 3.9999999, 4.0]))


def _good_reply(request, rng):
    pix = np.repeat(np.arange(W * H), request.counts.ravel()) if request.counts is not None else np.zeros(0, int)
    pos = np.stack([pix % W, pix // W], 1) + rng.random((pix.size, 2))
    if request.positions is not None:
        pos = np.concatenate([pos, request.positions])
    return pos, rng.random((len(pos), 3))


def _reply_mutation():
    return st.one_of(
        st.tuples(st.just("set"), st.sampled_from(["positions", "values"]), st.integers(0, 40), st.integers(0, 2),
                  _FLOATS),
        st.tuples(st.just("shape"), st.sampled_from(["positions", "values"]),
                  st.lists(st.integers(0, 12), max_size=3).map(tuple), st.just(0), st.just(0.0)),
        st.tuples(st.just("dtype"), st.sampled_from(["positions", "values"]),
                  st.sampled_from(["f4", "f2", "i8", "u1", "bool", "c16", "O", "U3", "M8[s]"]), st.just(0), st.just(0.0)),
        st.tuples(st.just("truncate"), st.sampled_from(["positions", "values"]), st.integers(0, 20), st.just(0),
                  st.just(0.0)),
        st.tuples(st.just("feature"), st.sampled_from(["depth", "", "a/b"]),
                  st.sampled_from(["ok", "short", "scalar", "str", "obj", "2d"]), st.just(0), st.just(0.0)),
        st.tuples(st.just("type"), st.sampled_from(["none", "list", "tuple1", "tuple4", "ragged", "dict"]),
                  st.just(0), st.just(0), st.just(0.0)),
    )


def _mutate_reply(pos, val, feats, m):
    kind, a, b, c, x = m
    arrs = {"positions": pos, "values": val}
    if kind == "set" and arrs[a].size:
        arr = np.array(arrs[a], dtype=np.float64)
        arr.reshape(-1, arr.shape[-1] if arr.ndim > 1 else 1)[b % max(1, arr.shape[0]), c % arr.shape[-1]
                                                                if arr.ndim > 1 else 0] = x
        arrs[a] = arr
    elif kind == "shape":
        arrs[a] = np.ones(b, dtype=np.float64) * 0.5
    elif kind == "dtype":
        try:
            with warnings.catch_warnings():  # NaN to integers and the like: whatever numpy makes of it
                warnings.simplefilter("ignore", RuntimeWarning)
                arrs[a] = np.asarray(arrs[a]).astype(b)
        except (TypeError, ValueError):
            pass
    elif kind == "truncate":
        arrs[a] = np.asarray(arrs[a])[: b]
    elif kind == "feature":
        n = len(np.asarray(arrs["positions"]))
        feats[a] = {"ok": np.ones(n), "short": np.ones(max(n - 1, 0)), "scalar": np.float64(1.0),
                    "str": np.array(["x"] * n), "obj": np.array([None] * n, dtype=object), "2d": np.ones((n, 2, 2))}[b]
    elif kind == "type":
        return {"none": None, "list": [arrs["positions"], arrs["values"]],
                "tuple1": (arrs["positions"],), "tuple4": (1, 2, 3, 4),
                "ragged": ([[0.5, 0.5], [1.5]], arrs["values"]), "dict": dict(arrs)}[a], feats
    return (arrs["positions"], arrs["values"]), feats


def _check_reply(request, reply):
    try:
        batch = validate_reply(request, reply, n_channels=3, renderer="fuzz")
    except RendererError as exc:
        assert "\n" not in str(exc) and str(exc), repr(exc)
        return
    pos = np.asarray(batch.positions)
    assert pos.shape == (request.total, 2) and np.isfinite(pos).all()
    assert (pos >= 0).all() and (pos[:, 0] < W).all() and (pos[:, 1] < H).all()
    assert np.asarray(batch.values).shape[0] == request.total


def _reply_fuzz(use_counts, use_positions, seed, mutations):
    request = SampleRequest(W, H, counts=COUNTS if use_counts or not use_positions else None,
                            positions=REQ_POS if use_positions else None, round_index=1, seed=seed)
    pos, val = _good_reply(request, np.random.default_rng(seed))
    reply, feats = (pos, val), {}
    for m in mutations:
        if not isinstance(reply, tuple) or len(reply) != 2:
            break
        try:
            with warnings.catch_warnings():  # complex to real, NaN to integers: whatever numpy makes of it
                warnings.simplefilter("ignore")
                reply, feats = _mutate_reply(*reply, feats, m)
        except (ValueError, IndexError, TypeError, AttributeError):
            pass  # a mutation that does not apply to what the earlier ones made
    if isinstance(reply, tuple) and len(reply) == 2 and feats:
        reply = SampleBatch(reply[0], reply[1], feats)
    _check_reply(request, reply)


REPLY_ARGS = dict(use_counts=st.booleans(), use_positions=st.booleans(), seed=st.integers(0, 2**32 - 1))


@settings(max_examples=150, derandomize=True, deadline=None, database=None, suppress_health_check=list(HealthCheck))
@given(mutations=st.lists(_reply_mutation(), min_size=0, max_size=3), **REPLY_ARGS)
def test_mutated_replies_give_a_renderer_error_or_finite_samples(use_counts, use_positions, seed, mutations):
    _reply_fuzz(use_counts, use_positions, seed, mutations)


@pytest.mark.slow
@settings(max_examples=3000 if FULL else 600, derandomize=True, deadline=None, database=None,
          suppress_health_check=list(HealthCheck))
@given(mutations=st.lists(_reply_mutation(), min_size=0, max_size=5), **REPLY_ARGS)
def test_mutated_replies_larger_budget(use_counts, use_positions, seed, mutations):
    _reply_fuzz(use_counts, use_positions, seed, mutations)


# ------------------------------------------------------------------ request files (command protocol)
from mcrecon.renderers.command import read_request, write_request  # noqa: E402

REQ_ATTRS = ("format", "format_version", "width", "height", "round", "seed", "n_total", "channels")


def _request_mutation():
    return st.one_of(
        st.tuples(st.just("attr"), st.sampled_from(REQ_ATTRS), ATTR_VALUES),
        st.tuples(st.just("delattr"), st.sampled_from(REQ_ATTRS), st.just(None)),
        st.tuples(st.just("dataset"), st.sampled_from(["counts", "positions"]),
                  st.tuples(st.lists(st.integers(0, 6), max_size=3).map(tuple), DTYPES)),
        st.tuples(st.just("huge"), st.sampled_from([(10**9, 10**9), (2**40, 1), (0, 3), (-1, 3)]), st.just(None)),
    )


def _request_fuzz(tmp_dir, mutations):
    path = Path(tmp_dir) / "r.h5"
    write_request(path, SampleRequest(W, H, counts=COUNTS, positions=REQ_POS, round_index=1, seed=5), channels="RGB")
    for m in mutations:  # attribute and dataset edits through h5py (raw bytes are fuzzed in a worker above)
        try:
            if m[0] == "delattr":
                with h5py.File(path, "r+") as f:
                    del f.attrs[m[1]]
            else:
                _apply(path, m)
        except (OSError, ValueError, TypeError, KeyError, RuntimeError):
            pass
    try:
        req = read_request(path)
    except InputError as exc:
        assert "\n" not in str(exc) and str(path) in str(exc), repr(exc)
        return
    assert req.width >= 1 and req.height >= 1 and req.total >= 0
    if req.positions is not None:
        assert np.isfinite(req.positions).all()


@settings(max_examples=100, derandomize=True, deadline=None, database=None, suppress_health_check=list(HealthCheck))
@given(mutations=st.lists(_request_mutation(), min_size=1, max_size=3))
def test_mutated_request_files_give_one_line_or_a_valid_request(mutations):
    with tempfile.TemporaryDirectory() as tmp:
        _request_fuzz(tmp, mutations)


@pytest.mark.slow
@settings(max_examples=2000 if FULL else 400, derandomize=True, deadline=None, database=None,
          suppress_health_check=list(HealthCheck))
@given(mutations=st.lists(_request_mutation(), min_size=1, max_size=5))
def test_mutated_request_files_larger_budget(mutations):
    with tempfile.TemporaryDirectory() as tmp:
        _request_fuzz(tmp, mutations)


# ------------------------------------------------------------------ pixel-statistics EXR inputs (worker)
EXR_CHANNELS = ("R", "G", "B", "Variance.R", "Variance.G", "Variance.B", "Albedo.R", "N.X")
EXR_VALUES = st.sampled_from([np.nan, np.inf, -np.inf, -1.0, 0.0, 1e-30, 1e30, 65504.0, 7.0])
EXR_DTYPES = st.sampled_from(["f4", "f2", "u4"])
EXR_ATTR_VALUES = st.one_of(st.integers(-2**31, 2**31 - 1), st.sampled_from([0, 1, -1, 2**31 - 1]),
                            st.floats(allow_nan=True, allow_infinity=True, width=32), st.text(max_size=8))


def _exr_mutation():
    return st.one_of(
        st.tuples(st.just("bytes"), st.floats(0, 1), st.binary(min_size=1, max_size=32)),
        st.tuples(st.just("truncate"), st.floats(0, 1), st.just(b"")),
        st.tuples(st.just("value"), st.sampled_from(EXR_CHANNELS), st.tuples(EXR_VALUES, st.booleans())),
        st.tuples(st.just("drop"), st.sampled_from(EXR_CHANNELS), st.just(None)),
        st.tuples(st.just("dtype"), st.sampled_from(EXR_CHANNELS), EXR_DTYPES),
        st.tuples(st.just("spp"), st.just("samplesPerPixel"), EXR_ATTR_VALUES),
    )


def _exr_channels(seed=5, h=6, w=8):
    rng = np.random.default_rng(seed)
    ch = {c: rng.random((h, w)).astype(np.float32) for c in EXR_CHANNELS}
    return ch, {"samplesPerPixel": 16}


def _write_exr(path, channels, attrs):
    import OpenEXR

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage, **attrs}
    with OpenEXR.File(header, {k: np.ascontiguousarray(v) for k, v in channels.items()}) as f:
        f.write(str(path))


def _exr_fuzz(worker, mutations, commands=(0, 1, 2)):
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        path = tmp / "in.exr"
        channels, attrs = _exr_channels()
        raw, dtypes = [], {}
        for kind, where, what in mutations:  # structured edits first, then raw bytes of the written file
            if kind in ("value", "dtype") and where not in channels:
                continue  # the channel was dropped by an earlier mutation
            if kind == "value":
                value, everywhere = what
                if everywhere:
                    channels[where] = np.full_like(channels[where], value)
                else:
                    channels[where] = channels[where].copy()
                    channels[where][2, 3] = value
            elif kind == "drop":
                channels.pop(where, None)
            elif kind == "dtype":
                dtypes[where] = what  # applied when the file is written (values stay float until then)
            elif kind == "spp":
                attrs[where] = what
            else:
                raw.append((kind, where, what))
        for name, dt in dtypes.items():
            if name in channels:
                x = channels[name]
                if np.dtype(dt).kind == "u":  # what an integer channel can hold
                    x = np.clip(np.nan_to_num(x, nan=0.0, posinf=2**32 - 1, neginf=0.0), 0, 2**32 - 1)
                with np.errstate(over="ignore", invalid="ignore"):
                    channels[name] = x.astype(dt)
        try:
            _write_exr(path, channels, attrs)
        except Exception:  # noqa: BLE001 - a file OpenEXR refuses to write is no input
            return
        for m in raw:
            _apply(path, m)
        argvs = (["denoise", path, "-o", tmp / "o.exr", "--method", "box"],
                 ["denoise", path, "-o", tmp / "o.exr", "--layout", "pbrt-v4", "--method", "gem"],
                 ["denoise", path, "-o", tmp / "o.exr", "--mean", "R,G,B", "--variance",
                  "Variance.R,Variance.G,Variance.B", "--spp", "4", "--method", "awr"])
        for argv in (argvs[k] for k in commands):
            r = worker.run(argv)
            code, err = r["code"], r["err"]
            assert code in (0, 2), f"{argv}: {code}: {err}"
            assert "Traceback" not in err, err
            errors = [ln for ln in err.splitlines() if "error" in ln]
            if code == 2:
                assert len(errors) == 1 and errors[0].startswith("mcrecon: error: "), err
            else:
                assert not errors, err
                img, _ = read_exr(tmp / "o.exr")
                assert np.isfinite(img).all(), argv


def test_the_untouched_base_exr_denoises(worker):
    _exr_fuzz(worker, [])
    with tempfile.TemporaryDirectory() as tmp:  # and it really is accepted (not refused with one line)
        path = Path(tmp) / "in.exr"
        _write_exr(path, *_exr_channels())
        r = worker.run(["denoise", path, "-o", Path(tmp) / "o.exr", "--method", "gem"])
        assert r["code"] == 0, r


@settings(max_examples=25, derandomize=True, deadline=None, database=None, suppress_health_check=list(HealthCheck))
@given(mutations=st.lists(_exr_mutation(), min_size=1, max_size=3), command=st.integers(0, 2))
def test_mutated_pixel_statistics_exrs_give_one_line_or_a_finite_image(worker, mutations, command):
    _exr_fuzz(worker, mutations, (command,))


@pytest.mark.slow
@settings(max_examples=400 if FULL else 60, derandomize=True, deadline=None, database=None,
          suppress_health_check=list(HealthCheck))
@given(mutations=st.lists(_exr_mutation(), min_size=1, max_size=4))
def test_mutated_pixel_statistics_exrs_larger_budget(worker, mutations):
    _exr_fuzz(worker, mutations)


# ------------------------------------------------------------------ reply files (command protocol, in process)
from mcrecon.renderers.command import CommandRenderer  # noqa: E402

_COPY = "import shutil, sys; shutil.copyfile(sys.argv[1], sys.argv[2])"


def _reply_file_fuzz(tmp_dir, mutations, use_positions):
    tmp_dir = Path(tmp_dir)
    tmp_dir.mkdir(parents=True, exist_ok=True)
    request = SampleRequest(W, H, counts=COUNTS, positions=REQ_POS if use_positions else None, round_index=1,
                            seed=5)
    pos, val = _good_reply(request, np.random.default_rng(2))
    src = tmp_dir / "made.h5"
    write_log(src, pos, val, width=W, height=H,
              features={"depth": np.arange(request.total, dtype=np.float32)})
    for m in mutations:
        try:
            _apply(src, m)
        except (OSError, ValueError, TypeError, KeyError, RuntimeError):
            pass
    r = CommandRenderer([sys.executable, "-c", _COPY, str(src), "{reply}", "{request}"], width=W, height=H,
                        workdir=tmp_dir / "work")
    try:
        batch = r.render(request)
        batch = validate_reply(request, batch, n_channels=3)
    except (RendererError, InputError) as exc:
        assert "\n" not in str(exc), repr(exc)
        return
    assert len(batch.positions) == request.total and np.isfinite(batch.positions).all()
    return batch


def test_the_untouched_reply_file_is_accepted_with_its_features(tmp_path):
    for use_positions in (False, True):
        batch = _reply_file_fuzz(tmp_path / str(use_positions), [], use_positions)
        assert batch is not None and batch.features["depth"].shape == (len(batch.positions),)


@settings(max_examples=30, derandomize=True, deadline=None, database=None, suppress_health_check=list(HealthCheck))
@given(mutations=st.lists(_mutation(), min_size=1, max_size=3), use_positions=st.booleans())
def test_mutated_reply_files_give_a_renderer_error_or_valid_samples(mutations, use_positions):
    with tempfile.TemporaryDirectory() as tmp:
        _reply_file_fuzz(tmp, mutations, use_positions)


@pytest.mark.slow
@settings(max_examples=400 if FULL else 60, derandomize=True, deadline=None, database=None,
          suppress_health_check=list(HealthCheck))
@given(mutations=st.lists(_mutation(), min_size=1, max_size=4), use_positions=st.booleans())
def test_mutated_reply_files_larger_budget(mutations, use_positions):
    with tempfile.TemporaryDirectory() as tmp:
        _reply_file_fuzz(tmp, mutations, use_positions)
