"""A live run counts a round's samples per pixel from its validated request, not from the reply's positions.

The validation has already matched the reply's counted samples to the
request pixel by pixel, so the driver's per-pixel tally of rendered samples
(each request's ``first_index``) takes the request's counts instead of a
bincount over every sample of the round; a resume's replay, which has no
request, still counts the positions.  Both give the same tally.
"""

import numpy as np

from mcrecon import get_method
from mcrecon.adaptive import rounds
from mcrecon.adaptive.run import adapt, resume
from mcrecon.io import read_log

from helpers import jittered_renderer


def _renderer(w=12, h=8):
    def shade(pos, rng, req):
        return np.repeat(0.3 + 0.5 * (pos[:, :1] > w / 2), 3, axis=1) * rng.uniform(0.5, 1.5, (len(pos), 1))
    return jittered_renderer(shade, width=w, height=h, name="counts test renderer")


def _tally(monkeypatch):
    """Record the run context the rounds are taken into and every count of positions."""
    seen, calls = {}, []
    take, count = rounds._take_round, rounds._pixel_counts_of

    def spy_take(ctx, *a, **k):
        seen["ctx"] = ctx
        return take(ctx, *a, **k)

    def spy_count(pos, w, h):
        calls.append(len(pos))
        return count(pos, w, h)

    monkeypatch.setattr(rounds, "_take_round", spy_take)
    monkeypatch.setattr(rounds, "_pixel_counts_of", spy_count)
    return seen, calls


def _log_counts(path, w, h):
    pos = np.asarray(read_log(path).read_all().positions, np.float64)
    return np.bincount(pos[:, 1].astype(np.int64) * w + pos[:, 0].astype(np.int64), minlength=w * h).reshape(h, w)


def test_live_rounds_take_the_requests_counts(monkeypatch, tmp_path):
    for pipeline in (False, True):
        seen, calls = _tally(monkeypatch)
        log = tmp_path / f"run{int(pipeline)}.h5"
        res = adapt(_renderer(), get_method("box"), spp=6, seed=3, log=str(log),
                    progress=False, pipeline=pipeline)
        assert res.samples == 6 * 12 * 8
        assert calls == []  # no bincount over a round's positions
        assert np.array_equal(seen["ctx"].rendered, _log_counts(log, 12, 8))


def test_resume_replay_still_counts_positions(monkeypatch, tmp_path):
    log = tmp_path / "run.h5"
    adapt(_renderer(), get_method("box"), spp=4, seed=1, log=str(log), progress=False, max_rounds=2)
    seen, calls = _tally(monkeypatch)
    resume(str(log), _renderer(), progress=False)
    assert calls  # the replayed rounds have no request: their positions are counted
    assert np.array_equal(seen["ctx"].rendered, _log_counts(log, 12, 8))
