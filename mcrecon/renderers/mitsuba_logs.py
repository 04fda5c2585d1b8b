"""Mitsuba 3 bridge: high-spp references and uniform sample logs (re-exported by :mod:`.mitsuba`).

Both go through :class:`~mcrecon.renderers.mitsuba.MitsubaRenderer`, so a
reference estimates exactly what mcrecon reconstructs from the bridge's
samples, and a log holds the bridge's samples and (by default) their
per-sample features.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from ..core.requests import SampleRequest
from ..core.samples import pixel_index
from .spec_format import MITSUBA_FEATURES, check_mitsuba_features

__all__ = ["render_reference", "dump_uniform_log"]

#: The bridge's renderer class, which builds a renderer from a scene argument (None, a path or a dict).
#: :mod:`.mitsuba` defines it and re-exports this module's functions as part of its interface; it hands
#: the class over here when it does, so this module never imports the bridge back.
_renderer_class = None


def _check_int(field, value, *, minimum, allow_none=False, extra=()):
    """``value`` as an int >= ``minimum`` (or one of ``extra``; None with ``allow_none``), else an
    :class:`InputError` naming the bridge and ``field`` (the bridge's own options use it too)."""
    if value is None and allow_none:
        return None
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) \
            or (value < minimum and value not in extra):
        valid = f"an integer >= {minimum}" + ("".join(f" or {e}" for e in extra))
        raise InputError("MitsubaRenderer", field,
                         f"got {value!r}, expected {valid}" + (" or None" if allow_none else ""))
    return int(value)


def _make_renderer(scene, width, height, variant, max_depth, spp_per_pass, features="all"):
    if isinstance(scene, _renderer_class):
        if (width or scene.width, height or scene.height) != (scene.width, scene.height):
            raise InputError(scene.name, "width/height", f"requested {width}x{height}, the renderer's film is "
                             f"{scene.width}x{scene.height}")
        return scene
    return _renderer_class(scene, width=width, height=height, variant=variant, max_depth=max_depth,
                           spp_per_pass=spp_per_pass, features=features)


def _uniform_passes(renderer, spp: int, seed: int, features: tuple[str, ...] = ()):
    """Yield uniform batches (positions, values, features), one per pass of <= spp_per_pass spp."""
    done, k = 0, 0
    while done < spp:
        m = min(renderer.spp_per_pass, spp - done)
        counts = np.full((renderer.height, renderer.width), m, np.int64)
        yield renderer._render(SampleRequest(renderer.width, renderer.height, counts=counts,
                                             round_index=k, seed=seed), features)
        done += m
        k += 1


def render_reference(scene=None, *, width: int | None = None, height: int | None = None, spp: int = 1024,
                     seed: int = 0, variant: str = "llvm_ad_rgb", max_depth: int | None = None,
                     spp_per_pass: int = 16) -> np.ndarray:
    """A high-spp reference image: the per-pixel mean of ``spp`` jittered samples.

    It goes through the bridge (not ``mi.render``) so that it estimates
    exactly what mcrecon reconstructs from the bridge's samples: the box
    integral of the radiance over each pixel, without Mitsuba's film
    reconstruction filter (Gaussian in the Cornell box) and with the same
    integrator settings.

    Parameters
    ----------
    scene : None, path, dict or MitsubaRenderer
        As :class:`MitsubaRenderer` (an existing renderer is reused).
    width, height : int, optional
        Film size (default 128 x 128 for the Cornell box).
    spp : int
        Samples per pixel.
    seed : int
        Seeds the passes (use a seed different from the one of the samples
        being evaluated: the reference must be independent of them).
    variant, max_depth, spp_per_pass
        As :class:`MitsubaRenderer`.

    Returns
    -------
    ndarray of float64, shape (H, W, 3)
        Accumulated in float64; never clipped.

    References
    ----------
    .. [1] W. Jakob et al., "Mitsuba 3 renderer", 2022.
    """
    spp = _check_int("spp", spp, minimum=1)
    seed = _check_int("seed", seed, minimum=0)
    r = _make_renderer(scene, width, height, variant, max_depth, spp_per_pass, features="none")
    acc = np.zeros((r.height * r.width, 3), np.float64)
    for batch in _uniform_passes(r, spp, seed):
        idx = pixel_index(batch.positions, r.width)
        for c in range(3):
            acc[:, c] += np.bincount(idx, weights=batch.values[:, c].astype(np.float64), minlength=acc.shape[0])
    return (acc / spp).reshape(r.height, r.width, 3)


