"""Write a large uniform sample log for benchmarks (pixel-ordered, as renderers dump them).

usage: python data_tools/make_benchmark_log.py OUT.h5 [--size 1024x1024] [--spp 32]
Values are a smooth image plus noise, float32; streamed in row blocks so memory stays small.
"""

import argparse
import os
import tempfile

import h5py
import numpy as np

from mcrecon.io.logformat import DEFAULT_CHUNK_ROWS, FORMAT_NAME, FORMAT_VERSION, cast_positions


def main(argv=None):
    p = argparse.ArgumentParser()
    p.add_argument("out")
    p.add_argument("--size", default="1024x1024")
    p.add_argument("--spp", type=int, default=32)
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args(argv)
    w, h = (int(x) for x in a.size.split("x"))
    n = w * h * a.spp
    rng = np.random.default_rng(a.seed)
    fd, tmp = tempfile.mkstemp(dir=os.path.dirname(os.path.abspath(a.out)), suffix=".tmp")
    os.close(fd)
    with h5py.File(tmp, "w") as f:
        f.attrs.update(format=FORMAT_NAME, format_version=FORMAT_VERSION, width=w, height=h,
                       metadata_json='{"renderer": "make_benchmark_log"}')
        f.attrs["channels"] = np.array(["R", "G", "B"], dtype=h5py.string_dtype())
        pos_d = f.create_dataset("positions", (n, 2), np.float32, chunks=(DEFAULT_CHUNK_ROWS, 2), maxshape=(None, 2))
        val_d = f.create_dataset("values", (n, 3), np.float32, chunks=(DEFAULT_CHUNK_ROWS, 3), maxshape=(None, 3))
        rows = max(1, (1 << 21) // (w * a.spp))
        for y0 in range(0, h, rows):
            y1 = min(h, y0 + rows)
            pix = np.repeat(np.arange(y0 * w, y1 * w), a.spp)
            pos = np.stack([pix % w, pix // w], 1) + rng.random((pix.size, 2))
            base = 0.5 + 0.4 * np.sin(pos[:, :1] / 37.0) * np.cos(pos[:, 1:] / 23.0)
            val = base * rng.exponential(1.0, (pix.size, 3))
            s, e = y0 * w * a.spp, y1 * w * a.spp
            pos_d[s:e] = cast_positions(pos, np.float32)
            val_d[s:e] = val
        f.attrs["n_committed"] = n
    os.replace(tmp, a.out)
    print(f"wrote {a.out}: {w}x{h}, {a.spp} spp, {n} samples")


if __name__ == "__main__":
    main()
