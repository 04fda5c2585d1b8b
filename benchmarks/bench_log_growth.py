"""Sample-log growth: 400 rounds of 10 samples appended as the adaptive driver does.

Each round is appended with ``append_log`` (with its round record) and its
record then rewritten with ``update_round_record``, exactly as
``mcrecon.adaptive.run._run`` does, into a log created like the driver's (an empty
float32 RGB log plus run settings).  Prints, all measured in this run:

* the log size against the bytes of the samples (positions + values, 20 B
  per float32 RGB sample; the rounds are rows of ``/rounds/end``) and against samples + stored
  records (the JSON strings of ``/run/records``, or the rows of
  ``/run/round_records`` plus the JSON of ``/run/round_records_extra``),
  with a breakdown of where the bytes are (sample chunks, per-round
  datasets, global heap of the record strings, HDF5 object headers and
  B-tree nodes);
* the median append time (wall and CPU) of rounds 0-49 and of rounds
  350-399 and their ratio (flat = ~1; CPU time is the steadier number on a
  shared machine);
* all of this for the driver's records and for the larger records of a run
  that has a reference (error, eval_seconds);
* the same for the previous implementation, loaded from git
  (``--old-ref``, default HEAD) into a temporary module, if it differs from
  the installed one;
* with ``--variants``: the size with no records, with records that have a
  key outside the fixed columns, of a log that keeps JSON records
  (``/run/records``, written before format_minor 2) continued by this code,
  with 1024-row chunks for the per-round datasets, and with HDF5
  ``libver=('v110', 'latest')`` (files then need HDF5 >= 1.10 to read).

Targets (issue): size <= 2x the sample bytes if the HDF5 overhead allows it;
append time flat in the round index.  Numbers only, no assertions.

usage: python benchmarks/bench_log_growth.py [--rounds 400] [--samples 10] [--variants] [--old-ref REV]
"""

import argparse
import contextlib
import importlib.util
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np

from mcrecon.io import writer as samplelog  # the log writer: write_log, append_log, its chunk constants

W, H = 64, 64
SAMPLE_BYTES = 2 * 4 + 3 * 4  # float32 positions, float32 RGB values (the rounds: /rounds/end, one row per round)
PER_ROUND = ("rounds/end", "run/records", "run/round_records", "run/round_records_extra")


def run(mod, path, rounds, m, *, records=True, reference=False, extra_key=False, json_layout=False, seed=0):
    """Log ``rounds`` rounds of ``m`` samples like mcrecon.adaptive.run._run; return per-round seconds.

    ``extra_key``: every record also has a key outside the fixed columns.
    ``json_layout``: the log starts with an empty JSON ``/run/records``, as
    a log written before format_minor 2 (which is continued in that layout).
    """
    rng = np.random.default_rng(seed)
    settings = {"method": "box", "method_options": {}, "spp": rounds * m / (W * H), "seed": 0,
                "nonfinite": "drop", "time_limit": None, "width": W, "height": H, "channels": ["R", "G", "B"],
                "renderer": "bench", "renderer_spec": {}, "storage_dtype": "float32"}
    mod.write_log(path, np.zeros((0, 2), np.float32), np.zeros((0, 3), np.float32), width=W, height=H,
                  channels=("R", "G", "B"), metadata={"renderer": "bench", "seed": 0, "settings": settings})
    mod.set_run_settings(path, settings)
    if json_layout:
        with h5py.File(path, "r+") as f:
            f.create_dataset("run/records", shape=(0,), dtype=h5py.string_dtype("utf-8"), maxshape=(None,),
                             chunks=(256,))
            f.attrs["format_minor"] = 1
    t_append, t_update = np.zeros((rounds, 2)), np.zeros((rounds, 2))  # wall, CPU seconds
    wall0 = time.perf_counter()
    for r in range(rounds):
        pos = (rng.random((m, 2)) * [W, H]).astype(np.float32)
        val = rng.random((m, 3)).astype(np.float32)
        record = {"round": r, "samples": m, "samples_total": (r + 1) * m,
                  "renderer_seconds": float(rng.uniform(1e-4, 1e-3))}
        if extra_key:
            record["renderer_note"] = f"tile {r % 16}"
        t0, c0 = time.perf_counter(), time.process_time()
        if records:
            mod.append_log(path, pos, val, round_index=r, features=None,
                           round_record={**record, "toolkit_seconds": float(rng.uniform(1e-4, 1e-3)),
                                         "wall_seconds": time.perf_counter() - wall0})
        else:
            mod.append_log(path, pos, val, round_index=r)
        t1, c1 = time.perf_counter(), time.process_time()
        t_append[r] = t1 - t0, c1 - c0
        if records:
            record["toolkit_seconds"] = float(rng.uniform(1e-4, 1e-3))
            record["wall_seconds"] = time.perf_counter() - wall0
            if reference:
                record["error"] = float(rng.uniform(0.01, 1.0))
                record["eval_seconds"] = float(rng.uniform(1e-4, 1e-3))
            mod.update_round_record(path, record)
            t_update[r] = time.perf_counter() - t1, time.process_time() - c1
    return t_append, t_update


