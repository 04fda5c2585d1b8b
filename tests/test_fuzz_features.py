"""Fuzzing of the per-sample feature surface of sample logs (Hypothesis and a fixed corpus).

Logs whose ``/features/NAME`` datasets have odd dtypes (bool, integers, float16 to float128, big-endian,
strings, compound), widths (0, 1, 3, 64, 65 components, billions declared and never written), shapes
(rows short or long, scalars, (N, 2, 2)), values (NaN, "no hit" sentinels) and links (soft, dangling,
looping, external to a missing or a present file) go through ``mcrecon info``, ``reconstruct`` with
every method and ``batch``, in a worker process under a memory limit, so an allocation bomb shows as a
failure rather than killing the run.  Each must end in exit 2 with exactly one error line on stderr, or
in exit 0 with a finite image: never a traceback, a hang or a crash.

A fixed seed (derandomized), small logs and a small example budget keep it to seconds once numba's
kernels are cached; set ``MCRECON_FULL=1`` for a larger budget.
"""

import os
import shutil
import tempfile
from pathlib import Path

import h5py
import numpy as np
import pytest

hypothesis = pytest.importorskip("hypothesis", reason="needs hypothesis: pip install -e '.[test]'")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from mcrecon.io import append_log, read_exr, write_log  # noqa: E402
from helpers import CliWorker  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
FULL = os.environ.get("MCRECON_FULL", "") not in ("", "0")
METHODS = ("box", "gem", "awr", "splat", "ci", "auto", "nfor")
W, H = 6, 5

@pytest.fixture(scope="module")
def worker():
    w = CliWorker(memory_limit=16 << 30, timeout=120.0)
    yield w
    w.close()


@pytest.fixture(scope="module")
def base_log(tmp_path_factory):
    """Two rounds, 3 spp, albedo (N, 3) float64 and depth (N,) float32, and a reference."""
    rng = np.random.default_rng(5)
    path = tmp_path_factory.mktemp("fuzzf") / "base.h5"
    n, m = W * H * 2, W * H
    write_log(path, rng.random((n, 2)) * [W, H], rng.random((n, 3)).astype(np.float32), width=W, height=H,
              features={"depth": rng.random(n).astype(np.float32), "albedo": rng.random((n, 3))},
              reference=np.full((H, W, 3), 0.5), metadata={"renderer": "fuzz"})
    append_log(path, rng.random((m, 2)) * [W, H], rng.random((m, 3)),
               features={"depth": np.ones(m, np.float32), "albedo": np.full((m, 3), 0.5)})
    return path


DTYPES = ("bool", "i1", "u2", "i4", ">i2", "u8", "f2", "f4", "f8", "f16", ">f4", ">f8", "S3", "str", "compound")
#: None: (N,); "2x2": (N, 2, 2); "scalar": shape (); "huge": (N, 2e9) declared, nothing written
WIDTHS = (None, 0, 1, 3, 64, 65, "2x2", "scalar", "huge")
LINKS = ("soft", "dangling", "loop", "external_missing", "external")
NAMES = ("depth", "albedo", "normal", "x")


def _dtype(key):
    if key == "f16":
        return np.dtype(np.longdouble)
    if key == "str":
        return h5py.string_dtype()
    if key == "compound":
        return np.dtype([("a", "<f4"), ("b", "<i2")])
    return np.dtype(key)


def _data(dtype, shape, values, rng):
    if dtype.kind in "SO":
        return np.full(shape, b"abc", dtype=dtype if dtype.kind == "S" else object)
    if dtype.kind == "V":
        return np.zeros(shape, dtype)
    if dtype.kind == "b":
        return rng.random(shape) > 0.5
    if dtype.kind in "iu":
        return rng.integers(0, 100, shape).astype(dtype)
    x = rng.random(shape).astype(dtype)
    if values == "nan" and x.size:
        x.flat[::5] = np.nan
        x.flat[1::7] = np.inf
    elif values == "sentinel" and x.size:
        x.flat[::3] = np.finfo(dtype).max
    return x


def _feature_mutation():
    return st.tuples(st.just("feature"), st.sampled_from(NAMES), st.sampled_from(DTYPES), st.sampled_from(WIDTHS),
                     st.sampled_from([0, 0, 0, 7, -1]), st.sampled_from(["random", "nan", "sentinel"]))


def _mutation():
    return st.one_of(
        _feature_mutation(), _feature_mutation(),
        st.tuples(st.just("link"), st.sampled_from(NAMES), st.sampled_from(LINKS)),
        st.tuples(st.just("delete"), st.sampled_from(NAMES)),
    )


