"""The batch command's frames: the workers it starts, names taken literally before as patterns, and
outputs that are damaged or of another size redone."""

from __future__ import annotations

import contextlib
import json

import numpy as np
import pytest

from mcrecon.cli import main
from mcrecon.errors import InputError
from mcrecon.io import read_exr, write_exr
from mcrecon.renderers.scenes import get_scene, write_scene_log


def _one_line_error(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    return err[0]


@pytest.fixture(scope="module")
def client():
    pytest.importorskip("distributed", reason="needs the dask extra: pip install 'mcrecon[dask]'")
    from mcrecon.distributed import cluster as D_cluster

    with D_cluster.local_client(1, threads=1) as c:
        yield c


@pytest.fixture(scope="module")
def shots(tmp_path_factory):
    d = tmp_path_factory.mktemp("shots")
    write_scene_log(get_scene("soft_shadow"), d / "shot[1].h5", width=12, height=8, spp=4, seed=1)
    write_scene_log(get_scene("caustic"), d / "shot1.h5", width=16, height=8, spp=4, seed=2)
    write_scene_log(get_scene("soft_shadow"), d / "take[2].h5", width=12, height=8, spp=4, seed=3)
    return d


def test_batch_workers_capped_at_frames_and_cores(shots, tmp_path, capsys, monkeypatch):
    pytest.importorskip("distributed", reason="needs the dask extra: pip install 'mcrecon[dask]'")
    from mcrecon.distributed import cluster as D_cluster

    asked = []

    @contextlib.contextmanager
    def no_cluster(workers=None, **kw):
        asked.append(workers)
        raise InputError("test", "cluster", "not started")
        yield  # pragma: no cover

    monkeypatch.setattr(D_cluster, "local_client", no_cluster)
    assert main(["batch", str(shots / "shot1.h5"), "--out-dir", str(tmp_path), "--workers", "1000000",
                 "--quiet"]) == 2
    assert asked == [1]                                  # one frame: one worker, not a million
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and "warning" in err[0] and "1000000 workers capped at 1" in err[0]
    assert "not started" in err[1]
    for bad in ("0", "-3", "two"):                       # refused by the flag, before any work
        with pytest.raises(SystemExit) as exc:
            main(["batch", str(shots / "shot1.h5"), "--out-dir", str(tmp_path), "--workers", bad])
        assert exc.value.code == 2
        assert "--workers" in _one_line_error(capsys)
    assert len(asked) == 1


def test_batch_existing_name_is_literal_not_a_pattern(shots):
    pytest.importorskip("distributed", reason="needs the dask extra: pip install 'mcrecon[dask]'")
    from mcrecon.distributed import batch as D_batch

    assert D_batch._expand([str(shots / "shot[1].h5")]) == [shots / "shot[1].h5"]   # not shot1.h5
    assert D_batch._expand([str(shots / "take[2].h5")]) == [shots / "take[2].h5"]   # exists: no "matches no file"
    assert D_batch._expand([str(shots / "shot?.h5")]) == [shots / "shot1.h5"]       # a pattern still globs
    with pytest.raises(InputError, match="matches no file"):
        D_batch._expand([str(shots / "take[3].h5")])


def test_batch_literal_name_and_damaged_output_redone(client, shots, tmp_path, capsys):
    out = tmp_path / "out"
    argv = ["batch", str(shots / "shot[1].h5"), "--out-dir", str(out), "--scheduler", client.scheduler.address,
            "--quiet"]
    assert main(argv) == 0
    exr = out / "shot[1].exr"
    assert read_exr(exr)[0].shape == (8, 12, 3)          # shot[1].h5 (12x8), not shot1.h5 (16x8)
    doc = json.loads((out / "batch_summary.json").read_text())
    assert [f["log"] for f in doc["frames"]] == [str(shots / "shot[1].h5")]
    capsys.readouterr()
    good = exr.read_bytes()
    assert main(argv) == 0
    assert "1 up to date" in capsys.readouterr().out     # intact: skipped

    exr.write_bytes(good[:40])                           # truncated, still newer than the log
    assert main(argv) == 0
    cap = capsys.readouterr()
    assert "1 reconstructed" in cap.out
    assert "damaged" in cap.err and "not a readable EXR" in cap.err and str(exr) in cap.err
    assert exr.read_bytes() == good

    exr.write_bytes(good[:len(good) // 2])               # cut after its header: the pixels are missing
    assert main(argv) == 0
    cap = capsys.readouterr()
    assert "1 reconstructed" in cap.out and "not a readable EXR" in cap.err
    assert exr.read_bytes() == good

    write_exr(exr, np.zeros((4, 4, 3)))                  # readable, but not this log's size
    assert main(argv) == 0
    cap = capsys.readouterr()
    assert "1 reconstructed" in cap.out and "4x4" in cap.err
    assert exr.read_bytes() == good
