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
    constant expectation with uniform noise (border and variance tests);
``checker_wall``
    a checkerboard wall (16 px and 4 px squares at 128 px) under a soft
    shadow and a noisy sky: noise-free albedo explains the texture;
``checker_spot``
    the same wall under a small light found by 1 sample in 20 (high
    variance, fireflies over sharp texture);
``checker_dof``
    checkered cards at three depths through a thin lens: colour *and*
    features are blurred and noisy off focus.

Every built-in scene also gives per-sample features of the primary hit
(``albedo``, ``normal``, ``depth``, :meth:`Scene.features`) with exact
expectations (:func:`feature_reference`): computed from the same random
numbers as the colour, so they draw nothing extra.  The textured scenes
send them by default; the others only when asked (``features=True``), so
that their default samples, logs and references stay as they were.

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
from ...core.requests import SampleBatch, SampleRequest, jittered_positions, place_in_pixels, sample_indices
from ..spec_format import scene_spec
from .sobol import SAMPLERS, sobol_points
from .params import PARAMS
from .catalog import (FEATURE_LAYOUT, SCENES, CausticScene, CheckerDofScene, CheckerSpotScene, CheckerWallScene,
                      DepthOfFieldScene, FlatScene, HDRScene, MotionBlurScene, Scene, SoftShadowScene, split_features)

__all__ = ["SCENES", "FEATURE_LAYOUT", "Scene", "SoftShadowScene", "DepthOfFieldScene", "MotionBlurScene",
           "CausticScene", "HDRScene", "FlatScene", "CheckerWallScene", "CheckerSpotScene", "CheckerDofScene",
           "scene_names", "get_scene", "reference_image", "feature_reference", "SceneRenderer", "render_uniform",
           "write_scene_log", "SAMPLERS", "PARAMS"]


def scene_names() -> list[str]:
    """Names of the built-in scenes, in registry order."""
    return list(SCENES)


def get_scene(name, params: dict | None = None, **kwargs) -> Scene:
    """A built-in scene by name, with parameters (a :class:`Scene` is returned unchanged).

    Parameters
    ----------
    name : str or Scene
        A built-in scene name (:func:`scene_names`), or a scene (returned as it is).
    params : dict, optional
        Parameter values by name (:data:`PARAMS` lists each scene's, with
        defaults and ranges); keywords add to them:
        ``get_scene("caustic", power=4.0, hit_probability=0.01)``.

    Raises
    ------
    InputError
        For an unknown name (the message lists the valid names), an unknown
        parameter, a value out of its range, or parameters given with a Scene.
    """
    if isinstance(name, Scene):
        if params or kwargs:
            raise InputError("scene", "params", f"given with the scene {name!r}: pass its name instead")
        return name
    if not isinstance(name, str) or name not in SCENES:
        raise InputError("scene", "name", f"unknown scene {name!r}; valid scenes: {', '.join(SCENES)}")
    return SCENES[name](params, **kwargs)


# ----------------------------------------------------------------------------
# Reference images
# ----------------------------------------------------------------------------

def _check_int(where, field, value, minimum):
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or int(value) < minimum:
        raise InputError(where, field, f"{value!r}, expected an integer >= {minimum}")
    return int(value)


def _averaged(sc, width, height, quadrature, features):
    """The pixel averages of the expected features, or of the expected colour times ``exposure``."""
    if features:
        return sc._feature_reference(width, height, quadrature)
    return sc._expose(sc._reference(width, height, quadrature))


@functools.lru_cache(maxsize=48)
def _reference_cached(name: str, params: tuple, width: int, height: int, quadrature: int,
                      features: bool) -> np.ndarray:
    out = _averaged(get_scene(name, dict(params)), width, height, quadrature, features)
    out.setflags(write=False)  # shared between callers: they get copies
    return out


def _pixel_average(sc, where: str, width, height, quadrature, *, features: bool) -> np.ndarray:
    """The pixel-area average of ``sc``'s expected colour (or features) at checked sizes; read-only when it
    comes from the cache of the built-in scenes."""
    width = _check_int(where, "width", width, 1)
    height = _check_int(where, "height", height, 1)
    quadrature = _check_int(where, "quadrature", quadrature, 1)
    if sc.name in SCENES and type(sc) is SCENES[sc.name]:
        return _reference_cached(sc.name, sc.param_key, width, height, quadrature, features)
    # A user's own Scene: not cached (its name need not be unique).
    return _averaged(sc, width, height, quadrature, features)


