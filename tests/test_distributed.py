"""Scale-out on Dask (mcrecon.distributed, `mcrecon batch`) against the one-process paths.

One real LocalCluster (2 worker processes) serves the whole module: its
start is the main cost.
"""

from __future__ import annotations

import csv
import json
import math
import os

import numpy as np
import pytest

distributed = pytest.importorskip("distributed", reason="needs the dask extra: pip install 'mcrecon[dask]'")

import mcrecon  # noqa: E402
from mcrecon import distributed as D  # noqa: E402
from mcrecon.distributed import ingestion as DI  # noqa: E402
from mcrecon.distributed import batch as D_batch
from mcrecon.distributed import cluster as D_cluster
from mcrecon.distributed import ingestion as D_ingestion
from mcrecon.distributed import tiles as D_tiles
from mcrecon.cli import main  # noqa: E402
from mcrecon.errors import InputError  # noqa: E402
from mcrecon.io import read_exr, read_log, write_log  # noqa: E402
from mcrecon.renderers.scenes import get_scene, write_scene_log  # noqa: E402
from mcrecon.core.stats import PixelStats  # noqa: E402


@pytest.fixture(scope="module")
def client():
    with D_cluster.local_client(2, threads=1) as c:
        yield c


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    d = tmp_path_factory.mktemp("frames")
    for i, scene in enumerate(("soft_shadow", "caustic", "soft_shadow")):
        write_scene_log(get_scene(scene), d / f"f{i}.h5", width=40, height=32, spp=8, seed=i)
    (d / "f3.h5").write_bytes(b"not an HDF5 file")      # a bad frame
    return d


def _same_exr(a, b) -> bool:
    (ia, ca), (ib, cb) = read_exr(a), read_exr(b)
    return ca == cb and ia.dtype == ib.dtype and np.array_equal(ia, ib)


# ----------------------------------------------------------------- 1. batch
def test_batch_equals_denoise_bit_for_bit_bad_frame_and_rerun(client, frames, tmp_path, capsys):
    out = tmp_path / "out"
    sched = client.scheduler.address
    argv = ["batch", str(frames / "*.h5"), "--out-dir", str(out), "--method", "gem", "--gamma", "0.25",
            "--scheduler", sched, "--quiet"]
    assert main(argv) == 2                                   # the bad frame fails the batch ...
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "f3.h5" in err[0] and "HDF5" in err[0]   # ... with its one-line error
    for i in range(3):                                       # ... and the others complete
        ref = tmp_path / f"denoise{i}.exr"
        assert main(["denoise", str(frames / f"f{i}.h5"), "-o", str(ref), "--method", "gem", "--gamma", "0.25"]) == 0
        assert _same_exr(out / f"f{i}.exr", ref)
    assert not (out / "f3.exr").exists()
    rows = list(csv.DictReader(open(out / "batch_summary.csv")))
    assert [r["frame"] for r in rows] == ["f0", "f1", "f2", "f3"]
    assert [r["status"] for r in rows] == ["done", "done", "done", "failed"]
    assert all(r["method"] == "gem" and float(r["seconds"]) > 0 and r["worker"].startswith("tcp://")
               for r in rows)
    assert all(float(r["rel_mse"]) > 0 for r in rows[:3])  # scene logs carry their reference
    doc = json.loads((out / "batch_summary.json").read_text())
    assert doc["config"]["options"]["gamma"] == 0.25 and doc["frames"][3]["error"] == rows[3]["error"]
    capsys.readouterr()

    # rerun: complete, newer outputs are skipped; the bad frame is tried (and fails) again
    mtimes = {i: (out / f"f{i}.exr").stat().st_mtime_ns for i in range(3)}
    assert main(argv) == 2
    assert "0 reconstructed, 3 up to date, 1 failed" in capsys.readouterr().out
    assert all((out / f"f{i}.exr").stat().st_mtime_ns == mtimes[i] for i in range(3))
    # a log newer than its output is redone; so is every frame under other options
    os.utime(frames / "f1.h5", ns=(mtimes[1] + 10**9, mtimes[1] + 10**9))
    res = D_batch.reconstruct_many([frames / f"f{i}.h5" for i in range(3)], method="gem", gamma=0.25, out_dir=out,
                         client=client)
    assert [r["status"] for r in res.records] == ["skipped", "done", "skipped"] and res.ok
    res = D_batch.reconstruct_many([frames / f"f{i}.h5" for i in range(3)], method="gem", gamma=0.3, out_dir=out,
                         client=client)
    assert [r["status"] for r in res.records] == ["done"] * 3


