"""Every method's default and paper variant give the same images, logs and round plans as when pinned.

A refactor is a move, not a change of behaviour: this test pins, on small
built-in scenes, the SHA-256 hashes of the exact bytes of adaptive runs'
logged samples (their round plans: positions, values and round ends),
sequential and pipelined, and the images themselves (offline and adaptive
final images, in ``pinned_images.npz``).

The pins hold on x86-64 CPUs with AVX2 (written on an AVX2 AMD EPYC and
checked on an AVX-512 one).  numpy picks its kernels by the CPU, and its
X86_V4 (AVX-512) ones give other last bits than its X86_V3 (AVX2) ones;
one ulp in an estimate moves an adaptive round's plan (gem's and awr's
soft_shadow and caustic runs), so the cases run in a child process whose numpy
is held to its X86_V3 (AVX2) kernels (``NPY_DISABLE_CPU_FEATURES``, checked
there with ``numpy.lib.introspect.opt_func_info``).  Images are compared
within ``RTOL`` of their values, not by their bits; an image that passes
through Intel OIDN, whose kernels follow the CPU with no switch to hold
them, within ``RTOL_OIDN`` (AVX-512 against AVX2 moves auto's 24 x 24
pins by up to 5.1e-6 relative).  A deliberate change of a method's output
regenerates the pins, in its own commit that says why:

    python tests/test_pinned_outputs.py --write
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest

import mcrecon
from mcrecon.renderers.scenes import SceneRenderer, write_scene_log

PINS = Path(__file__).with_name("data") / "pinned_outputs.json"
IMAGES = Path(__file__).with_name("data") / "pinned_images.npz"
#: Relative tolerance of an image against its pin (float32-stored pins; a real change moves far more).
RTOL = 1e-6
#: The same for the methods whose images pass through OIDN (its kernels follow the CPU's vector width).
RTOL_OIDN = 3e-5
OIDN_METHODS = ("auto",)
#: The numpy targets the cases run on in their child process (:func:`held_numpy_env`).
HELD_TARGETS = frozenset({"baseline(X86_V2)", "X86_V3"})
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


def assert_image_matches(image, pinned, key, *, rtol=RTOL):
    """``image`` equals its pin within ``rtol`` of the pin's values (shape and finiteness exactly)."""
    image = np.asarray(image)
    assert image.shape == pinned.shape, f"{key}: shape {image.shape} against the pin's {pinned.shape}"
    assert np.array_equal(np.isfinite(image), np.isfinite(pinned)), f"{key}: finite pixels differ"
    scale = float(np.max(np.abs(pinned[np.isfinite(pinned)]), initial=0.0))
    err = np.abs(image.astype(np.float64) - pinned.astype(np.float64))
    bound = rtol * (np.abs(pinned.astype(np.float64)) + 1e-3 * scale)
    bad = np.isfinite(pinned) & ~(err <= bound)
    assert not bad.any(), f"{key}: {int(bad.sum())} values differ from the pin (largest {float(err[bad].max()):.3g})"


def held_numpy_env() -> dict:
    """This process's environment with numpy held to its X86_V3 (AVX2) kernels: every AVX-512 feature
    numpy finds on this CPU disabled (none on a CPU without them)."""
    from numpy._core._multiarray_umath import __cpu_features__

    above = [f for f, on in __cpu_features__.items() if on and (f.startswith(("AVX512", "AMX")) or f == "X86_V4")]
    env = dict(os.environ)
    env.pop("NPY_DISABLE_CPU_FEATURES", None)
    if above:
        env["NPY_DISABLE_CPU_FEATURES"] = " ".join(above)
    return env


def numpy_targets() -> set[str]:
    """The CPU targets numpy's dispatched kernels run on in this process."""
    from numpy.lib.introspect import opt_func_info

    return {v["current"] for f in opt_func_info().values() for v in f.values()}


def run_cases(out: Path) -> None:
    """:func:`compute` in a child process whose numpy is held (:func:`held_numpy_env`), into ``out``."""
    subprocess.run([sys.executable, str(Path(__file__).resolve()), "--compute", str(out)], env=held_numpy_env(),
                   check=True)


def _load(hashes_path: Path, images_path: Path) -> tuple[dict, dict]:
    with np.load(images_path) as z:
        return json.loads(hashes_path.read_text()), {k: z[k] for k in z.files}


