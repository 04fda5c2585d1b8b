"""Every method's default and paper variant give the same images, logs and round plans as when pinned.

A refactor is a move, not a change of behaviour: this test pins, on small
built-in scenes, the SHA-256 hashes of the exact bytes of adaptive runs'
logged samples (their round plans: positions, values and round ends),
sequential and pipelined, and the images themselves (offline and adaptive
final images, in ``pinned_images.npz``).  Images are compared within
``RTOL`` of their values, not by their bits: numpy's reductions take
another summation order on another CPU's vector width (AVX2 against
AVX-512), which moves the last bits of a float64 image and nothing else.
A deliberate change of a method's output regenerates the pins, in its own
commit that says why:

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
IMAGES = Path(__file__).with_name("data") / "pinned_images.npz"
#: Relative tolerance of an image against its pin (float32-stored pins; a real change moves far more).
RTOL = 1e-6
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
    return np.asarray(mcrecon.reconstruct(str(log), method=_method(name, variant)))


def _adaptive(tmp: Path, name, variant, scene, pipeline: bool) -> str:
    method = _method(name, variant)
    path = tmp / f"run-{name}-{variant}-{scene}-{int(pipeline)}.h5"
    renderer = SceneRenderer(scene, width=SIZE, height=SIZE, seed=5)
    result = mcrecon.adapt(renderer, method, spp=ADAPT_SPP, seed=7, log=str(path), progress=False,
                           track_error=False, pipeline=pipeline)
    log = mcrecon.read_log(str(path))
    positions = np.concatenate([c.positions for c in log.iter_chunks()]) if log.n_samples else np.zeros((0, 2))
    values = np.concatenate([c.values for c in log.iter_chunks()]) if log.n_samples else np.zeros((0, 3))
    return _digest(positions, values, np.asarray(log.round_ends)), np.asarray(result.image)


def _pipelines(name, variant) -> list[bool]:
    return [False, True]  # every method runs both ways (pipelined: the round in flight as state.pending)


def compute(tmp: Path) -> tuple[dict, dict]:
    """(the adaptive runs' sample hashes, every image) by key."""
    hashes, images = {}, {}
    for name, variant, scene in _cases():
        key = f"{name}/{variant}/{scene}"
        images[f"offline:{key}"] = _offline(tmp, name, variant, scene)
        for p in _pipelines(name, variant):
            k = f"adapt:{key}:pipeline={p}"
            hashes[k], images[k] = _adaptive(tmp, name, variant, scene, p)
    return hashes, images


def assert_image_matches(image, pinned, key):
    """``image`` equals its pin within RTOL of the pin's values (shape, dtype kind and finiteness exactly)."""
    image = np.asarray(image)
    assert image.shape == pinned.shape, f"{key}: shape {image.shape} against the pin's {pinned.shape}"
    assert np.array_equal(np.isfinite(image), np.isfinite(pinned)), f"{key}: finite pixels differ"
    scale = float(np.max(np.abs(pinned[np.isfinite(pinned)]), initial=0.0))
    err = np.abs(image.astype(np.float64) - pinned.astype(np.float64))
    bound = RTOL * (np.abs(pinned.astype(np.float64)) + 1e-3 * scale)
    bad = np.isfinite(pinned) & ~(err <= bound)
    assert not bad.any(), f"{key}: {int(bad.sum())} values differ from the pin (largest {float(err[bad].max()):.3g})"


@pytest.fixture(scope="module")
def pins():
    if not (PINS.exists() and IMAGES.exists()):
        pytest.fail(f"{PINS} or {IMAGES} missing: run `python {__file__} --write` on the commit whose outputs it pins")
    with np.load(IMAGES) as z:
        return json.loads(PINS.read_text()), {k: z[k] for k in z.files}


@pytest.mark.parametrize("name,variant,scene", list(_cases()))
def test_outputs_match_pins(pins, tmp_path_factory, name, variant, scene):
    hashes, images = pins
    tmp = tmp_path_factory.getbasetemp() / "pinned"
    tmp.mkdir(exist_ok=True)
    key = f"{name}/{variant}/{scene}"
    assert_image_matches(_offline(tmp, name, variant, scene), images[f"offline:{key}"], f"offline:{key}")
    for p in _pipelines(name, variant):
        k = f"adapt:{key}:pipeline={p}"
        samples, image = _adaptive(tmp, name, variant, scene, p)
        assert samples == hashes[k], f"{k}: the logged samples (round plans) differ"
        assert_image_matches(image, images[k], k)


def test_image_comparison_sees_a_change():
    """The tolerance is far below any change of a method's output: one value moved by 1e-5 fails."""
    pinned = np.linspace(0.0, 2.0, 48, dtype=np.float32).reshape(4, 4, 3)
    assert_image_matches(pinned.astype(np.float64) * (1 + 1e-8), pinned, "noise")
    moved = pinned.astype(np.float64).copy()
    moved[2, 1, 0] += 1e-5
    with pytest.raises(AssertionError, match="1 values differ"):
        assert_image_matches(moved, pinned, "moved")


def test_every_registered_method_is_pinned(pins):
    keys = {k.split(":")[1].split("/")[0] for k in pins[1]}
    assert keys == set(_featureless_methods())


if __name__ == "__main__" and sys.argv[1:] == ["--write"]:
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        hashes, images = compute(Path(d))
        PINS.parent.mkdir(exist_ok=True)
        PINS.write_text(json.dumps(hashes, indent=1, sort_keys=True) + "\n")
        np.savez_compressed(IMAGES, **{k: v.astype(np.float32) for k, v in images.items()})
    print(f"wrote {PINS} and {IMAGES}")
