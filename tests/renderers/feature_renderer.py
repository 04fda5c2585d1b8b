"""A protocol renderer whose replies carry per-sample features, for tests.

usage: feature_renderer.py MODE REQUEST REPLY
MODE: ok     /features/depth (N,) float32 = x + 1000 y and /features/normal (N, 3) float64
      short  /features/depth one row short
      long   /features/depth one row too many
      text   /features/depth of strings
      nan    /features/depth NaN in the first row, +inf in the last (a ray that left the scene)
      matrix /features/depth (N, 2, 2)
      bool   /features/depth of booleans
      rename from round 1 on, /features/dist in place of /features/depth
      widen  from round 1 on, /features/normal (N, 4)
"""

import sys

import h5py
import numpy as np


def main(mode, req_path, reply_path):
    with h5py.File(req_path, "r") as f:
        w, h, seed, rnd = (int(f.attrs[k]) for k in ("width", "height", "seed", "round"))
        channels = list(f.attrs["channels"])
        counts = f["counts"][...] if "counts" in f else np.zeros((h, w), np.int64)
        extra = f["positions"][...] if "positions" in f else np.zeros((0, 2))
    rng = np.random.default_rng(seed)
    pix = np.repeat(np.arange(w * h), counts.ravel())
    pos = np.concatenate([np.stack([pix % w, pix // w], 1) + rng.random((pix.size, 2)), extra])
    val = rng.uniform(0.5, 1.5, (len(pos), len(channels)))
    depth = (pos[:, 0] + 1000 * pos[:, 1]).astype(np.float32)
    normal = np.stack([np.ones(len(pos)), pos[:, 0], pos[:, 1]], axis=1)
    if mode == "short":
        depth = depth[:-1]
    elif mode == "long":
        depth = np.append(depth, np.float32(0))
    elif mode == "text":
        depth = np.array([str(v) for v in depth], dtype=h5py.string_dtype())
    elif mode == "nan":
        depth[0], depth[-1] = np.nan, np.inf
    elif mode == "matrix":
        depth = np.repeat(depth, 4).reshape(-1, 2, 2)
    elif mode == "bool":
        depth = depth > 500
    elif mode == "widen" and rnd > 0:
        normal = np.concatenate([normal, normal[:, :1]], axis=1)
    names = {"depth": "dist" if mode == "rename" and rnd > 0 else "depth"}
    with h5py.File(reply_path, "w") as f:
        f.attrs.update(format="mcrecon-sample-log", format_version=1, width=w, height=h, channels=channels)
        f["positions"] = pos
        f["values"] = val
        f["features/" + names["depth"]] = depth
        f["features/normal"] = normal


if __name__ == "__main__":
    main(*sys.argv[1:])
