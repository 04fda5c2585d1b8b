"""Built-in procedural scenes with exact references.

Each scene is a tiny "renderer": a radiance function ``L(x, y, u)`` of a
film position (normalised, ``x, y`` in [0, 1)) and ``n_dims`` uniform random
numbers ``u`` (an area-light sample, a lens sample, a time, a path choice).
Every scene is built so that the expectation over ``u``,
``E_u[L(x, y, u)]``, has a closed form (:meth:`Scene.expected`); the
reference image is the pixel-area average of that closed form
(:func:`reference_image`).  A method's error can therefore be measured
against a reference that carries no Monte Carlo noise at all.

The scenes stress exactly what the adaptive-sampling papers are about:

``soft_shadow``
    sharp albedo edges (which must stay sharp) beside an area light's soft
    penumbra (which is noise, not detail);
``depth_of_field``
    a square lens aperture whose blur grows from nothing (in focus) to ~8
    pixels: where an edge is blurred, its detail is noise;
``motion_blur``
    coloured objects moving over a sharp static background;
``caustic``
    97 % exactly-zero samples with rare huge ones (values ~C/0.03);
``hdr``
    an emitter of radiance ~500 beside surfaces of 1e-3 .. 1e-2 and a
    mid-grey region (Tamstorf and Jensen's "scene with a bright emitter");
``flat``
    constant expectation with uniform noise (border and variance tests).

The formulas are in each class's docstring and in ``docs/scenes.md``.

References
----------
.. [1] R. Tamstorf and H. W. Jensen, "Adaptive Sampling and Bias
   Estimation in Path Tracing", Rendering Techniques '97 (caustic and
   bright-emitter test scenes).
.. [2] F. Rousselle, C. Knaus and M. Zwicker, "Adaptive Sampling and
   Reconstruction using Greedy Error Minimization", SIGGRAPH Asia 2011
   (soft shadows, depth of field, motion blur as test content).
.. [3] R. S. Overbeck, C. Donner and R. Ramamoorthi, "Adaptive Wavelet
   Rendering", SIGGRAPH Asia 2009 (distribution effects: area lights,
   depth of field, motion blur).
"""

from __future__ import annotations

import functools
import math
import os
import time
from pathlib import Path

import numpy as np

from ...errors import InputError
from ...core.samples import check_memory
from ...core.requests import SampleBatch, SampleRequest, jittered_positions
from .catalog import (SCENES, CausticScene, DepthOfFieldScene, FlatScene, HDRScene, MotionBlurScene, Scene,
                      SoftShadowScene)

__all__ = ["SCENES", "Scene", "SoftShadowScene", "DepthOfFieldScene", "MotionBlurScene", "CausticScene",
           "HDRScene", "FlatScene", "scene_names", "get_scene", "reference_image", "SceneRenderer",
           "render_uniform", "write_scene_log"]


def scene_names() -> list[str]:
    """Names of the built-in scenes, in registry order."""
    return list(SCENES)


def get_scene(name) -> Scene:
    """A built-in scene by name (a :class:`Scene` is returned unchanged).

    Raises
    ------
    InputError
        For an unknown name; the message lists the valid names.
    """
    if isinstance(name, Scene):
        return name
    if not isinstance(name, str) or name not in SCENES:
        raise InputError("scene", "name", f"unknown scene {name!r}; valid scenes: {', '.join(SCENES)}")
    return SCENES[name]()


# ----------------------------------------------------------------------------
# Reference images
# ----------------------------------------------------------------------------

def _check_int(where, field, value, minimum):
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or int(value) < minimum:
        raise InputError(where, field, f"{value!r}, expected an integer >= {minimum}")
    return int(value)


@functools.lru_cache(maxsize=32)
def _reference_cached(name: str, width: int, height: int, quadrature: int) -> np.ndarray:
    out = get_scene(name)._reference(width, height, quadrature)
    out.setflags(write=False)  # shared between callers: they get copies
    return out


def reference_image(scene, width: int, height: int, *, quadrature: int = 32) -> np.ndarray:
    """The exact-expectation image of a scene, averaged over each pixel's area.

    The expectation over the random dimensions is analytic
    (:meth:`Scene.expected`); the pixel-area average is the midpoint rule
    with ``quadrature x quadrature`` points per pixel (deterministic).
    Where ``expected`` is smooth the rule errs by O(1/q^2); a pixel cut by
    a discontinuity of height J errs by at most J/(2q) per point row
    crossing it (1.6 % of the jump at q = 32).  Results are cached in
    memory by (scene name, size, quadrature).

    Parameters
    ----------
    scene : str or Scene
        A built-in scene name (or instance; cached by its name).
    width, height : int
        Film size in pixels (>= 1).
    quadrature : int
        Midpoint-rule points per pixel and axis (>= 1).

    Returns
    -------
    ndarray (height, width, 3) float64
        A fresh, writable copy.
    """
    sc = get_scene(scene)
    width = _check_int("reference_image", "width", width, 1)
    height = _check_int("reference_image", "height", height, 1)
    quadrature = _check_int("reference_image", "quadrature", quadrature, 1)
    if sc.name in SCENES and type(sc) is SCENES[sc.name]:
        return _reference_cached(sc.name, width, height, quadrature).copy()
    # A user's own Scene: not cached (its name need not be unique).
    return sc._reference(width, height, quadrature)


# ----------------------------------------------------------------------------
# Renderer
# ----------------------------------------------------------------------------

#: Environment variable: the samples per second of every :class:`SceneRenderer` without ``rate=`` (benchmarks).
ENV_SCENE_RATE = "MCRECON_SCENE_RATE"


