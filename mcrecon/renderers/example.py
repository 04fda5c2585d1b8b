"""A minimal out-of-process renderer speaking mcrecon's file protocol, shipped with the package.

Run it from any directory (mcrecon fills in the two paths)::

    mcrecon adapt --renderer-cmd "python -m mcrecon.renderers.example {request} {reply}" \
        --size 64x64 --spp 16 --method box -o out.exr --log run.h5

It renders a soft disc over a gradient with per-sample noise: the picture
and the samples of ``data_tools/example_renderer.py``, which does the same
with h5py alone, as a renderer in another language does with the HDF5
library (docs/renderer-protocol.md).  Where the request carries each
pixel's ``first_index`` (every adaptive run sends it), the film positions
continue each pixel's stratified sequence (:func:`stratified`) round after
round, and the reply declares it (root attribute ``sampler = "sobol"``), so the methods complete
whole nets.  This one reads the request with
:func:`mcrecon.renderers.command.read_request`, which checks it, and
writes the reply with :func:`mcrecon.renderers.command.write_reply`.
"""

from __future__ import annotations

import sys

import numpy as np

__all__ = ["main", "shade", "stratified"]


def shade(x, y, w, h, rng):
    """Radiance (N, 3) of the film positions ``x``, ``y`` on a ``w`` x ``h`` film, noisy per sample."""
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


def main(request_path, reply_path) -> None:
    """Answer the request file at ``request_path`` with a reply file at ``reply_path``."""
    from ..core.requests import sample_indices
    from .command import read_request, request_channels, write_reply

    req = read_request(request_path)
    w, h = req.width, req.height
    counts = req.counts if req.counts is not None else np.zeros((h, w), np.int64)
    extra = req.positions if req.positions is not None else np.zeros((0, 2))
    rng = np.random.default_rng(req.seed)
    pix = np.repeat(np.arange(w * h), counts.ravel())  # counted samples first, inside their pixels
    if req.first_index is None:  # optional in the request: independent jitter
        offsets = rng.random((pix.size, 2))
    else:  # each pixel's sequence goes on from the samples it already has (sample_indices: pixel by pixel)
        offsets = stratified(pix, sample_indices(req)[:pix.size])
    # x0 + u can round up to x0 + 1 far from the origin: keep it inside the pixel
    cell = np.stack([pix % w, pix // w], 1).astype(np.float64)
    pos = np.concatenate([np.minimum(cell + offsets, np.nextafter(cell + 1.0, 0.0)), extra])
    values = shade(pos[:, 0], pos[:, 1], w, h, rng)
    # with first_index the film positions continue each pixel's stratified sequence: the reply says so
    write_reply(reply_path, pos, values, width=w, height=h, channels=request_channels(request_path),
                sampler=None if req.first_index is None else "sobol")


def _cli(argv) -> int:
    if len(argv) != 2:
        sys.stderr.write("usage: python -m mcrecon.renderers.example REQUEST.h5 REPLY.h5 (mcrecon adapt "
                         "--renderer-cmd fills in {request} and {reply})\n")
        return 2
    main(argv[0], argv[1])
    return 0


if __name__ == "__main__":
    raise SystemExit(_cli(sys.argv[1:]))
