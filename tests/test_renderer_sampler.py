"""A renderer declares its sampler (``Renderer.sampler``, a reply file's ``sampler`` attribute), and the
methods' ``net_counts=-1`` follows it: whole nets for a stratified sampler, the counts as they fall for
independent samples; an explicit ``net_counts`` wins."""

from __future__ import annotations

import sys

import h5py
import numpy as np
import pytest

import mcrecon
from mcrecon.core.requests import check_sampler
from mcrecon.errors import InputError, RendererError
from mcrecon.io import read_log
from mcrecon.methods import get_method
from mcrecon.methods.base import Method
from mcrecon.renderers.command import CommandRenderer

from helpers import jittered_renderer

W = H = 16


def _film(sampler=None, *, late=False, then=None):
    """A cheap renderer: an edge and noise, the declared ``sampler`` (None: says nothing); ``late``: declared
    by the first reply, as a command renderer does; ``then``: the declaration of every round after the first."""
    def shade(pos, rng, req):
        film.sampler = sampler if then is None or req.round_index == 0 else then
        return np.where(pos[:, :1] < W / 2, 0.2, 1.0) * rng.uniform(0.5, 1.5, (len(pos), 3))

    film = jittered_renderer(shade, width=W, height=H)
    film.sampler = None if late else sampler
    return film


def _pow2_share(counts):
    c = counts.ravel()
    return float(((c & (c - 1)) == 0).mean())


def _run(renderer, method="awr", **opts):
    # gem follows the renderer when asked; its share's fill and rare nets follow it too, held fixed here
    opts = {"net_counts": -1, "uniform_fill": "lowest", "rare_nets": 0, **opts} if method == "gem" else opts
    return mcrecon.adapt(renderer, get_method(method, **opts), spp=24, seed=1, progress=False, track_error=False)


def test_check_sampler_values_and_one_line_refusal():
    assert check_sampler(None, where="r") == "independent"
    assert check_sampler(" Sobol", where="r") == "sobol"
    assert check_sampler(np.bytes_(b"independent"), where="r") == "independent"
    with pytest.raises(InputError) as e:
        check_sampler("halton", where="reply.h5", field="attribute sampler")
    msg = str(e.value)
    assert "reply.h5" in msg and "attribute sampler" in msg and "'sobol'" in msg and "\n" not in msg


def test_bad_declaration_refused_before_rendering():
    with pytest.raises(InputError, match="sampler"):
        _run(_film("stratified"))


@pytest.mark.parametrize("method", ["awr", "gem"])
def test_stratified_renderer_switches_whole_nets_on(method, monkeypatch):
    # the allocation's own counts: the net gate (tests/test_net_gate.py) would make this film's rounds even
    monkeypatch.setattr(Method, "net_gate", False)
    sobol = _run(_film("sobol"), method).stats.count
    indep = _run(_film(None), method).stats.count
    assert _pow2_share(sobol) > 0.9
    assert _pow2_share(indep) < 0.7
    # the explicit option wins either way
    assert np.array_equal(_run(_film("sobol"), method, net_counts=0).stats.count, indep)
    assert np.array_equal(_run(_film(None), method, net_counts=1).stats.count, sobol)


def test_sampler_recorded_and_resume_plans_alike(tmp_path):
    """A declaration that comes with the first reply (a command renderer's) is recorded in the run settings,
    and a resume, whose fresh renderer has declared nothing yet, plans with it: the same counts."""
    full = _run(_film("sobol", late=True)).stats.count
    log = tmp_path / "run.h5"
    mcrecon.adapt(_film("sobol", late=True), get_method("awr"), spp=24, seed=1, progress=False,
                  track_error=False, log=log, max_rounds=3)
    assert read_log(log).run_settings["sampler"] == "sobol"
    resumed = mcrecon.adaptive.run.resume(log, _film("sobol", late=True), progress=False, track_error=False)
    assert np.array_equal(resumed.stats.count, full) and _pow2_share(full) > 0.9


def test_a_changed_declaration_is_refused():
    with pytest.raises(RendererError, match="round 1"):
        _run(_film("sobol", then="independent"))


_REPLY = """import sys, h5py, numpy as np
with h5py.File(sys.argv[1], "r") as f:
    w, h, c = int(f.attrs["width"]), int(f.attrs["height"]), f["counts"][()]
pix = np.repeat(np.arange(w * h), c.ravel())
pos = np.stack([pix % w + 0.5, pix // w + 0.5], 1)
with h5py.File(sys.argv[2], "w") as f:
    f.attrs["format"], f.attrs["format_version"] = "mcrecon-sample-log", 1
    f.attrs["width"], f.attrs["height"] = w, h
    f.attrs["channels"] = ["R", "G", "B"]
    f.attrs["sampler"] = sys.argv[3]
    f["positions"], f["values"] = pos, np.ones((len(pos), 3))
"""


@pytest.mark.parametrize("declared, expect", [("sobol", "sobol"), ("jittered", None)])
def test_command_reply_declares_its_sampler(tmp_path, declared, expect):
    script = tmp_path / "r.py"
    script.write_text(_REPLY)
    r = CommandRenderer([sys.executable, str(script), "{request}", "{reply}", declared], width=4, height=2)
    req = mcrecon.core.requests.SampleRequest(4, 2, counts=np.full((2, 4), 2))
    if expect is None:
        with pytest.raises(InputError) as e:
            r.render(req)
        assert "reply.h5" in str(e.value) and "attribute sampler" in str(e.value)
    else:
        r.render(req)
        assert r.sampler == expect


def test_a_log_without_the_record_resumes_with_independent_plans(tmp_path):
    """A run's log from before renderers declared a sampler holds no record: its resume keeps the plans it had
    (independent), whatever the renderer declares now, and is not refused."""
    from mcrecon.io.writer import set_run_settings

    log = tmp_path / "old.h5"
    mcrecon.adapt(_film(None), get_method("awr"), spp=24, seed=1, progress=False, track_error=False, log=log,
                  max_rounds=3)
    settings = dict(read_log(log).run_settings)
    settings.pop("sampler")
    set_run_settings(log, settings)
    resumed = mcrecon.adaptive.run.resume(log, _film("sobol"), progress=False, track_error=False)
    assert np.array_equal(resumed.stats.count, _run(_film(None)).stats.count)


def test_example_renderer_declares_sobol_when_it_continues_the_sequences(tmp_path):
    from mcrecon.renderers import example
    from mcrecon.renderers.command import write_request

    for first, expect in ((None, None), (np.full((2, 4), 3), "sobol")):
        req = mcrecon.core.requests.SampleRequest(4, 2, counts=np.full((2, 4), 2), first_index=first)
        write_request(tmp_path / "q.h5", req, channels=("R", "G", "B"))
        example.main(tmp_path / "q.h5", tmp_path / "r.h5")
        with h5py.File(tmp_path / "r.h5", "r") as f:
            got = f.attrs.get("sampler")
        assert (got if got is None else check_sampler(got, where="r.h5")) == expect
