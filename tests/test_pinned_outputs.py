"""Every method's default and paper variant give the same images, logs and round plans as when pinned.

The redesign of the method contract and the package layout (issue 23) is a
move, not a change of behaviour: this test pins SHA-256 hashes of the exact
bytes of offline images, of adaptive runs' logged samples (their round
plans: positions and round ends) and final images, sequential and
pipelined, on small built-in scenes.  A deliberate change of a method's
output regenerates the pins, in its own commit that says why:

    python tests/test_pinned_outputs.py --write
"""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

import numpy as np
import pytest

import mcrecon
from mcrecon.renderers.scenes import SceneRenderer, write_scene_log

PINS = Path(__file__).with_name("data") / "pinned_outputs.json"
SCENES = ("soft_shadow", "caustic")
SIZE = 24
SPP = 8
ADAPT_SPP = 40  # above every default initial pass (awr: 16 spp), so every placement runs


def _variants(name: str) -> list[str]:
    cls = mcrecon.methods.method_class(name)
    return ["default", "paper"] if "paper" in cls.variants else ["default"]


def _method(name: str, variant: str):
    return mcrecon.get_method(name) if variant == "default" else mcrecon.get_method(name, variant=variant)


def _digest(*arrays) -> str:
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(str((a.dtype.str, a.shape)).encode())
        h.update(a.tobytes())
    return h.hexdigest()[:20]


def _featureless_methods():
    """The methods the pinned (featureless) scenes can run: not those that need per-sample features."""
    return [n for n in mcrecon.available_methods() if mcrecon.get_method(n).requires.features != "required"]


def _cases():
    for name in _featureless_methods():
        for variant in _variants(name):
            for scene in SCENES:
                yield name, variant, scene


def _offline(tmp: Path, name, variant, scene) -> str:
    log = tmp / f"{scene}.h5"
    if not log.exists():
        write_scene_log(scene, log, width=SIZE, height=SIZE, spp=SPP, seed=3)
    return _digest(mcrecon.reconstruct(str(log), method=_method(name, variant)))


def _adaptive(tmp: Path, name, variant, scene, pipeline: bool) -> str:
    method = _method(name, variant)
    path = tmp / f"run-{name}-{variant}-{scene}-{int(pipeline)}.h5"
    renderer = SceneRenderer(scene, width=SIZE, height=SIZE, seed=5)
    result = mcrecon.adapt(renderer, method, spp=ADAPT_SPP, seed=7, log=str(path), progress=False,
                           track_error=False, pipeline=pipeline)
    log = mcrecon.read_log(str(path))
    positions = np.concatenate([c.positions for c in log.iter_chunks()]) if log.n_samples else np.zeros((0, 2))
    values = np.concatenate([c.values for c in log.iter_chunks()]) if log.n_samples else np.zeros((0, 3))
    return _digest(positions, values, np.asarray(log.round_ends), result.image)


def _pipelines(name, variant) -> list[bool]:
    return [False, True]  # every method runs both ways (pipelined: the round in flight as state.pending)


def compute(tmp: Path) -> dict:
    out = {}
    for name, variant, scene in _cases():
        key = f"{name}/{variant}/{scene}"
        out[f"offline:{key}"] = _offline(tmp, name, variant, scene)
        for p in _pipelines(name, variant):
            out[f"adapt:{key}:pipeline={p}"] = _adaptive(tmp, name, variant, scene, p)
    return out


@pytest.fixture(scope="module")
def pins():
    if not PINS.exists():
        pytest.fail(f"{PINS} missing: run `python {__file__} --write` on the commit whose outputs it pins")
    return json.loads(PINS.read_text())


@pytest.mark.parametrize("name,variant,scene", list(_cases()))
def test_outputs_match_pins(pins, tmp_path_factory, name, variant, scene):
    tmp = tmp_path_factory.getbasetemp() / "pinned"
    tmp.mkdir(exist_ok=True)
    key = f"{name}/{variant}/{scene}"
    assert _offline(tmp, name, variant, scene) == pins[f"offline:{key}"], f"offline {key}"
    for p in _pipelines(name, variant):
        k = f"adapt:{key}:pipeline={p}"
        assert _adaptive(tmp, name, variant, scene, p) == pins[k], k


def test_every_registered_method_is_pinned(pins):
    keys = {k.split(":")[1].split("/")[0] for k in pins}
    assert keys == set(_featureless_methods())


if __name__ == "__main__" and sys.argv[1:] == ["--write"]:
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        PINS.parent.mkdir(exist_ok=True)
        PINS.write_text(json.dumps(compute(Path(d)), indent=1, sort_keys=True) + "\n")
    print(f"wrote {PINS}")