def _apply(path: Path, mutation, rng):
    kind, name = mutation[:2]
    with h5py.File(path, "r+") as f:
        n = int(f.attrs["n_committed"])
        g = f.require_group("features")
        if name in g or g.get(name, getlink=True) is not None:
            del g[name]
        if kind == "delete":
            return
        if kind == "link":
            link = mutation[2]
            if link == "soft":
                if "depth" in g and name != "depth":
                    g[name] = h5py.SoftLink("/features/depth")
            elif link == "dangling":
                g[name] = h5py.SoftLink("/nowhere")
            elif link == "loop":
                g[name] = h5py.SoftLink(f"/features/{name}")
            elif link == "external_missing":
                g[name] = h5py.ExternalLink("missing.h5", "/d")
            else:
                other = path.with_name("ext.h5")
                with h5py.File(other, "w") as e:
                    e["d"] = rng.random(n).astype(np.float32)
                g[name] = h5py.ExternalLink(str(other), "/d")
            return
        _, _, dkey, width, rows, values = mutation
        dtype, rows = _dtype(dkey), max(n + rows, 0)
        if width == "scalar":
            g.create_dataset(name, data=_data(dtype, (), values, rng))
        elif width == "huge":  # declared, never written: the file stays small
            g.create_dataset(name, shape=(rows, 2_000_000_000), dtype=dtype, chunks=(1, 1 << 14))
        else:
            shape = (rows,) if width is None else (rows, 2, 2) if width == "2x2" else (rows, width)
            g.create_dataset(name, data=_data(dtype, shape, values, rng))


def _check(worker, path: Path, out_dir: Path, methods=METHODS):
    runs = [["info", path]] + [["reconstruct", path, "--method", m, "-o", out_dir / f"{m}.exr"] for m in methods]
    for argv in runs:
        r = worker.run(argv)
        what = f"{' '.join(map(str, argv[:1] + argv[2:4]))}: {r['code']}: {r['err']}"
        assert r["code"] in (0, 2), what
        assert "Traceback" not in r["err"], what
        if r["code"] == 2:
            assert r["err"].count("\n") == 1 and r["err"].startswith("mcrecon: error: "), what
        else:
            assert "error" not in r["err"], what
            if argv[0] == "reconstruct":
                img, _ = read_exr(argv[-1])
                assert np.isfinite(img).all(), what


def _fuzz(worker, base_log, mutations, methods=METHODS):
    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "f.h5"
        shutil.copyfile(base_log, path)
        for m in mutations:
            _apply(path, m, rng)
        _check(worker, path, Path(tmp), methods)


@settings(max_examples=40 if FULL else 8, derandomize=True, deadline=None, database=None,
          suppress_health_check=list(HealthCheck))
@given(mutations=st.lists(_mutation(), min_size=1, max_size=3))
def test_logs_with_fuzzed_features_give_one_line_or_a_finite_image(worker, base_log, mutations):
    _fuzz(worker, base_log, mutations)


#: One log per dtype, width and link kind, each with a single odd feature (the random draws above combine
#: them); each goes through info and one method, the methods in turn (nfor, which reads every feature,
#: and auto besides).
CORPUS = ([("feature", "x", d, 3, 0, "random") for d in DTYPES]
          + [("feature", "depth", "f4", w, 0, "sentinel") for w in WIDTHS]
          + [("feature", "albedo", "f8", 3, r, "nan") for r in (7, -1)]
          + [("link", "x", k) for k in LINKS]
          + [("feature", "x", d, "huge", 0, "random") for d in ("bool", "f2", "S3", "compound")])


def test_a_corpus_of_single_odd_features_gives_one_line_or_a_finite_image(worker, base_log):
    for i, m in enumerate(CORPUS):
        _fuzz(worker, base_log, [m], methods=(METHODS[i % len(METHODS)],) + (("nfor",) if i % 2 else ()))


def test_batch_names_each_refused_log_in_one_line(worker, base_log, tmp_path):
    """``batch`` over logs with odd features: a finite EXR for each log it reconstructs, one error line for
    each it refuses (naming that log), no traceback."""
    rng = np.random.default_rng(1)
    logs = []
    for i, m in enumerate(CORPUS[::3]):
        path = tmp_path / f"c{i:02d}.h5"
        shutil.copyfile(base_log, path)
        _apply(path, m, rng)
        logs.append(path)
    out = tmp_path / "out"
    r = worker.run(["batch", *logs, "--out-dir", out, "--method", "auto", "--workers", "1", "--quiet"], timeout=300)
    assert r["code"] in (0, 2) and "Traceback" not in r["err"], r
    lines = r["err"].splitlines()
    assert all(ln.startswith("mcrecon: error: ") for ln in lines), r["err"]
    for log in logs:
        named = [ln for ln in lines if ln.startswith(f"mcrecon: error: {log}: ")]
        exr = out / f"{log.stem}.exr"
        if named:
            assert len(named) == 1 and not exr.exists(), (log, named)
        else:
            img, _ = read_exr(exr)
            assert np.isfinite(img).all(), log
    assert (r["code"] == 2) == bool(lines)