def test_batch_local_cluster_and_refusals(frames, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["batch", str(frames / "f0.h5"), "--out-dir", str(out), "--workers", "1", "--quiet"]) == 0
    assert main(["denoise", str(frames / "f0.h5"), "-o", str(tmp_path / "d.exr")]) == 0
    assert _same_exr(out / "f0.exr", tmp_path / "d.exr")
    capsys.readouterr()
    for argv, text in ((["--workers", "2", "--scheduler", "tcp://127.0.0.1:1"], "give one"),
                       (["--method", "gem", "--alpha", "0.3"], "does not apply"),
                       (["--method", "nope"], "nope")):
        assert main(["batch", str(frames / "f0.h5"), "--out-dir", str(out), *argv]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and text in err[0]
    assert main(["batch", str(tmp_path / "none" / "*.h5"), "--out-dir", str(out)]) == 2
    assert "matches no file" in capsys.readouterr().err


def _housekeeping(dask_worker):
    import dask

    return ("profile" in dask_worker.periodic_callbacks, dask.config.get("distributed.admin.tick.interval"))


def test_local_cluster_workers_run_without_the_profiler(client):
    """local_client's workers get its quieter Dask configuration (the nanny hands it to the worker process)."""
    assert set(client.run(_housekeeping).values()) == {(False, "1s")}


# ----------------------------------------------------------------- 2. ingestion
def _merge_bound(st: PixelStats, parts: int):
    """Rounding bound of |distributed - one-process| for mean, m2 and subpixel sums (docs/distributed.md).

    Both paths are sequences of Chan updates, one per run of consecutive
    samples of a pixel (at most n per pixel) plus ceil(log2 parts) tree
    merges.  An update ``mean += (b - mean) * nb / n`` rounds three times,
    each error at most u times a magnitude <= M (the pixel's largest |value|;
    differences of means are <= R = max - min <= 2M), and earlier errors are
    carried with weight <= 1: a path errs by at most 3 u M (n + L); the two
    paths differ by at most the sum.  ``m2 += q + delta^2 na nb / n`` rounds
    its terms (each <= m2_final + n R^2) and carries the mean's error through
    delta (2 R eps_mean per sample): c u (n + L) (m2 + n R M) with c = 8.
    """
    u = 2.0 ** -53
    n = st.count[..., None].astype(np.float64)
    L = math.ceil(math.log2(max(parts, 1))) if parts > 1 else 0
    M = np.maximum(np.abs(st.min), np.abs(st.max))
    R = st.max - st.min
    steps = 2 * (n + L)
    return 3 * u * M * steps, 8 * u * steps * (st.m2 + n * R * M)


@pytest.mark.parametrize("subpixels", [0, 4])
def test_distributed_ingestion_equals_one_process(client, tmp_path, subpixels):
    rng = np.random.default_rng(7)
    w, h, spp = 40, 32, 16
    n = w * h * spp
    pos = (rng.random((n, 2)) * [w, h]).astype(np.float32)          # shuffled: runs of one sample
    pos = np.minimum(pos, np.nextafter(np.float32([w, h]), 0))
    val = (1000.0 + rng.normal(0, 1, (n, 3)) * [1, 1e-2, 10]).astype(np.float32)  # offset: rounding shows
    path = write_log(tmp_path / "big.h5", pos, val, width=w, height=h)
    one = PixelStats.from_log(read_log(path), subpixels=subpixels)
    parts = 5
    dist = D_ingestion.ingest(path, client=client, parts=parts, chunk_size=997, subpixels=subpixels)
    assert np.array_equal(dist.count, one.count) and dist.n_samples == n
    assert np.array_equal(dist.min, one.min) and np.array_equal(dist.max, one.max)
    bm, b2 = _merge_bound(one, parts)
    dm, d2 = np.abs(dist.mean - one.mean), np.abs(dist.m2 - one.m2)
    assert (dm <= bm).all() and (d2 <= b2).all()
    assert (b2 / one.m2).max() < 1e-6               # the bound is far below the statistics themselves
    if subpixels:
        assert np.array_equal(dist.sub_count, one.sub_count)
        nsub = dist.sub_count[..., None]
        u = 2.0 ** -53
        bound = 2 * u * (nsub + 3) * nsub * np.abs(val).max()
        assert (np.abs(dist.sub_sum - one.sub_sum) <= bound).all()
    # a reconstruction from them is the one-process reconstruction to rounding
    a = mcrecon.reconstruct(one, method="box")
    b = mcrecon.reconstruct(dist, method="box")
    assert np.allclose(a, b, rtol=1e-12, atol=0)


def test_banded_partials_merge_exactly_like_full_image_partials(tmp_path):
    """Shipping only the rows a part touched changes nothing: merging an empty pixel is the identity."""
    rng = np.random.default_rng(11)
    w, h, spp = 24, 20, 6
    ys, xs = np.divmod(np.repeat(np.arange(w * h), spp), w)                  # written pixel by pixel
    pos = np.stack([xs + rng.random(xs.size), ys + rng.random(ys.size)], axis=1)
    val = 5.0 + rng.normal(0, 1, (pos.shape[0], 3))
    path = write_log(tmp_path / "rows.h5", pos, val, width=w, height=h)
    ranges = D_ingestion.row_ranges(pos.shape[0], 5, align=97)                         # bands overlap at their ends
    bands = [D_ingestion._ingest_range(str(path), a, b, 2, "drop", 97) for a, b in ranges]
    assert all(0 < b.stats.height < h for b in bands)                       # really banded
    fulls = [b.full() for b in bands]
    assert all(f.height == h and f.n_samples == b.stats.n_samples for f, b in zip(fulls, bands))
    merged = D_ingestion.tree_merge(bands, merge=D_ingestion._merge_bands).full()
    reference = D_ingestion.tree_merge([f.copy() for f in fulls])                      # PixelStats.merge of full images
    for name in ("count", "mean", "m2", "min", "max", "sub_sum", "sub_count"):
        assert np.array_equal(getattr(merged, name), getattr(reference, name)), name
    assert merged.n_samples == pos.shape[0] and merged.dtype == reference.dtype
    # the tasks ship bands packed as arrays (Dask sends arrays as raw frames): the same numbers
    packed = D_ingestion.tree_merge([D_ingestion._ingest_part(str(path), a, b, 2, "drop", 97) for a, b in ranges], merge=D_ingestion._merge_packed)
    unpacked = D_ingestion._Band.unpack(packed).full()
    for name in ("count", "mean", "m2", "min", "max", "sub_sum", "sub_count"):
        assert np.array_equal(getattr(unpacked, name), getattr(merged, name)), name
    assert unpacked.n_samples == merged.n_samples and unpacked.dtype == merged.dtype


def test_row_ranges_and_tree_merge():
    assert D_ingestion.row_ranges(10, 3) == [(0, 3), (3, 6), (6, 10)]
    r = D_ingestion.row_ranges(10_000, 4, align=997)
    assert r[0][0] == 0 and r[-1][1] == 10_000 and all(a % 997 == 0 for a, _ in r)
    assert all(b == c for (_, b), (c, _) in zip(r[:-1], r[1:]))
    assert D_ingestion.row_ranges(5, 8) == [(k, k + 1) for k in range(5)]
    assert D_ingestion.row_ranges(0, 3) == [(0, 0)]
    assert D_ingestion.tree_merge([1, 2, 3, 4, 5], merge=lambda a, b: a + b) == 15
    assert D_ingestion.tree_merge([1, 2, 3, 4, 5], merge=lambda a, b: a + b, until=2) == [10, 5]   # [3, 7, 5] -> [10, 5]
    with pytest.raises(InputError):
        D_ingestion.tree_merge([])


# ----------------------------------------------------------------- 3. tiles
@pytest.fixture(scope="module")
def big_stats(tmp_path_factory):
    d = tmp_path_factory.mktemp("tiles")
    path = write_scene_log(get_scene("soft_shadow"), d / "t.h5", width=104, height=88, spp=4, seed=3)
    return PixelStats.from_log(read_log(path))


@pytest.mark.parametrize("method, options, tile, on_cluster", [
    ("box", {}, 24, True),
    ("ci", {}, 40, False),
    ("gem", {"final_scales": 4, "risk_guard": 2.0}, 32, True),          # halo 27 + 6: interior tiles
    ("gem", {"final_scales": 4, "final_outliers": "paper", "risk_guard": 1.0}, 16, False),  # halo 39 + 3
])
def test_tiled_equals_untiled_bit_for_bit(client, big_stats, method, options, tile, on_cluster):
    m = mcrecon.get_method(method, **options)
    halo = m.halo(big_stats.width, big_stats.height)
    assert halo is not None and 2 * halo + tile < big_stats.width     # some tiles see only part of the film
    full = mcrecon.reconstruct(big_stats, method=m)
    assert np.array_equal(D_tiles.reconstruct_tiled(big_stats, method=m, tile=tile), full)
    if on_cluster:   # the same tiles as futures (the other cases add only worker start-up imports)
        assert np.array_equal(D_tiles.reconstruct_tiled(big_stats, method=m, tile=tile, client=client), full)


def test_tiled_one_sample_pixels_on_the_cluster_read_the_films_fill(client):
    """1 spp but for a 4-spp corner: the tiles shipped to the workers carry the film's fill-in values (the
    average variance of the corner's pixels), so gem's tiles away from the corner fill as the film does."""
    rng = np.random.default_rng(1)
    counts = np.ones((64, 96), np.int64)
    counts[:6, :6] = 4
    pix = np.repeat(np.arange(counts.size), counts.ravel())
    pos = np.stack([pix % 96 + rng.random(pix.size), pix // 96 + rng.random(pix.size)], 1)
    st = PixelStats(96, 64)
    st.add(pos, rng.gamma(2.0, 0.5, (pix.size, 3)))
    m = mcrecon.get_method("gem", final_scales=4, risk_guard=2.0)
    assert np.array_equal(D_tiles.reconstruct_tiled(st, method=m, tile=24, client=client),
                          mcrecon.reconstruct(st, method=m))


def test_tiled_gem_default_halo(tmp_path):
    m = mcrecon.get_method("gem")
    assert m.halo(1, 1) == 123                      # 49 (sigma 16 pixel kernel) + 49 (outlier vote) + 1 + 24 (risk guard)
    assert mcrecon.get_method("gem", final_outliers="paper").halo(1, 1) == 171
    path = write_scene_log(get_scene("soft_shadow"), tmp_path / "wide.h5", width=240, height=48, spp=4, seed=5)
    st = PixelStats.from_log(read_log(path))
    full = mcrecon.reconstruct(st, method=m)
    # tiles [0, 80) [80, 160) [160, 240): the outer ones see x < 203 and x >= 37 only
    assert np.array_equal(D_tiles.reconstruct_tiled(st, method=m, tile=80), full)


def test_tiling_is_dask_map_overlap(client):
    """Our tiles (boxes, halos clipped at the film's edges, trimming, assembly) are map_overlap's, bit for bit."""
    da = pytest.importorskip("dask.array", reason="needs the dask extra: pip install 'mcrecon[dask]'")
    from scipy import ndimage

    rng = np.random.default_rng(5)
    image = rng.random((53, 70))
    tile, halo = 16, 4
    running = lambda a: ndimage.uniform_filter(a, size=2 * halo + 1, mode="reflect")   # noqa: E731
    local = lambda a: ndimage.gaussian_filter(a, sigma=1.5, truncate=halo / 1.5, mode="reflect")  # noqa: E731
    for func in (running, local):
        ours = D_tiles.map_tiles(func, image, tile=tile, halo=halo)
        theirs = da.from_array(image, chunks=tile).map_overlap(func, depth=halo, boundary="none",
                                                               dtype=float).compute(scheduler="sync")
        assert np.array_equal(ours, theirs)
        assert np.array_equal(D_tiles.map_tiles(func, image, tile=tile, halo=halo, client=client), theirs)
    # a correlation of radius `halo` is local: tiles give the untiled result exactly ...
    assert np.array_equal(D_tiles.map_tiles(local, image, tile=tile, halo=halo), local(image))
    # ... and only with the whole halo (the comparison above can fail)
    assert not np.array_equal(D_tiles.map_tiles(local, image, tile=tile, halo=halo - 1), local(image))
    # a running sum (uniform_filter) rounds by its place in the line: equal to rounding only
    assert np.allclose(D_tiles.map_tiles(running, image, tile=tile, halo=halo), running(image), rtol=1e-13, atol=0)


def _fireflies(w=168, h=56, spp=8, seed=3):
    """Samples written pixel by pixel (spp consecutive per pixel): a smooth image with 0.3 % fireflies."""
    rng = np.random.default_rng(seed)
    ys, xs = np.divmod(np.repeat(np.arange(w * h), spp), w)
    pos = np.stack([xs + rng.random(xs.size), ys + rng.random(ys.size)], axis=1)
    val = rng.gamma(4.0, 0.25, (pos.shape[0], 1)) * [1.0, 0.8, 0.6]
    val[rng.random(pos.shape[0]) < 0.003] *= 1e4
    return pos, val


@pytest.fixture(scope="module")
def splat_log(tmp_path_factory):
    pos, val = _fireflies()
    return write_log(tmp_path_factory.mktemp("splat") / "fireflies.h5", pos, val, width=168, height=56)


def test_tiled_splat_equals_untiled_bit_for_bit(client, splat_log, monkeypatch):
    m = mcrecon.get_method("splat")                              # the robust default
    halo = m.halo(168, 56)
    assert halo == 34 and 2 * halo + 40 < 168                      # interior tiles exist
    full = mcrecon.reconstruct(splat_log, method=m, full=True)
    assert full.run.splatter.rounds[0]["outliers"] > 100         # the fireflies' excess is spread
    assert np.array_equal(D_tiles.reconstruct_tiled(splat_log, method=m, tile=40), full.image)
    assert np.array_equal(D_tiles.reconstruct_tiled(str(splat_log), method=m, tile=56, client=client), full.image)
    # the comparison can fail: with too small a halo, pixels near the tile edges change
    monkeypatch.setattr(type(m), "halo", lambda self, w, h: 2)
    assert not np.array_equal(D_tiles.reconstruct_tiled(splat_log, method=m, tile=40), full.image)


def test_tiled_splat_rounds():
    """Rounds are weighed by their film-wide density: equal in every tile (uniform rounds) or refused."""
    pos, val = _fireflies()
    rank = np.arange(pos.shape[0]) % 8
    order = np.argsort(rank >= 2, kind="stable")                 # round 0: 2 spp everywhere, round 1: 6 spp
    pos, val, rounds = pos[order], val[order], (rank[order] >= 2).astype(np.int64)
    uniform = mcrecon.SampleSet(pos, val, width=168, height=56, rounds=rounds)
    full = mcrecon.reconstruct(uniform, method="splat")
    assert np.array_equal(D_tiles.reconstruct_tiled(uniform, method="splat", tile=48), full)
    # an adaptive second round (samples on the left half only) is not local: refused
    keep = (pos[:, 0] < 84) | (rounds == 0)
    adaptive = mcrecon.SampleSet(pos[keep], val[keep], width=168, height=56, rounds=rounds[keep])
    with pytest.raises(InputError, match="film-wide density"):
        D_tiles.reconstruct_tiled(adaptive, method="splat", tile=48)


def test_tiled_refusals(big_stats, splat_log, tmp_path):
    with pytest.raises(InputError, match="whole image"):
        D_tiles.reconstruct_tiled(big_stats, method="awr")
    assert mcrecon.get_method("awr").halo(64, 64) is None
    with pytest.raises(InputError, match="sample log or a SampleSet"):
        D_tiles.reconstruct_tiled(big_stats, method="splat")
    with pytest.raises(InputError, match="paper variant"):
        D_tiles.reconstruct_tiled(splat_log, method="splat", variant="paper")
    thin = big_stats.copy()
    thin.count[5, 7] = 0   # a pixel without a sample (one sample tiles: the film's fill-in values, test_tiles_fill.py)
    with pytest.raises(InputError, match="without a sample"):
        D_tiles.reconstruct_tiled(thin, method="box")
    with pytest.raises(InputError, match="tile"):
        D_tiles.reconstruct_tiled(big_stats, method="box", tile=0)