def _check_rate(rate):
    """``rate`` (or ``$MCRECON_SCENE_RATE`` when None) as a positive float, or None for no limit."""
    where, field = "SceneRenderer", "rate"
    if rate is None:
        raw = os.environ.get(ENV_SCENE_RATE, "").strip()
        if not raw:
            return None
        where, field, rate = "environment", ENV_SCENE_RATE, raw
    try:
        r = float(rate)
    except (TypeError, ValueError):
        r = float("nan")
    if not (r > 0 and math.isfinite(r)) or isinstance(rate, bool):
        raise InputError(where, field, f"{rate!r}: expected a positive number of samples per second (e.g. 2e6), "
                         f"or unset for no limit")
    return r


class SceneRenderer:
    """A built-in scene as a renderer (:class:`mcrecon.renderers.protocol.Renderer`).

    Parameters
    ----------
    scene : str or Scene
        Scene name (see :func:`scene_names`) or instance.
    width, height : int
        Film size in pixels (>= 1).
    seed : int
        Renderer seed (>= 0).  Round random numbers come from
        ``np.random.default_rng([seed, request.seed, request.round_index])``,
        so the same request gives the same samples.
    rate : float, optional
        Benchmarks: samples per second at most; a reply of n samples then
        takes at least n / rate seconds (asleep for the rest; the samples are
        the same).  Default: ``$MCRECON_SCENE_RATE`` when set (so that whole
        commands, ``mcrecon adapt --scene`` and ``render-log``, can stand in
        for a renderer of a realistic speed), else no limit.

    Notes
    -----
    The reply lists the samples for ``request.counts`` first (uniformly
    jittered inside each pixel, sorted by pixel, see
    :func:`mcrecon.core.requests.jittered_positions`), then one sample per
    requested position, in request order.  Values are float64 (N, 3).
    """

    def __init__(self, scene, *, width: int = 128, height: int = 128, seed: int = 0, rate: float | None = None):
        self.scene = get_scene(scene)
        self.width = _check_int("SceneRenderer", "width", width, 1)
        self.height = _check_int("SceneRenderer", "height", height, 1)
        self.seed = _check_int("SceneRenderer", "seed", seed, 0)
        self.rate = _check_rate(rate)
        self.channels = tuple(self.scene.channels)
        self.name = f"scene:{self.scene.name}"

    def render(self, request: SampleRequest) -> SampleBatch:
        """Answer a request (counts first, then explicit positions in order)."""
        if (request.width, request.height) != (self.width, self.height):
            raise InputError(self.name, "request width/height",
                             f"{request.width}x{request.height}, this renderer's film is "
                             f"{self.width}x{self.height}")
        seed = _check_int(self.name, "request.seed", request.seed, 0)
        rnd = _check_int(self.name, "request.round_index", request.round_index, 0)
        t0 = time.perf_counter()
        rng = np.random.default_rng([self.seed, seed, rnd])
        parts = []
        if request.counts is not None:
            parts.append(jittered_positions(request.counts, rng))
        if request.positions is not None:
            parts.append(np.asarray(request.positions, dtype=np.float64))
        pos = np.concatenate(parts, axis=0) if len(parts) > 1 else parts[0]
        u = rng.random((pos.shape[0], self.scene.n_dims))
        values = self.scene.radiance(pos[:, 0] / self.width, pos[:, 1] / self.height, u)
        if self.rate is not None:
            rest = pos.shape[0] / self.rate - (time.perf_counter() - t0)
            if rest > 0:
                time.sleep(rest)
        return SampleBatch(pos, values)

    def reference(self, *, quadrature: int = 32) -> np.ndarray:
        """:func:`reference_image` of this scene at this film size."""
        return reference_image(self.scene, self.width, self.height, quadrature=quadrature)

    def __repr__(self) -> str:
        return f"SceneRenderer({self.scene.name!r}, width={self.width}, height={self.height}, seed={self.seed})"


def render_uniform(scene, *, width: int = 128, height: int = 128, spp: int, seed: int = 0) -> SampleBatch:
    """``spp`` jittered samples in every pixel of a scene (one request, round 0, request seed 0)."""
    r = SceneRenderer(scene, width=width, height=height, seed=seed)
    spp = _check_int("render_uniform", "spp", spp, 1)
    n = spp * r.width * r.height
    check_memory("render_uniform", "spp", 8.0 * n * (2 + len(r.channels)),
                 f"{spp} samples per pixel on {r.width}x{r.height} ({n} samples)", "lower --spp or --size")
    counts = np.full((r.height, r.width), spp, dtype=np.int64)
    return r.render(SampleRequest(r.width, r.height, counts=counts, round_index=0, seed=0))


def write_scene_log(scene, path, *, width: int = 128, height: int = 128, spp: int, seed: int = 0,
                    reference: bool = True, quadrature: int = 32) -> Path:
    """Render ``spp`` samples per pixel of a scene and write them as a sample log.

    The log's metadata is ``{"renderer": "mcrecon.scenes", "scene": name,
    "seed": seed, "settings": {"width", "height", "spp", "quadrature",
    "n_dims"}}``; with ``reference=True`` the :func:`reference_image` is
    stored in it.

    Returns
    -------
    Path
        The log written.
    """
    from ...io import write_log

    sc = get_scene(scene)
    batch = render_uniform(sc, width=width, height=height, spp=spp, seed=seed)
    ref = reference_image(sc, width, height, quadrature=quadrature) if reference else None
    meta = {"renderer": "mcrecon.scenes", "scene": sc.name, "seed": int(seed),
            "settings": {"width": int(width), "height": int(height), "spp": int(spp),
                         "quadrature": int(quadrature), "n_dims": int(sc.n_dims)}}
    return write_log(path, batch.positions, batch.values, width=width, height=height,
                     channels=sc.channels, reference=ref, metadata=meta)