def _to_float32_positions(pos: np.ndarray) -> np.ndarray:
    """float32 copies of film positions that stay inside their pixels.

    Rounding i + u (u just below 1) to float32 can give i + 1, moving the
    sample to the next pixel (or off the film); clamp to the largest float32
    below i + 1.
    """
    cell = np.floor(pos)
    p32 = pos.astype(np.float32)
    return np.minimum(p32, np.nextafter((cell + 1).astype(np.float32), np.float32(0)))


def dump_uniform_log(path, scene=None, *, width: int | None = None, height: int | None = None, spp: int = 16,
                     seed: int = 0, reference_spp: int | None = None, variant: str = "llvm_ad_rgb",
                     max_depth: int | None = None, spp_per_pass: int = 16, features=None):
    """Render ``spp`` uniform jittered samples per pixel into an mcrecon sample log.

    The log (``mcrecon.io.write_log`` format) holds one round per pass of at
    most ``spp_per_pass`` samples per pixel, float32 positions and values,
    metadata naming the renderer, scene, variant, integrator depth, spp,
    seed and the Mitsuba version, and, with ``reference_spp``, a reference
    from :func:`render_reference` rendered with an independent seed.  The
    file is written under a temporary name and renamed when complete, so a
    crash never leaves a partial log at ``path``.

    Parameters
    ----------
    path : path-like
        The ``.h5`` log to write.
    scene, width, height, variant, max_depth, spp_per_pass
        As :class:`MitsubaRenderer`.
    spp : int
        Samples per pixel in the log.
    seed : int
        Seed of the samples.
    reference_spp : int, optional
        Samples per pixel of the stored reference (none when omitted).
    features : None, "all", "none" or sequence of str
        Per-sample features stored as ``/features/NAME`` (see
        :class:`MitsubaRenderer`).  None (default): all (albedo, normal,
        depth), or with a :class:`MitsubaRenderer` as ``scene`` the ones it
        was built with; otherwise a subset of those.

    Returns
    -------
    pathlib.Path
    """
    from ..io import append_log, write_log
    from ..io._atomic import atomic_path
    from ..io.writer import check_log_fits

    spp = _check_int("spp", spp, minimum=1)
    seed = _check_int("seed", seed, minimum=0)
    reference_spp = _check_int("reference_spp", reference_spp, minimum=1, allow_none=True)
    names = None if features is None else check_mitsuba_features(features, where="dump_uniform_log")
    path = Path(path)
    r = _make_renderer(scene, width, height, variant, max_depth, spp_per_pass,
                       features="all" if names is None else names)
    if names is None:
        names = r.features
    missing = [f for f in names if f not in r.features]
    if missing:
        raise InputError(r.name, "features", f"{', '.join(missing)} asked for, but this renderer was built with "
                         f"features={','.join(r.features) or 'none'!r}")
    n_comp = len(r.channels) + sum(MITSUBA_FEATURES[f] for f in names)
    check_log_fits(path, spp * r.width * r.height, n_comp, where="mitsuba log", spp=spp,
                   film="--size" if r._spec_scene is None else "the film's width/height in the scene")
    reference = None
    if reference_spp is not None:
        # An independent stream: the reference must not share noise with the samples.
        ref_seed = int(np.random.SeedSequence([seed, 0x726566]).generate_state(1, np.uint32)[0])
        reference = render_reference(r, width=r.width, height=r.height, spp=reference_spp, seed=ref_seed)
    metadata = {"renderer": "mitsuba", "mitsuba_version": r._mi.__version__, "variant": r.variant,
                "scene": r.scene_name, "max_depth": r.max_depth, "integrator": str(r._integrator).split("[")[0].strip(),
                "sampling": "uniform jittered", "spp": spp, "seed": seed, "spp_per_pass": r.spp_per_pass,
                "reference_spp": reference_spp, "positions": "x = column, y = row from the top",
                "features": ",".join(names) or "none"}
    if names:
        metadata["features_definition"] = ("primary hit; albedo: BSDF diffuse reflectance, 1 without a diffuse lobe; "
                                           "normal: world-space shading normal; depth: camera-space z; "
                                           "0 where the ray hits nothing")
    with atomic_path(path) as tmp:
        first = True
        for k, batch in enumerate(_uniform_passes(r, spp, seed, names)):
            pos = _to_float32_positions(batch.positions)
            if first:
                write_log(tmp, pos, batch.values, width=r.width, height=r.height, channels=r.channels,
                          rounds=np.zeros(len(batch), np.int32), reference=reference, metadata=metadata,
                          features=batch.features or None)
                first = False
            else:
                append_log(tmp, pos, batch.values, round_index=k, features=batch.features or None)
    return path