@pytest.fixture(scope="module")
def pins():
    if not (PINS.exists() and IMAGES.exists()):
        pytest.fail(f"{PINS} or {IMAGES} missing: run `python {__file__} --write` on the commit whose outputs it pins")
    return _load(PINS, IMAGES)


def test_outputs_match_pins(pins, tmp_path):
    """Every case's hashes and images against the pins; the failures listed together."""
    if not numpy_targets() <= HELD_TARGETS | {"X86_V4"}:
        pytest.skip(f"the pins are numpy's x86-64 AVX2 kernels' and this numpy runs {sorted(numpy_targets())}: "
                    "run this test on an x86-64 machine with AVX2")
    run_cases(tmp_path)
    hashes, images = _load(tmp_path / "hashes.json", tmp_path / "images.npz")
    pinned_hashes, pinned_images = pins
    assert set(images) == set(pinned_images) and set(hashes) == set(pinned_hashes), "the cases differ from the pins'"
    failures = []
    for k in sorted(images):
        rtol = RTOL_OIDN if k.split(":")[1].split("/")[0] in OIDN_METHODS else RTOL
        if k in hashes and hashes[k] != pinned_hashes[k]:
            failures.append(f"{k}: the logged samples (round plans) differ")
        try:
            assert_image_matches(images[k], pinned_images[k], k, rtol=rtol)
        except AssertionError as e:
            failures.append(str(e).splitlines()[0])
    assert not failures, f"{len(failures)} of {len(images)} outputs differ from their pins:\n" + "\n".join(failures)


def test_cases_run_on_held_numpy(tmp_path):
    """The child process's numpy runs no kernel above X86_V3, whatever this CPU has."""
    out = subprocess.run([sys.executable, "-c", "import numpy.lib.introspect as i; "
                          "print(sorted({v['current'] for f in i.opt_func_info().values() for v in f.values()}))"],
                         env=held_numpy_env(), check=True, capture_output=True, text=True).stdout
    assert "X86_V4" not in out and "AVX512" not in out, out
    assert ("X86_V3" in out) == bool(numpy_targets() & {"X86_V3", "X86_V4"}), out


def test_image_comparison_sees_a_change():
    """The tolerance is far below any change of a method's output: one value moved by 1e-5 fails."""
    pinned = np.linspace(0.0, 2.0, 48, dtype=np.float32).reshape(4, 4, 3)
    assert_image_matches(pinned.astype(np.float64) * (1 + 1e-8), pinned, "noise")
    moved = pinned.astype(np.float64).copy()
    moved[2, 1, 0] += 1e-5
    with pytest.raises(AssertionError, match="1 values differ"):
        assert_image_matches(moved, pinned, "moved")
    moved[2, 1, 0] += 1e-4 - 1e-5
    with pytest.raises(AssertionError, match="1 values differ"):
        assert_image_matches(moved, pinned, "moved", rtol=RTOL_OIDN)


def test_every_registered_method_is_pinned(pins):
    keys = {k.split(":")[1].split("/")[0] for k in pins[1]}
    assert keys == set(_featureless_methods())


if __name__ == "__main__" and sys.argv[1:2] == ["--compute"] and len(sys.argv) == 3:
    if not numpy_targets() <= HELD_TARGETS:
        sys.exit(f"numpy runs {sorted(numpy_targets())}: run through run_cases (its environment holds it to X86_V3)")
    out = Path(sys.argv[2])
    with tempfile.TemporaryDirectory() as d:
        hashes, images = compute(Path(d))
    (out / "hashes.json").write_text(json.dumps(hashes, indent=1, sort_keys=True) + "\n")
    np.savez(out / "images.npz", **images)
elif __name__ == "__main__" and sys.argv[1:] == ["--write"]:
    with tempfile.TemporaryDirectory() as d:
        run_cases(Path(d))
        hashes, images = _load(Path(d) / "hashes.json", Path(d) / "images.npz")
    PINS.parent.mkdir(exist_ok=True)
    PINS.write_text(json.dumps(hashes, indent=1, sort_keys=True) + "\n")
    np.savez_compressed(IMAGES, **{k: v.astype(np.float32) for k, v in images.items()})
    print(f"wrote {PINS} and {IMAGES}")
