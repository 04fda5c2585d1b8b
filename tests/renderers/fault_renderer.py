"""A protocol renderer with switchable faults, for tests.

usage: fault_renderer.py MODE FAULT_ROUND REQUEST REPLY
MODE: ok, slow, exit, hang, nan, short, channels, offpixel, noreply, garbage

Environment (for tests that kill the driver at a known point):
FAULT_RENDERER_MARKER=PATH  append a line "ROUND PID" to PATH when called for a round
FAULT_RENDERER_HOLD=K       for rounds >= K, write the marker and then wait to be killed
                            (at most 120 s) instead of rendering: the driver has then
                            committed rounds 0..K-1 and is blocked on this call
FAULT_RENDERER_DISK=fill:PATH  at round FAULT_RENDERER_DISK_ROUND (default 2), fill the
                            filesystem of PATH by writing PATH until it is full (ENOSPC)
FAULT_RENDERER_DISK=ro:DIR     at that round, mount DIR read-only over itself (a bind mount;
                            needs root; the test unmounts it)
"""

import errno
import os
import subprocess
import sys
import time

import h5py
import numpy as np


def main(mode, fault_round, req_path, reply_path):
    with h5py.File(req_path, "r") as f:
        w, h, seed, rnd = (int(f.attrs[k]) for k in ("width", "height", "seed", "round"))
        channels = list(f.attrs["channels"])
        counts = f["counts"][...] if "counts" in f else np.zeros((h, w), np.int64)
        extra = f["positions"][...] if "positions" in f else np.zeros((0, 2))
    marker = os.environ.get("FAULT_RENDERER_MARKER")
    if marker:
        with open(marker, "a") as m:  # one short line per call; the reader uses complete lines only
            m.write(f"{rnd} {os.getpid()}\n")
    hold = os.environ.get("FAULT_RENDERER_HOLD")
    if hold is not None and rnd >= int(hold):
        time.sleep(120)  # the test SIGKILLs the driver, then this process
        sys.exit(4)
    disk = os.environ.get("FAULT_RENDERER_DISK")
    if disk and rnd == int(os.environ.get("FAULT_RENDERER_DISK_ROUND", "2")):
        action, target = disk.split(":", 1)
        if action == "fill":
            _fill(target)
        elif action == "ro":
            # a read-only bind mount over it: files opened before (the run's lock) stay writable
            subprocess.run(["mount", "--bind", target, target], check=True)
            subprocess.run(["mount", "-o", "remount,bind,ro", target], check=True)
    rng = np.random.default_rng(seed)
    pix = np.repeat(np.arange(w * h), counts.ravel())
    pos = np.concatenate([np.stack([pix % w, pix // w], 1) + rng.random((pix.size, 2)), extra])
    val = (0.5 + (pos[:, :1] > w / 2)) * rng.uniform(0.5, 1.5, (len(pos), len(channels)))
    faulty = rnd == int(fault_round)
    if mode == "slow":
        time.sleep(0.4)
    if faulty:
        if mode == "exit":
            sys.stderr.write("renderer crashed: out of memory\n")
            sys.exit(3)
        if mode == "hang":
            time.sleep(60)
        if mode == "nan":
            val[0, 0] = np.nan
            val[1, 1] = np.inf
        if mode == "short":
            pos, val = pos[:-1], val[:-1]
        if mode == "channels":
            val = val[:, :2]
            channels = channels[:2]
        if mode == "offpixel":
            pos[0, 0] = (pos[0, 0] + 1) % w
        if mode == "noreply":
            return
        if mode == "garbage":
            open(reply_path, "w").write("not hdf5")
            return
    with h5py.File(reply_path, "w") as f:
        f.attrs.update(format="mcrecon-sample-log", format_version=1, width=w, height=h, channels=channels)
        f["positions"] = pos
        f["values"] = val


def _fill(path):
    """Write ``path`` until its filesystem is full."""
    block = b"\0" * 4096
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND)
    try:
        while True:
            os.write(fd, block)
    except OSError as exc:
        if exc.errno != errno.ENOSPC:
            raise
    finally:
        os.close(fd)


if __name__ == "__main__":
    main(*sys.argv[1:])