def reference_image(scene, width: int, height: int, *, quadrature: int = 32) -> np.ndarray:
    """The exact-expectation image of a scene, averaged over each pixel's area.

    The expectation over the random dimensions is analytic
    (:meth:`Scene.expected`); the pixel-area average is the midpoint rule
    with ``quadrature x quadrature`` points per pixel (deterministic).
    Where ``expected`` is smooth the rule errs by O(1/q^2); a pixel cut by
    a discontinuity of height J errs by at most J/(2q) per point row
    crossing it (1.6 % of the jump at q = 32).  Results are cached in
    memory by (scene name, parameters, size, quadrature).

    Parameters
    ----------
    scene : str or Scene
        A built-in scene name (or instance, e.g. from :func:`get_scene` with parameters; cached by its
        name and parameters).
    width, height : int
        Film size in pixels (>= 1).
    quadrature : int
        Midpoint-rule points per pixel and axis (>= 1).

    Returns
    -------
    ndarray (height, width, 3) float64
        A fresh, writable copy.
    """
    return _pixel_average(get_scene(scene), "reference_image", width, height, quadrature, features=False).copy()


def feature_reference(scene, width: int, height: int, *, quadrature: int = 32) -> dict:
    """The exact expected features of a scene, averaged over each pixel's area.

    What the per-pixel means of the features converge to: the pixel-area
    average (midpoint rule, ``quadrature x quadrature`` points, as
    :func:`reference_image`, with the same error bounds) of
    :meth:`Scene.expected_features`, itself exact over the random
    dimensions.  A normal's pixel average is not of unit length where the
    pixel sees several surfaces (that is what a pixel mean of normals is).

    Parameters
    ----------
    scene, width, height, quadrature
        As for :func:`reference_image`; the scene needs ``feature_names``.

    Returns
    -------
    dict
        ``{"albedo": (H, W, 3), "normal": (H, W, 3), "depth": (H, W, 1)}``
        float64, fresh writable arrays.

    Raises
    ------
    InputError
        For a scene without features.
    """
    sc = get_scene(scene)
    sc._check_has_features("feature_reference")
    arr = _pixel_average(sc, "feature_reference", width, height, quadrature, features=True)
    return {name: np.array(a) for name, a in split_features(arr).items()}


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
    features : bool or None
        Send the per-sample features (``albedo`` (N, 3), ``normal`` (N, 3),
        ``depth`` (N, 1)) in each reply's ``SampleBatch.features``.  None
        (default): the scene's ``features_default`` (on for the textured
        scenes, off for the others).
    rate : float, optional
        Benchmarks: samples per second at most; a reply of n samples then
        takes at least n / rate seconds (asleep for the rest; the samples are
        the same).  Default: ``$MCRECON_SCENE_RATE`` when set (so that whole
        commands, ``mcrecon adapt --scene`` and ``render-log``, can stand in
        for a renderer of a realistic speed), else no limit.
    sampler : {"independent", "sobol"}
        ``"independent"`` (default): uniform random numbers from the round's
        generator (above).  ``"sobol"``: each pixel's own Owen-scrambled Sobol
        sequence over all dimensions (film x, y and the scene's random
        numbers; :mod:`.sobol`), continued from ``request.first_index``: a
        sample is a function of (pixel, its index there, ``seed``) alone, not
        of the request's seed or round, so rounds of 8 + 8 + 8 + 8 samples are
        the samples of one 32-sample request.  It is the renderer's declared
        sampler too (``Renderer.sampler``, docs/renderer-protocol.md): an
        adaptive run's methods follow it (``net_counts=-1``).

    Notes
    -----
    The reply lists the samples for ``request.counts`` first (uniformly
    jittered inside each pixel, sorted by pixel, see
    :func:`mcrecon.core.requests.jittered_positions`), then one sample per
    requested position, in request order.  Values are float64 (N, 3).  The
    features are functions of the same random numbers as the colour, so
    turning them on or off leaves positions and values bit-identical.
    """

    #: Every reply's arrays are new (never a buffer the renderer fills again): the driver keeps them
    #: for the log while the next round renders, without a copy (renderers without it are copied).
    fresh_replies = True

    def __init__(self, scene, *, width: int = 128, height: int = 128, seed: int = 0, features=None,
                 rate: float | None = None, sampler: str = "independent"):
        if sampler not in SAMPLERS:
            raise InputError("SceneRenderer", "sampler", f"{sampler!r}, expected one of {', '.join(SAMPLERS)}")
        self.scene = get_scene(scene)
        self.width = _check_int("SceneRenderer", "width", width, 1)
        self.height = _check_int("SceneRenderer", "height", height, 1)
        self.seed = _check_int("SceneRenderer", "seed", seed, 0)
        self.features = _check_features_flag("SceneRenderer", self.scene, features)
        self.rate = _check_rate(rate)
        self.channels = tuple(self.scene.channels)
        self.feature_names = tuple(self.scene.feature_names) if self.features else ()
        self.name = f"scene:{self.scene.name}"
        self.sampler = sampler

    def spec(self) -> dict:
        """How to build this renderer again (:mod:`mcrecon.renderers.spec_format`); features other than the
        scene's default are recorded, a sampler other than ``independent``, and the scene's parameters that
        differ from its defaults.  ``rate`` changes no reply:
        not recorded."""
        default = _check_features_flag(self.name, self.scene, None)
        return scene_spec(self.scene.name, width=self.width, height=self.height, seed=self.seed,
                          features=None if self.features == default else self.features,
                          sampler=None if self.sampler == "independent" else self.sampler,
                          params=self.scene.params or None)

    def render(self, request: SampleRequest) -> SampleBatch:
        """Answer a request (counts first, then explicit positions in order)."""
        if (request.width, request.height) != (self.width, self.height):
            raise InputError(self.name, "request width/height",
                             f"{request.width}x{request.height}, this renderer's film is "
                             f"{self.width}x{self.height}")
        seed = _check_int(self.name, "request.seed", request.seed, 0)
        rnd = _check_int(self.name, "request.round_index", request.round_index, 0)
        t0 = time.perf_counter()
        if self.sampler == "sobol":
            pos, u = self._sobol(request)
        else:
            rng = np.random.default_rng([self.seed, seed, rnd])
            parts = []
            if request.counts is not None:
                parts.append(jittered_positions(request.counts, rng))
            if request.positions is not None:
                parts.append(np.asarray(request.positions, dtype=np.float64))
            pos = np.concatenate(parts, axis=0) if len(parts) > 1 else parts[0]
            u = rng.random((pos.shape[0], self.scene.n_dims))
        return self._shade(pos, u, t0)

    def _sobol(self, request):
        """Positions (N, 2) and random numbers (N, n_dims) of a request from the pixels' Sobol sequences:
        counted samples pixel by pixel in row-major order (as the independent sampler), then the explicit
        positions, whose film dimensions are the requested ones (the rest of their point is used)."""
        w, h = self.width, self.height
        counts = (np.zeros(w * h, np.int64) if request.counts is None
                  else np.ascontiguousarray(request.counts, np.int64).ravel())
        pix = np.repeat(np.arange(w * h, dtype=np.int64), counts)
        if request.positions is not None:
            ep = np.asarray(request.positions, dtype=np.float64)
            pix = np.concatenate([pix, ep[:, 1].astype(np.int64) * w + ep[:, 0].astype(np.int64)])
        pts = sobol_points(pix, sample_indices(request), 2 + self.scene.n_dims, seed=self.seed)
        nc = int(counts.sum())
        pos = place_in_pixels(np.ascontiguousarray(pts[:, :2]), counts, w)  # in place; counted rows only
        if request.positions is not None:
            pos[nc:] = ep
        return pos, np.ascontiguousarray(pts[:, 2:])

    def uniform_rows(self, spp: int, start: int, stop: int) -> SampleBatch:
        """Rows ``start:stop`` of :meth:`render`'s reply to a uniform request of ``spp`` samples per pixel.

        The request :func:`render_uniform` makes (counts ``spp`` everywhere,
        round 0, request seed 0), answered a block of rows at a time and bit
        for bit: the independent sampler's generator jumps ahead to the
        block's random numbers (``PCG64.advance``: one 64-bit draw per
        float64, positions first, then the scene's numbers), the Sobol
        sampler's points are functions of (pixel, index, seed).  Memory is
        that of the block.
        """
        spp = _check_int(self.name, "spp", spp, 1)
        n = spp * self.width * self.height
        if not 0 <= start <= stop <= n:
            raise InputError(self.name, "rows", f"{start}:{stop}, expected 0 <= start <= stop <= {n}")
        t0 = time.perf_counter()
        k = np.arange(start, stop, dtype=np.int64)
        pix = k // spp
        d = self.scene.n_dims
        if self.sampler == "sobol":
            pts = sobol_points(pix, k - pix * spp, 2 + d, seed=self.seed)
            jitter, u = pts[:, :2], np.ascontiguousarray(pts[:, 2:])
        else:
            def draws(skip, shape):
                bits = np.random.PCG64([self.seed, 0, 0])   # default_rng([seed, request seed, round])
                bits.advance(skip)
                return np.random.Generator(bits).random(shape)
            jitter = draws(2 * start, (stop - start, 2))
            u = draws(2 * n + d * start, (stop - start, d))
        # as place_in_pixels: the pixel's corner plus the jitter, kept inside the pixel
        cell = np.stack([pix % self.width, pix // self.width], 1).astype(np.float64)
        pos = cell + jitter
        edge = cell + 1.0
        np.copyto(pos, np.nextafter(edge, 0.0), where=pos >= edge)
        return self._shade(pos, u, t0)

    def _shade(self, pos: np.ndarray, u: np.ndarray, t0: float) -> SampleBatch:
        """The batch of samples at film positions ``pos`` with random numbers ``u``: radiance, features
        when kept, and the wait that holds a ``rate`` (samples per second) counted from ``t0``."""
        x, y = pos[:, 0] / self.width, pos[:, 1] / self.height
        values = self.scene.radiance(x, y, u)
        feats = self.scene.features(x, y, u) if self.features else None
        if self.rate is not None:
            rest = pos.shape[0] / self.rate - (time.perf_counter() - t0)
            if rest > 0:
                time.sleep(rest)
        return SampleBatch(pos, values) if feats is None else SampleBatch(pos, values, feats)

    def reference(self, *, quadrature: int = 32) -> np.ndarray:
        """:func:`reference_image` of this scene at this film size."""
        return reference_image(self.scene, self.width, self.height, quadrature=quadrature)

    def feature_reference(self, *, quadrature: int = 32) -> dict:
        """:func:`feature_reference` of this scene at this film size."""
        return feature_reference(self.scene, self.width, self.height, quadrature=quadrature)

    def __repr__(self) -> str:
        extra = "" if self.features == self.scene.features_default else f", features={self.features}"
        extra += f", params={self.scene.params!r}" if self.scene.params else ""
        extra += "" if self.sampler == "independent" else f", sampler={self.sampler!r}"
        return (f"SceneRenderer({self.scene.name!r}, width={self.width}, height={self.height}, seed={self.seed}"
                f"{extra})")


def _check_features_flag(where, scene, features) -> bool:
    """``features`` (None: the scene's default) as a bool, refused for a scene without features."""
    if features is None:
        return bool(scene.features_default and scene.feature_names)
    if not isinstance(features, (bool, np.bool_)):
        raise InputError(where, "features", f"{features!r}, expected True, False or None (the scene's default)")
    if features and not scene.feature_names:
        raise InputError(where, "features", f"scene {scene.name!r} has no per-sample features; pass "
                         "features=False, or use a built-in scene")
    return bool(features)


def render_uniform(scene, *, width: int = 128, height: int = 128, spp: int, seed: int = 0,
                   features=None, sampler: str = "independent") -> SampleBatch:
    """``spp`` jittered samples in every pixel of a scene (one request, round 0, request seed 0).

    ``features``, ``sampler``: as :class:`SceneRenderer` (None: the scene's default features).
    """
    r = SceneRenderer(scene, width=width, height=height, seed=seed, features=features, sampler=sampler)
    spp = _check_int("render_uniform", "spp", spp, 1)
    n = spp * r.width * r.height
    n_feat = sum(FEATURE_LAYOUT.values()) if r.features else 0
    check_memory("render_uniform", "spp", 8.0 * n * (2 + len(r.channels) + n_feat),
                 f"{spp} samples per pixel on {r.width}x{r.height} ({n} samples)", "lower --spp or --size")
    counts = np.full((r.height, r.width), spp, dtype=np.int64)
    return r.render(SampleRequest(r.width, r.height, counts=counts, round_index=0, seed=0))


#: Samples :func:`write_scene_log` renders and writes at a time (a multiple of the log's HDF5 chunk rows):
#: about 100 bytes a sample while a block is in flight with features, so memory is this block plus the image.
LOG_BLOCK_SAMPLES = 1 << 20


def write_scene_log(scene, path, *, width: int = 128, height: int = 128, spp: int, seed: int = 0,
                    reference: bool = True, quadrature: int = 32, features=None,
                    sampler: str = "independent", block_samples: int = LOG_BLOCK_SAMPLES) -> Path:
    """Render ``spp`` samples per pixel of a scene and write them as a sample log.

    The log's metadata is ``{"renderer": "mcrecon.scenes", "scene": name,
    "seed": seed, "settings": {"width", "height", "spp", "quadrature",
    "n_dims"}}``; with ``reference=True`` the :func:`reference_image` is
    stored in it.  With features (``features=True``, or None for a scene
    whose ``features_default`` is on) the log holds ``/features/albedo``,
    ``/features/normal`` and ``/features/depth`` per sample and the
    settings say ``"features": [names]``; without them the log is exactly
    what it was before scenes had features.  ``sampler``: as :class:`SceneRenderer`; one other than
    ``independent`` is recorded in the settings (``"sampler"``); a scene's parameters other than the
    defaults under ``"params"``.

    The samples are those of :func:`render_uniform`, rendered and written
    ``block_samples`` at a time (:meth:`SceneRenderer.uniform_rows`,
    :func:`mcrecon.io.log_stream.stream_log`): the file holds the same rows
    whatever the block, and memory is bounded by a block and the image,
    not by the log.

    Returns
    -------
    Path
        The log written.
    """
    from ...io.log_stream import stream_log

    block = _check_int("write_scene_log", "block_samples", block_samples, 1)
    r = SceneRenderer(scene, width=width, height=height, seed=seed, features=features, sampler=sampler)
    sc = r.scene
    spp = _check_int("write_scene_log", "spp", spp, 1)
    n = spp * r.width * r.height
    ref = reference_image(sc, width, height, quadrature=quadrature) if reference else None
    meta = {"renderer": "mcrecon.scenes", "scene": sc.name, "seed": int(seed),
            "settings": {"width": int(width), "height": int(height), "spp": int(spp),
                         "quadrature": int(quadrature), "n_dims": int(sc.n_dims)}}
    names = list(FEATURE_LAYOUT) if r.features else []   # Scene.features gives every one of them
    if names:
        meta["settings"]["features"] = names
    if sampler != "independent":
        meta["settings"]["sampler"] = sampler
    if sc.params:
        meta["params"] = dict(sc.params)
    # float32 like the renderer bridges write (half the bytes of float64; positions stay in their pixel)
    feats = {name: ((FEATURE_LAYOUT[name],), np.float32) for name in names}
    # a stratified sampler is declared as the log's sampler attribute too (its halves then split by prefix
    # blocks); the independent sampler's log stays without it, as before scenes had samplers
    with stream_log(path, n, width=width, height=height, channels=sc.channels, features=feats, reference=ref,
                    metadata=meta, sampler=None if sampler == "independent" else sampler) as out:
        for a in range(0, n, block):
            b = r.uniform_rows(spp, a, min(n, a + block))
            out.write(b.positions, np.asarray(b.values, np.float32),
                      features={k: np.asarray(v, np.float32) for k, v in (b.features or {}).items()})
    return Path(path)
