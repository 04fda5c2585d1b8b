"""A minimal out-of-process renderer speaking mcrecon's file protocol.

Usage (mcrecon fills in the two paths)::

    mcrecon adapt --renderer-cmd "python data_tools/example_renderer.py {request} {reply}" \
        --size 64x64 --spp 16 --method box -o out.exr --log run.h5

It renders a soft disc over a gradient with per-sample noise.  A C++
renderer does the same with the HDF5 C API: read ``counts`` and/or
``positions`` from the request, write ``positions``/``values`` and the
attributes of docs/renderer-protocol.md to the reply.  Where the request
has ``first_index`` (optional; every adaptive run sends it), the film
positions continue each pixel's stratified sequence round after round.
"""

import sys

import h5py
import numpy as np


def shade(x, y, w, h, rng):
    r = np.hypot(x / w - 0.5, y / h - 0.5)
    base = np.where(r < 0.3, 1.0, 0.2 * x / w)
    return np.stack([base, 0.5 * base, 0.25 + 0 * base], axis=1) * rng.uniform(0.5, 1.5, (x.size, 1))


def stratified(pix, index):
    """Film offsets (N, 2) in [0, 1)^2 of sample ``index`` of pixel ``pix``: the first two Sobol dimensions
    (a (0, 2)-sequence), XOR-scrambled per pixel (random digit scrambling keeps its stratification: every
    aligned block of 2^k samples of a pixel, a round after a round, has one sample per elementary
    interval).  A renderer continues each pixel's sequence from the request's ``first_index``."""
    i = np.asarray(index, np.uint64) & np.uint64(0xFFFFFFFF)
    x = np.zeros_like(i)
    y = np.zeros_like(i)
    v = np.uint64(0x80000000)
    for bit in range(32):
        on = ((i >> np.uint64(bit)) & np.uint64(1)).astype(bool)
        x[on] ^= np.uint64(0x80000000) >> np.uint64(bit)   # van der Corput
        y[on] ^= v                                          # Sobol's second dimension
        v ^= v >> np.uint64(1)
    with np.errstate(over="ignore"):                        # a per-pixel hash (SplitMix64), wrapping
        h = np.asarray(pix, np.uint64) * np.uint64(0x9E3779B97F4A7C15) + np.uint64(0xBF58476D1CE4E5B9)
        h = (h ^ (h >> np.uint64(31))) * np.uint64(0x94D049BB133111EB)
        h ^= h >> np.uint64(29)
    x ^= h & np.uint64(0xFFFFFFFF)
    y ^= h >> np.uint64(32)
    return np.stack([x, y], 1).astype(np.float64) / 4294967296.0


def main(request_path, reply_path):
    with h5py.File(request_path, "r") as f:
        w, h, seed = int(f.attrs["width"]), int(f.attrs["height"]), int(f.attrs["seed"])
        channels = f.attrs["channels"]
        counts = f["counts"][...] if "counts" in f else np.zeros((h, w), np.int64)
        extra = f["positions"][...] if "positions" in f else np.zeros((0, 2))
        first = f["first_index"][...] if "first_index" in f else None
    rng = np.random.default_rng(seed)
    pix = np.repeat(np.arange(w * h), counts.ravel())  # counted samples first, inside their pixels
    if first is None:
        offsets = rng.random((pix.size, 2))
    else:  # sample k of pixel p in this request is sample first[p] + k of the pixel's sequence
        starts = np.cumsum(counts.ravel()) - counts.ravel()
        offsets = stratified(pix, first.ravel()[pix] + np.arange(pix.size) - starts[pix])
    cell = np.stack([pix % w, pix // w], 1).astype(np.float64)
    pos = np.concatenate([np.minimum(cell + offsets, np.nextafter(cell + 1.0, 0.0)), extra])
    values = shade(pos[:, 0], pos[:, 1], w, h, rng)
    with h5py.File(reply_path, "w") as f:  # the reply is a sample log (format version 1)
        f.attrs.update(format="mcrecon-sample-log", format_version=1, width=w, height=h, channels=channels)
        f["positions"] = pos
        f["values"] = values


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
