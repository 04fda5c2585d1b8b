"""A minimal out-of-process renderer speaking mcrecon's file protocol, shipped with the package.

Run it from any directory (mcrecon fills in the two paths)::

    mcrecon adapt --renderer-cmd "python -m mcrecon.renderers.example {request} {reply}" \
        --size 64x64 --spp 16 --method box -o out.exr --log run.h5

It renders a soft disc over a gradient with per-sample noise.  It reads
and writes the two HDF5 files with h5py alone, as a renderer of your own
would: a C++ renderer does the same with the HDF5 C API -- read ``counts``
and/or ``positions`` from the request, write ``positions``/``values`` and
the attributes of docs/renderer-protocol.md to the reply.
"""

from __future__ import annotations

import sys

import h5py
import numpy as np

__all__ = ["main", "shade"]


def shade(x, y, w, h, rng):
    """Radiance (N, 3) of the film positions ``x``, ``y`` on a ``w`` x ``h`` film, noisy per sample."""
    r = np.hypot(x / w - 0.5, y / h - 0.5)
    base = np.where(r < 0.3, 1.0, 0.2 * x / w)
    return np.stack([base, 0.5 * base, 0.25 + 0 * base], axis=1) * rng.uniform(0.5, 1.5, (x.size, 1))


def main(request_path, reply_path) -> None:
    """Answer the request file at ``request_path`` with a reply file at ``reply_path``."""
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


def _cli(argv) -> int:
    if len(argv) != 2:
        sys.stderr.write("usage: python -m mcrecon.renderers.example REQUEST.h5 REPLY.h5 (mcrecon adapt "
                         "--renderer-cmd fills in {request} and {reply})\n")
        return 2
    main(argv[0], argv[1])
    return 0


if __name__ == "__main__":
    raise SystemExit(_cli(sys.argv[1:]))
