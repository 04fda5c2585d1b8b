"""A reply's samples on their way to the log and the statistics: validated once, converted at most once.

The adaptive driver validates a reply (``validate_reply_counted``: one pass) and
casts it to the log's dtype; the log append and the statistics take the
result as it is (``checked``).  The files and images are the same as the
long way round gave.
"""

from __future__ import annotations

import numpy as np

import mcrecon
from mcrecon.core import requests as core_requests
from mcrecon.core.requests import SampleBatch
from mcrecon.renderers.scenes import SceneRenderer


class _Float32Scene:
    """A built-in scene replying in float32, as the Mitsuba bridge does; keeps what it sent."""

    def __init__(self):
        self.inner = SceneRenderer("soft_shadow", width=20, height=16, seed=2)
        self.width, self.height, self.channels = 20, 16, self.inner.channels
        self.name = "float32 scene"
        self.sent = []

    def render(self, request):
        b = self.inner.render(request)
        out = SampleBatch(b.positions.astype(np.float32), b.values.astype(np.float32))
        self.sent.append(out.positions.copy())
        return out


def _run(tmp_path, name, method="box"):
    r = _Float32Scene()
    res = mcrecon.adapt(r, method, spp=12, seed=3, log=str(tmp_path / f"{name}.h5"), progress=False,
                        track_error=False)
    log = mcrecon.read_log(str(tmp_path / f"{name}.h5"))
    pos = np.concatenate([c.positions for c in log.iter_chunks()])
    val = np.concatenate([c.values for c in log.iter_chunks()])
    return r, res, pos, val


def test_float32_positions_go_to_the_log_unconverted_and_the_same(tmp_path, monkeypatch):
    r, res, pos, val = _run(tmp_path, "short")
    assert pos.dtype == np.float32 and np.array_equal(pos, np.concatenate(r.sent))  # bit for bit what was sent
    real = core_requests.validate_reply_counted

    def long_way(*a, **kw):  # the previous path: positions through float64 first
        kw["keep_float32"] = False
        return real(*a, **kw)

    monkeypatch.setattr("mcrecon.adaptive.rounds.validate_reply_counted", long_way)
    _, res2, pos2, val2 = _run(tmp_path, "long")
    assert np.array_equal(pos, pos2) and np.array_equal(val, val2)
    assert np.array_equal(res.image, res2.image)


def test_each_round_is_validated_once(tmp_path, monkeypatch):
    import mcrecon.core.samples as samples

    calls = []
    real = samples.check_samples

    def counting(positions, values, **kw):
        calls.append(np.asarray(positions).shape[0])
        return real(positions, values, **kw)

    for mod in ("mcrecon.core.samples", "mcrecon.core.requests", "mcrecon.core.stats", "mcrecon.core.halves",
                "mcrecon.io.log_stream"):
        monkeypatch.setattr(f"{mod}.check_samples", counting)
    _, res, pos, _ = _run(tmp_path, "count", method="gem")   # positions requested: the explicit-position path
    assert sum(calls) == pos.shape[0] == res.samples          # every sample checked once, in its reply
    assert len([n for n in calls if n]) == len(res.rounds)    # one check per round (and one of the empty log)
