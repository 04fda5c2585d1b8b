"""SIGKILL at random moments while rounds are appended: the log stays readable and consistent."""

import os
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

from mcrecon.io import read_log
from mcrecon.core.stats import PixelStats

# Reports each append before it starts and once it has returned (committed), so the
# test knows what the log must hold without opening it while the appender runs.
APPENDER = textwrap.dedent("""
    import sys, numpy as np
    from mcrecon.io import write_log, append_log
    p = sys.argv[1]
    rng = np.random.default_rng(int(sys.argv[2]))
    write_log(p, rng.random((1000, 2)) * 64, rng.random((1000, 3)), width=64, height=64)
    print("committed 1000", flush=True)
    while True:
        n = int(rng.integers(1000, 200000))
        print(f"appending {n}", flush=True)
        total = append_log(p, rng.random((n, 2)) * 64, rng.random((n, 3)), round_record={"n": n})
        print(f"committed {total}", flush=True)
""")


@pytest.mark.slow
def test_kill_during_appends_never_loses_committed_rounds(tmp_path, full_run):
    script = tmp_path / "appender.py"
    script.write_text(APPENDER)
    trials = 30 if full_run else 6
    rng = np.random.default_rng(4)
    for t in range(trials):
        path = tmp_path / f"k{t}.h5"
        proc = subprocess.Popen([sys.executable, str(script), str(path), str(t)], stdout=subprocess.PIPE)
        assert proc.stdout.readline().strip() == b"committed 1000"
        time.sleep(float(rng.uniform(0.05, 1.0)))
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        lines = proc.stdout.read().decode().split("\n")
        proc.stdout.close()
        committed, pending = 1000, None  # from complete lines only
        for ln in lines[:-1]:
            word, num = ln.split()
            committed, pending = (int(num), None) if word == "committed" else (committed, int(num))
        log = read_log(path)  # only now: the appender is dead
        # every append that returned is in the log; the one in flight is either committed or not at all
        assert log.n_samples in (committed, committed + (pending or 0))
        stats = PixelStats.from_log(log)
        assert stats.n_samples == log.n_samples == log.round_ends[-1]
        # every committed round except the initial write carries its record
        assert len(log.round_records) == log.n_rounds - 1
        assert [r["n"] for r in log.round_records] == np.diff(log.round_ends).tolist()
        path.unlink()
