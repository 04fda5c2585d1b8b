"""A minimal out-of-process renderer speaking mcrecon's file protocol, shipped with the package.

Run it from any directory (mcrecon fills in the two paths)::

    mcrecon adapt --renderer-cmd "python -m mcrecon.renderers.example {request} {reply}" \
        --size 64x64 --spp 16 --method box -o out.exr --log run.h5

It renders a soft disc over a gradient with per-sample noise: the picture
and the samples of ``data_tools/example_renderer.py``, which does the same
with h5py alone, as a renderer in another language does with the HDF5
library (docs/renderer-protocol.md).  This one reads the request with
:func:`mcrecon.renderers.command.read_request`, which checks it, and
writes the reply with :func:`mcrecon.io.write_log`.
"""

from __future__ import annotations

import sys

import numpy as np

__all__ = ["main", "shade"]


def shade(x, y, w, h, rng):
    """Radiance (N, 3) of the film positions ``x``, ``y`` on a ``w`` x ``h`` film, noisy per sample."""
    r = np.hypot(x / w - 0.5, y / h - 0.5)
    base = np.where(r < 0.3, 1.0, 0.2 * x / w)
    return np.stack([base, 0.5 * base, 0.25 + 0 * base], axis=1) * rng.uniform(0.5, 1.5, (x.size, 1))


def main(request_path, reply_path) -> None:
    """Answer the request file at ``request_path`` with a reply file at ``reply_path``."""
    from ..io import write_log
    from .command import read_request, request_channels

    req = read_request(request_path)
    w, h = req.width, req.height
    counts = req.counts if req.counts is not None else np.zeros((h, w), np.int64)
    extra = req.positions if req.positions is not None else np.zeros((0, 2))
    rng = np.random.default_rng(req.seed)
    pix = np.repeat(np.arange(w * h), counts.ravel())  # counted samples first, inside their pixels
    pos = np.concatenate([np.stack([pix % w, pix // w], 1) + rng.random((pix.size, 2)), extra])
    values = shade(pos[:, 0], pos[:, 1], w, h, rng)
    write_log(reply_path, pos, values, width=w, height=h, channels=request_channels(request_path))


def _cli(argv) -> int:
    if len(argv) != 2:
        sys.stderr.write("usage: python -m mcrecon.renderers.example REQUEST.h5 REPLY.h5 (mcrecon adapt "
                         "--renderer-cmd fills in {request} and {reply})\n")
        return 2
    main(argv[0], argv[1])
    return 0


if __name__ == "__main__":
    raise SystemExit(_cli(sys.argv[1:]))
