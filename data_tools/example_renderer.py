"""A minimal out-of-process renderer speaking mcrecon's file protocol.

Usage (mcrecon fills in the two paths)::

    mcrecon adapt --renderer-cmd "python data_tools/example_renderer.py {request} {reply}" \
        --size 64x64 --spp 16 --method box -o out.exr --log run.h5

It renders a soft disc over a gradient with per-sample noise.  A C++
renderer does the same with the HDF5 C API: read ``counts`` and/or
``positions`` from the request, write ``positions``/``values`` and the
attributes of docs/renderer-protocol.md to the reply.
"""

import sys

import h5py
import numpy as np


def shade(x, y, w, h, rng):
    r = np.hypot(x / w - 0.5, y / h - 0.5)
    base = np.where(r < 0.3, 1.0, 0.2 * x / w)
    return np.stack([base, 0.5 * base, 0.25 + 0 * base], axis=1) * rng.uniform(0.5, 1.5, (x.size, 1))


def main(request_path, reply_path):
    with h5py.File(request_path, "r") as f:
        w, h, seed = int(f.attrs["width"]), int(f.attrs["height"]), int(f.attrs["seed"])
        channels = f.attrs["channels"]
        counts = f["counts"][...] if "counts" in f else np.zeros((h, w), np.int64)
        extra = f["positions"][...] if "positions" in f else np.zeros((0, 2))
    rng = np.random.default_rng(seed)
    pix = np.repeat(np.arange(w * h), counts.ravel())  # counted samples first, inside their pixels
    pos = np.concatenate([np.stack([pix % w, pix // w], 1) + rng.random((pix.size, 2)), extra])
    values = shade(pos[:, 0], pos[:, 1], w, h, rng)
    with h5py.File(reply_path, "w") as f:  # the reply is a sample log (format version 1)
        f.attrs.update(format="mcrecon-sample-log", format_version=1, width=w, height=h, channels=channels)
        f["positions"] = pos
        f["values"] = values


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