def breakdown(path):
    """Bytes by kind: raw chunks per dataset, object headers, B-tree/heap metadata, and the rest."""
    out = {"file": os.path.getsize(path), "raw": {}, "headers": 0, "btrees": 0, "local_heaps": 0,
           "record_payload": 0, "record_heap_objects": 0}
    with h5py.File(path, "r") as f:
        def visit(name, obj):
            info = h5py.h5o.get_info(obj.id)
            out["headers"] += info.hdr.space.total
            out["btrees"] += info.meta_size.obj.index_size + info.meta_size.attr.index_size
            out["local_heaps"] += info.meta_size.obj.heap_size + info.meta_size.attr.heap_size
            if isinstance(obj, h5py.Dataset):
                out["raw"][name] = obj.id.get_storage_size()
        visit("/", f)
        f.visititems(visit)
        lens = []
        for name in ("run/records", "run/round_records_extra"):
            if name in f:
                lens += [len(x) for x in f[name][...]]
        if "run/round_records" in f:
            d = f["run/round_records"]
            out["record_payload"] += d.shape[0] * d.dtype.itemsize
        out["record_payload"] += sum(lens)
        # a global-heap object: 16-byte header + payload padded to 8 bytes (empty strings: none)
        out["record_heap_objects"] = sum(16 + (n + 7) // 8 * 8 for n in lens if n)
    out["rest"] = (out["file"] - sum(out["raw"].values()) - out["headers"] - out["btrees"] - out["local_heaps"])
    return out


def report(label, path, rounds, m, t_append, t_update):
    b = breakdown(path)
    samples = rounds * m * SAMPLE_BYTES
    size = b["file"]
    print(f"[{label}]")
    print(f"  log size {size:,} B for {samples:,} B of samples: {size / samples:.2f}x the samples "
          f"(target <= 2x: {'met' if size <= 2 * samples else 'NOT met'}); stored records "
          f"{b['record_payload']:,} B; size / (samples + records) = {size / (samples + b['record_payload']):.2f}x")
    raw = b["raw"]
    sample_raw = sum(v for k, v in raw.items() if k in ("positions", "values", "round") or k.startswith("features"))
    per_round = sum(v for k, v in raw.items() if k in PER_ROUND)
    print(f"  breakdown: sample chunks {sample_raw:,} (" + ", ".join(
        f"{k} {v:,}" for k, v in raw.items() if k in ("positions", "values", "round")) + ")"
          f"; per-round datasets {per_round:,} (" + ", ".join(
        f"{k} {v:,}" for k, v in raw.items() if k in PER_ROUND) + ")"
          f"; object headers {b['headers']:,}; B-tree nodes {b['btrees']:,}; local heaps {b['local_heaps']:,}"
          f"; global heap + superblock + free {b['rest']:,} (record heap objects {b['record_heap_objects']:,})")
    if t_append is not None:
        for label, t in (("append_log", t_append), ("update_round_record", t_update)):
            if not t.any():
                continue
            (w0, c0), (w1, c1) = np.median(t[:50], axis=0), np.median(t[-50:], axis=0)
            print(f"  {label} median wall (CPU): rounds 0-49 {w0 * 1e3:.2f} ms ({c0 * 1e3:.2f}), rounds "
                  f"{rounds - 50}-{rounds - 1} {w1 * 1e3:.2f} ms ({c1 * 1e3:.2f}); ratio {w1 / w0:.2f} "
                  f"({c1 / c0:.2f})")
    return size


def load_old(ref):
    """A samplelog.py from git (refs before it was split into io/reader, writer, lock) as a temporary module, or None."""
    repo = Path(__file__).resolve().parents[1]
    try:
        src = subprocess.run(["git", "-C", str(repo), "show", f"{ref}:mcrecon/io/samplelog.py"],
                             capture_output=True, text=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError) as exc:
        print(f"[old code] not available from git {ref}: {exc}")
        return None
    if src == Path(samplelog.__file__).read_text():
        print(f"[old code] git {ref} holds the current samplelog.py; pass --old-ref REV to compare, e.g. "
              "5ba6377 (JSON records in a resizable /run/records) or 89ecc3e (before the resizable "
              "per-round datasets)")
        return None
    tmpdir = tempfile.mkdtemp(prefix="mcrecon_old_samplelog_")
    file = Path(tmpdir) / "samplelog_old.py"
    file.write_text(src)
    name = "mcrecon.io._bench_old_samplelog"  # inside mcrecon.io, so its relative imports resolve
    spec = importlib.util.spec_from_file_location(name, file)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    try:
        spec.loader.exec_module(mod)
    finally:
        shutil.rmtree(tmpdir, ignore_errors=True)  # loaded: the copy is not needed any more
    return mod


@contextlib.contextmanager
def libver(low):
    """Create and open logs with HDF5 libver (low, 'latest') for the duration."""
    orig = h5py.File

    class File(orig):
        def __init__(self, name, mode="r", *a, **k):
            if mode in ("w", "r+"):
                k.setdefault("libver", (low, "latest"))
            super().__init__(name, mode, *a, **k)

    h5py.File = File
    try:
        yield
    finally:
        h5py.File = orig


@contextlib.contextmanager
def patched(mod, **consts):
    old = {k: getattr(mod, k) for k in consts}
    for k, v in consts.items():
        setattr(mod, k, v)
    try:
        yield
    finally:
        for k, v in old.items():
            setattr(mod, k, v)


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--rounds", type=int, default=400)
    p.add_argument("--samples", type=int, default=10, help="samples per round")
    p.add_argument("--variants", action="store_true", help="also measure the size of layout variants")
    p.add_argument("--old-ref", default="HEAD", help="git revision of the previous samplelog.py")
    a = p.parse_args()
    rounds, m = a.rounds, a.samples
    tmp = Path(tempfile.mkdtemp(prefix="mcrecon_bench_growth_"))
    print(f"{rounds} rounds of {m} float32 RGB samples, append_log + update_round_record as the driver does; "
          f"h5py {h5py.__version__}, HDF5 {h5py.version.hdf5_version}")
    ta, tu = run(samplelog, tmp / "new.h5", rounds, m)
    new_size = report("current samplelog", tmp / "new.h5", rounds, m, ta, tu)
    ta, tu = run(samplelog, tmp / "ref.h5", rounds, m, reference=True)
    new_ref = report("current samplelog, records of a run with a reference (+error, eval_seconds)",
                     tmp / "ref.h5", rounds, m, ta, tu)
    old = load_old(a.old_ref)
    if old is not None:
        ta, tu = run(old, tmp / "old.h5", rounds, m)
        old_size = report(f"previous samplelog (git {a.old_ref})", tmp / "old.h5", rounds, m, ta, tu)
        print(f"  old / new size: {old_size / new_size:.2f}x")
        ta, tu = run(old, tmp / "old_ref.h5", rounds, m, reference=True)
        old_size = report(f"previous samplelog (git {a.old_ref}), records of a run with a reference",
                          tmp / "old_ref.h5", rounds, m, ta, tu)
        print(f"  old / new size: {old_size / new_ref:.2f}x")
    if a.variants:
        ta, tu = run(samplelog, tmp / "norec.h5", rounds, m, records=False)
        report("variant: no round records", tmp / "norec.h5", rounds, m, ta, tu)
        ta, tu = run(samplelog, tmp / "extra.h5", rounds, m, extra_key=True)
        report("variant: every record with a key outside the columns (/run/round_records_extra)",
               tmp / "extra.h5", rounds, m, ta, tu)
        ta, tu = run(samplelog, tmp / "json.h5", rounds, m, json_layout=True)
        report("variant: a log with JSON /run/records (format_minor 1) continued by this code",
               tmp / "json.h5", rounds, m, ta, tu)
        consts = {k: 1024 for k in ("RECORD_CHUNK_ROWS", "ROUND_RECORD_CHUNK_ROWS") if hasattr(samplelog, k)}
        with patched(samplelog, **consts):
            ta, tu = run(samplelog, tmp / "rc1024.h5", rounds, m)
        report("variant: 1024-row chunks for the per-round datasets", tmp / "rc1024.h5", rounds, m, ta, tu)
        with libver("v110"):
            ta, tu = run(samplelog, tmp / "v110.h5", rounds, m)
        report("variant: libver=('v110', 'latest') (needs HDF5 >= 1.10 to read)", tmp / "v110.h5", rounds, m,
               ta, tu)
    for f in tmp.iterdir():
        f.unlink()
    tmp.rmdir()


if __name__ == "__main__":
    main()
