"""Blender Cycles bridge: sample logs whose sample k of a pixel is Cycles' own sample k.

Cycles does not hand out individual samples, but a render with a sample
subset of length one (``cycles.use_sample_subset``, ``sample_offset = k``,
``sample_subset_length = 1``, ``samples = N``) renders exactly sample k of
every pixel's N-sample pattern.  Rendering k = 0 .. N-1 gives N values per
pixel that keep the stratification of Cycles' own N-sample render, so a log
of them averages to Cycles' image far more closely than N independent
samples would (measured in ``docs/blender.md``).

What one log holds, per sample:

- colour: the Combined pass (linear, scene-referred; see :data:`LINEAR_SETTINGS`
  for the settings forced on every render so that it is);
- features (optional): Cycles' Denoising Albedo (3), Denoising Normal (3)
  and Denoising Depth (1) passes, stored as Cycles writes them.  The albedo
  holds an emitter's radiance (above 1) where a path through a mirror or
  glass ends on a light: mcrecon stores it as given;
- film position: Cycles keeps each sample's offset within its pixel to
  itself (a per-pixel scrambled sequence).  The bridge measures it with a
  *probe* render of the same sample index, film size, seed and sampling
  pattern, whose scene is reduced to a world shader that emits the camera
  ray's window coordinate (its film position over the film size): the
  filter offset is drawn from dimensions of the sample pattern that no
  scene content changes, so the probe's sample k sits where the scene's
  sample k sat.  Positions are in mcrecon's convention (``x`` the column,
  ``y`` the row counted from the top).

bpy (Blender as a Python module) is optional (``pip install
'mcrecon[blender]'``); this module imports it only when it renders.
"""

from __future__ import annotations

import contextlib
import importlib.util
import os
import tempfile
from pathlib import Path

import numpy as np

from ..errors import InputError, RendererError

__all__ = ["BLENDER_FEATURES", "LINEAR_SETTINGS", "bpy_available", "check_blender_features", "open_blend",
           "render_reference", "dump_cycles_log", "BPY_MISSING"]

#: The per-sample features the bridge can store, and their components
#: (Cycles' Denoising Albedo, Normal and Depth passes).
BLENDER_FEATURES: dict[str, int] = {"albedo": 3, "normal": 3, "depth": 1}
_FEATURE_PASSES = {"albedo": ("Denoising Albedo", "RGB"), "normal": ("Denoising Normal", "XYZ"),
                   "depth": ("Denoising Depth", "Z")}

#: What every render of the bridge forces, so that the Combined pass is the
#: scene's linear radiance, one sample per pixel is that sample's value, and a
#: log and a reference of the same file are the same estimator.
LINEAR_SETTINGS: dict[str, object] = {
    "view_transform": "Standard", "look": "None", "exposure": 0.0, "gamma": 1.0,
    "sample_clamp_direct": 0.0, "sample_clamp_indirect": 0.0, "film_transparent": False,
    "pixel_filter_type": "BOX", "filter_width": 1.0, "use_adaptive_sampling": False,
    "use_denoising": False, "use_compositing": False, "use_sequencer": False, "use_border": False,
    "use_animated_seed": False, "output": "OPEN_EXR_MULTILAYER, 32-bit float",
}

#: The one line a missing bpy gives.
BPY_MISSING = "needs bpy: pip install 'mcrecon[blender]'"

#: The header bytes of a .blend file: plain, gzip-compressed or zstd-compressed.
_BLEND_MAGIC = (b"BLENDER", b"\x1f\x8b", b"\x28\xb5\x2f\xfd")


def bpy_available() -> bool:
    """Whether ``import bpy`` can work here (without importing it: it takes a second)."""
    return importlib.util.find_spec("bpy") is not None


@contextlib.contextmanager
def _quiet():
    """Send what Blender prints (render progress on the process's stdout, the import's warnings on its
    stderr, both from C code) to a temporary file, and yield a function returning its last lines, for
    the error message when a render fails."""
    import sys

    for s in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            s.flush()
    with tempfile.TemporaryFile(mode="w+b") as log:
        saved = [os.dup(1), os.dup(2)]
        try:
            os.dup2(log.fileno(), 1)
            os.dup2(log.fileno(), 2)

            def tail(n: int = 3) -> str:
                log.seek(0)
                lines = [x for x in log.read().decode("utf-8", "replace").splitlines() if x.strip()]
                return " | ".join(lines[-n:])

            yield tail
        finally:
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            for fd in saved:
                os.close(fd)


def _bpy():
    if not bpy_available():
        raise InputError("bpy", "import", BPY_MISSING)
    with _quiet():
        import bpy
    return bpy


def check_blender_features(features, *, where: str = "--features") -> tuple[str, ...]:
    """The feature names asked for, in :data:`BLENDER_FEATURES` order: ``"all"``, ``"none"`` (or None,
    or empty), a comma-separated string or a sequence of names."""
    if features is None or features == "none":
        return ()
    if features == "all":
        return tuple(BLENDER_FEATURES)
    names = [x.strip() for x in features.split(",")] if isinstance(features, str) else [str(x) for x in features]
    bad = [x for x in names if x not in BLENDER_FEATURES]
    if bad:
        raise InputError(where, "features", f"{','.join(bad)!r}: valid are all, none, or a list of "
                         f"{', '.join(BLENDER_FEATURES)}")
    return tuple(f for f in BLENDER_FEATURES if f in names)


def _check_blend(path) -> Path:
    p = Path(path)
    if not p.is_file():
        raise InputError(str(p), "scene", "no such file: expected a .blend file")
    if p.suffix.lower() != ".blend":
        raise InputError(str(p), "scene", "expected a Blender file ending in .blend")
    with open(p, "rb") as f:
        head = f.read(8)
    if not head.startswith(_BLEND_MAGIC):
        raise InputError(str(p), "scene", "not a Blender file (its first bytes are not a .blend header)")
    return p


class _Scene:
    """A .blend file opened in bpy with the bridge's settings applied."""

    def __init__(self, bpy, path: Path, *, spp: int, size, camera, threads):
        self.bpy, self.path = bpy, path
        with _quiet() as tail:
            try:
                bpy.ops.wm.open_mainfile(filepath=str(path), load_ui=False)
            except RuntimeError:
                raise InputError(str(path), "scene", f"Blender could not open it: {tail()}") from None
        sc = self.scene = bpy.context.scene
        if camera is not None:
            obj = sc.objects.get(camera)
            if obj is None or obj.type != "CAMERA":
                names = sorted(o.name for o in sc.objects if o.type == "CAMERA")
                raise InputError("--camera", "camera", f"{camera!r} is not a camera of scene {sc.name!r} in "
                                 f"{path}; its cameras: {', '.join(map(repr, names)) or 'none'}")
            sc.camera = obj
        if sc.camera is None:
            raise InputError(str(path), "camera", f"scene {sc.name!r} has no active camera; give --camera NAME")
        r = sc.render
        if size is not None:
            r.resolution_x, r.resolution_y = int(size[0]), int(size[1])
            r.resolution_percentage = 100
        self.width = r.resolution_x * r.resolution_percentage // 100
        self.height = r.resolution_y * r.resolution_percentage // 100
        if self.width < 1 or self.height < 1:
            raise InputError(str(path), "--size", f"the scene's film is {self.width}x{self.height}; give --size WxH")
        r.engine = "CYCLES"
        cy = sc.cycles
        cy.device = "CPU"
        if threads is not None:
            r.threads_mode, r.threads = "FIXED", int(threads)
        r.use_persistent_data = True
        vs = sc.view_settings
        vs.view_transform, vs.look, vs.exposure, vs.gamma = "Standard", "None", 0.0, 1.0
        cy.sample_clamp_direct = cy.sample_clamp_indirect = 0.0
        r.film_transparent = False
        cy.pixel_filter_type, cy.filter_width = "BOX", 1.0
        cy.use_adaptive_sampling = False
        cy.use_denoising = False
        cy.use_animated_seed = False
        r.use_compositing = r.use_sequencer = r.use_border = False
        cy.samples = int(spp)
        r.use_single_layer = True
        self.layer = bpy.context.view_layer
        self.layer.use_pass_combined = True
        im = r.image_settings
        im.file_format, im.color_depth, im.exr_codec = "OPEN_EXR_MULTILAYER", "32", "NONE"
        self.spp = int(spp)

    def settings(self) -> dict:
        """What the log's metadata states of the render."""
        sc, cy = self.scene, self.scene.cycles
        return {"blender_version": self.bpy.app.version_string, "scene": self.path.name,
                "scene_name": sc.name, "view_layer": self.layer.name, "camera": sc.camera.name,
                "seed": int(cy.seed), "sampling_pattern": str(cy.sampling_pattern), "max_bounces": int(cy.max_bounces),
                "film_exposure": float(cy.film_exposure), **LINEAR_SETTINGS}

    def render(self, out: Path, *, offset: int | None, features: bool, region=None, scene=None) -> dict:
        """Render to ``out`` (sample ``offset`` alone, or all N samples with None); its channels.

        ``region`` ``(x0, x1, y0, y1)``: only the pixels of columns ``[x0, x1)`` and rows ``[y0, y1)``
        from the top (Cycles' render border, not cropped: the image keeps the film's size and the pixels
        outside are not rendered); ``scene``: another bpy scene of the file to render (the probe's)."""
        sc = self.scene if scene is None else scene
        cy, r = sc.cycles, sc.render
        cy.use_sample_subset = offset is not None
        if offset is not None:
            cy.sample_offset, cy.sample_subset_length = int(offset), 1
        (self.layer if scene is None else sc.view_layers[self.layer.name]).cycles.denoising_store_passes = bool(features)
        r.use_border = region is not None
        if region is not None:
            x0, x1, y0, y1 = region
            r.use_crop_to_border = False
            # the border in film fractions from the bottom left; whole pixels map to whole pixels
            r.border_min_x, r.border_max_x = x0 / self.width, x1 / self.width
            r.border_min_y, r.border_max_y = 1.0 - y1 / self.height, 1.0 - y0 / self.height
        r.filepath = str(out)
        with _quiet() as tail:
            try:
                self.bpy.ops.render.render(write_still=True, scene=sc.name)
            except RuntimeError:
                raise RendererError("blender", "render", f"Cycles failed on {self.path}: {tail()}") from None
        if not out.is_file():
            raise RendererError("blender", "render", f"Cycles wrote no image for {self.path}")
        return _read_channels(out)

    def probe_scene(self):
        """A second scene of the file that is the film-position probe of this one (see :meth:`probe`):
        a copy of its settings (seed, sampling pattern, samples, film) with nothing in it but a copy of
        the camera without depth of field, and a world emitting the window coordinate.  The scene
        itself stays as it is, so colour and probe renders can alternate."""
        bpy, sc = self.bpy, self.scene
        pr = sc.copy()
        pr.name = "mcrecon_film_position_probe"
        for child in list(pr.collection.children):
            pr.collection.children.unlink(child)
        for obj in list(pr.collection.objects):
            pr.collection.objects.unlink(obj)
        cam = sc.camera.copy()
        cam.data = sc.camera.data.copy()
        cam.data.dof.use_dof = False
        cam.animation_data_clear()
        pr.collection.objects.link(cam)
        pr.camera = cam
        pr.render.use_motion_blur = False
        pr.cycles.film_exposure = 1.0
        pr.world = self._probe_world()
        return pr

    def _probe_world(self):
        w = self.bpy.data.worlds.new("mcrecon_film_position_probe")
        w.use_nodes = True
        nt = w.node_tree
        bg = nt.nodes["Background"]
        tc = nt.nodes.new("ShaderNodeTexCoord")
        nt.links.new(tc.outputs["Window"], bg.inputs["Color"])
        bg.inputs["Strength"].default_value = 1.0
        with contextlib.suppress(AttributeError):
            w.cycles.sampling_method = "NONE"  # no importance map of a world no light path samples
        return w

    def probe(self):
        """Turn the scene into the film-position probe: every object hidden but the camera, a world
        emitting the window coordinate, no depth of field or motion blur (their sample dimensions are not
        the filter's), film exposure 1."""
        bpy, sc = self.bpy, self.scene
        for obj in sc.objects:
            if obj != sc.camera:
                obj.hide_render = True
        sc.camera.data.dof.use_dof = False
        sc.render.use_motion_blur = False
        sc.cycles.film_exposure = 1.0
        sc.world = self._probe_world()


def _read_channels(path: Path) -> dict:
    from ..io.images import open_exr  # every EXR is opened in io/

    return {name: np.asarray(a, dtype=np.float32) for name, a in open_exr(path)[0].items()}


def _pass(channels: dict, layer: str, name: str, comps: str, where) -> np.ndarray:
    keys = [f"{layer}.{name}.{c}" for c in comps]
    missing = [k for k in keys if k not in channels]
    if missing:
        raise RendererError("blender", "passes", f"Cycles' image of {where} has no {', '.join(missing)}")
    return np.stack([channels[k] for k in keys], axis=-1)


def open_blend(path, *, spp: int, size=None, camera: str | None = None, threads: int | None = None) -> _Scene:
    """Open ``path`` in bpy with the bridge's settings (:data:`LINEAR_SETTINGS`) for ``spp`` samples.

    Parameters
    ----------
    path : path-like
        A ``.blend`` file.
    spp : int
        Samples per pixel (Cycles' ``samples``), at least 1.
    size : (int, int), optional
        Film ``(width, height)``; default the file's resolution times its percentage.
    camera : str, optional
        Name of a camera object of the scene; default the scene's active camera.
    threads : int, optional
        Cycles' render threads; default Blender's (every core).
    """
    if isinstance(spp, bool) or not isinstance(spp, (int, np.integer)) or spp < 1:
        raise InputError("--spp", "spp", f"{spp!r}: expected a whole number of samples per pixel, at least 1")
    if threads is not None and (isinstance(threads, bool) or int(threads) < 1):
        raise InputError("--threads", "threads", f"{threads!r}: expected at least 1")
    p = _check_blend(path)
    return _Scene(_bpy(), p, spp=int(spp), size=size, camera=camera, threads=threads)


def render_reference(path, *, spp: int, size=None, camera: str | None = None, threads: int | None = None):
    """Cycles' own ``spp``-sample render of ``path`` (the bridge's settings): float32 (H, W, 3), row 0
    the top of the image, and the settings it was rendered with."""
    sc = open_blend(path, spp=spp, size=size, camera=camera, threads=threads)
    with tempfile.TemporaryDirectory(prefix="mcrecon_cycles_") as tmp:
        ch = sc.render(Path(tmp) / "reference.exr", offset=None, features=False)
    return _pass(ch, sc.layer.name, "Combined", "RGB", path), sc.settings()


def _pixel_centres(width: int, height: int) -> np.ndarray:
    ys, xs = np.mgrid[0:height, 0:width]
    return np.stack([xs.ravel() + 0.5, ys.ravel() + 0.5], axis=1)


def _probe_positions(channels: dict, layer: str, width: int, height: int, where) -> np.ndarray:
    """Film positions (N, 2) from a probe render: window coordinates (origin at the bottom left) to
    mcrecon's (x the column, y the row from the top), each kept inside its own pixel."""
    win = _pass(channels, layer, "Combined", "RG", where).astype(np.float64)
    x = win[..., 0] * width
    y = (1.0 - win[..., 1]) * height
    cx, cy = np.meshgrid(np.arange(width), np.arange(height))
    # a sample on a pixel's edge rounds to either side; beyond a hundredth of a pixel the probe is wrong
    off = max(np.max(np.abs(x - cx - 0.5)), np.max(np.abs(y - cy - 0.5)))
    if not off <= 0.51:
        raise RendererError("blender", "film positions", f"the probe of {where} put a sample {off - 0.5:.3g} "
                            "pixels outside its pixel: this camera's film positions cannot be measured "
                            "(a panoramic camera?)")
    pos = np.stack([x.ravel(), y.ravel()], axis=1)
    lo = np.stack([cx.ravel(), cy.ravel()], axis=1).astype(np.float64)
    hi = np.nextafter((lo + 1).astype(np.float32), np.float32(0)).astype(np.float64)
    return np.clip(pos, lo, hi).astype(np.float32)


def dump_cycles_log(path, scene, *, spp: int, size=None, camera: str | None = None, features="all",
                    threads: int | None = None, overwrite: bool = False):
    """Render a ``.blend`` scene sample by sample into an mcrecon sample log.

    Sample k of every pixel is Cycles' sample k of that pixel's ``spp``-sample
    pattern (a render with a sample subset of length one), so the log keeps
    Cycles' stratification; one round per sample index.  Film positions come
    from probe renders (see the module's notes).  The log is written under a
    temporary name and renamed when complete.

    Parameters
    ----------
    path : path-like
        The ``.h5`` log to write.
    scene : path-like
        The ``.blend`` file.
    spp : int
        Samples per pixel.
    size, camera, threads
        As :func:`open_blend`.
    features : "all", "none", str or sequence of str
        Which of :data:`BLENDER_FEATURES` to store as ``/features/NAME``.
    overwrite : bool
        Replace an existing log at ``path``.

    Returns
    -------
    pathlib.Path
    """
    from ..io import append_log, write_log
    from ..io._atomic import atomic_path
    from ..io.writer import check_log_fits

    names = check_blender_features(features)
    path = Path(path)
    if path.exists() and not overwrite:
        raise InputError(str(path), "-o/--output", "exists: give another path, or --overwrite to replace it")
    sc = open_blend(scene, spp=spp, size=size, camera=camera, threads=threads)
    w, h, layer = sc.width, sc.height, sc.layer.name
    check_log_fits(path, spp * w * h, 3 + sum(BLENDER_FEATURES[f] for f in names), where="blender log", spp=spp,
                   film="--size")
    metadata = {"renderer": "blender-cycles", **sc.settings(), "spp": int(spp),
                "sampling": "Cycles' own per-pixel pattern, sample k of each pixel = Cycles' sample k",
                "positions": "x = column, y = row from the top; measured by probe renders of the same samples",
                "colour": "Combined pass, linear scene-referred", "features": ",".join(names) or "none"}
    if names:
        metadata["features_definition"] = ("Cycles' Denoising Albedo (an emitter's radiance where a specular "
                                           "path ends on a light), Denoising Normal, Denoising Depth "
                                           "(0 on the background), as Cycles writes them")
    n_pix = w * h
    with tempfile.TemporaryDirectory(prefix="mcrecon_cycles_") as tmp:
        tmp = Path(tmp)
        values, feats = [], []
        for k in range(spp):
            ch = sc.render(tmp / f"s{k:06d}.exr", offset=k, features=bool(names))
            values.append(tmp / f"v{k:06d}.npy")
            np.save(values[-1], _pass(ch, layer, "Combined", "RGB", scene).reshape(n_pix, 3))
            fk = {f: _pass(ch, layer, *_FEATURE_PASSES[f], scene).reshape(n_pix, -1) for f in names}
            fk = {f: (v[:, 0] if v.shape[1] == 1 else v) for f, v in fk.items()}
            feats.append(tmp / f"f{k:06d}.npz")
            np.savez(feats[-1], **fk)
            (tmp / f"s{k:06d}.exr").unlink()
        sc.probe()
        with atomic_path(path) as out:
            for k in range(spp):
                ch = sc.render(tmp / f"p{k:06d}.exr", offset=k, features=False)
                pos = _probe_positions(ch, layer, w, h, scene)
                val = np.load(values[k])
                with np.load(feats[k]) as z:
                    fk = {f: z[f] for f in names} or None
                if k == 0:
                    write_log(out, pos, val, width=w, height=h, channels=("R", "G", "B"),
                              rounds=np.zeros(n_pix, np.int32), metadata=metadata, features=fk,
                              sampler="sobol")  # round k: every pixel's sample k of its own pattern
                else:
                    append_log(out, pos, val, round_index=k, features=fk)
    return path


#: Cycles' ``samples`` of an adaptive run: the length of every pixel's pattern, fixed for the whole run
#: (sample k of a pattern depends on it) and the highest sample index + 1 any pixel can reach.  A prefix
#: of a long pattern is as stratified as a short pattern (measured in ``docs/blender.md``), and a render
#: costs the same whatever it is.
PATTERN_SPP = 65536

#: The most memory the film positions of probe renders kept for later rounds take.
PROBE_CACHE_BYTES = 256 << 20


class BlenderRenderer:
    """A ``.blend`` scene as an in-process renderer of adaptive runs (``mcrecon adapt --blender``).

    A request's pixel p gets Cycles' samples ``first_index[p] .. first_index[p] + counts[p] - 1`` of
    its own pattern, so the rounds of a run continue each pixel's stratified sequence.  Per sample
    index k, one render with a sample subset of length one covers the bounding box of the pixels
    that still lack sample k (Cycles' render border); what it renders beyond the request for pixels
    of the box that reach index k only in a later round is kept for them, and the rest is waste:
    :attr:`samples_rendered` against :attr:`samples_delivered`.  Film positions come from probe
    renders of a second scene of the file (:meth:`_Scene.probe_scene`), one per sample index, kept
    up to :data:`PROBE_CACHE_BYTES`.

    Cycles cannot evaluate film positions of the caller's choosing: a request with ``positions``
    (gem, awr, auto's adaptive rounds) is refused with a :class:`~mcrecon.errors.RendererError`.

    Parameters
    ----------
    scene : path-like
        The ``.blend`` file.
    width, height : int, optional
        Film size, both or neither; default the file's.
    camera : str, optional
        A camera object of the scene; default its active camera.
    features : "all", "none", str or sequence of str
        Which of :data:`BLENDER_FEATURES` each reply carries (default all).
    threads : int, optional
        Cycles' render threads; default every core.
    pattern_spp : int
        Cycles' ``samples`` (:data:`PATTERN_SPP`), recorded in the spec.
    """

    channels = ("R", "G", "B")
    #: What a pixel's samples are (docs/renderer-protocol.md): Cycles' own per-pixel pattern continued from
    #: ``first_index``, stratified over aligned blocks of 2^k samples, so adaptive rounds go in whole nets.
    sampler = "sobol"

    def __init__(self, scene, *, width: int | None = None, height: int | None = None, camera: str | None = None,
                 features="all", threads: int | None = None, pattern_spp: int = PATTERN_SPP):
        names = check_blender_features(features, where="BlenderRenderer")
        if (width is None) != (height is None):
            raise InputError("BlenderRenderer", "width/height", "give both or neither")
        self._sc = open_blend(scene, spp=pattern_spp, size=None if width is None else (width, height),
                              camera=camera, threads=threads)
        self.width, self.height = self._sc.width, self._sc.height
        self.scene_path = os.path.abspath(scene)
        self.camera, self.threads, self.pattern_spp = self._sc.scene.camera.name, threads, int(pattern_spp)
        self.feature_names = names
        self.features = bool(names)
        self.name = f"blender:{Path(scene).name}"
        self._probe = self._sc.probe_scene()
        self._tmp = tempfile.TemporaryDirectory(prefix="mcrecon_cycles_")
        self._cache: dict[int, dict] = {}   # sample index -> pixels waiting for it, their values and features
        self._positions: dict[int, np.ndarray] = {}  # sample index -> (P, 2) film positions
        self.last_render_seconds = 0.0
        self.renders = 0
        self.samples_rendered = 0
        self.samples_delivered = 0

    def spec(self) -> dict:
        """The renderer spec that builds this renderer again (``resume`` re-opens the same file)."""
        from .spec_format import blender_spec

        return blender_spec(self.scene_path, width=self.width, height=self.height, camera=self.camera,
                            features=",".join(self.feature_names) or "none", threads=self.threads,
                            pattern_spp=self.pattern_spp)

    def _render_box(self, k: int, pixels: np.ndarray, *, probe: bool):
        """Render sample ``k`` (or its probe) over the bounding box of ``pixels`` (flat indices): the box's
        flat pixel indices and the full-film channels."""
        w, h = self.width, self.height
        rows, cols = pixels // w, pixels % w
        y0, y1, x0, x1 = int(rows.min()), int(rows.max()) + 1, int(cols.min()), int(cols.max()) + 1
        region = None if (x0, y0, x1, y1) == (0, 0, w, h) else (x0, x1, y0, y1)
        out = Path(self._tmp.name) / ("probe.exr" if probe else "colour.exr")
        ch = self._sc.render(out, offset=k, features=self.features and not probe, region=region,
                             scene=self._probe if probe else None)
        self.renders += 1
        box = (np.arange(y0, y1)[:, None] * w + np.arange(x0, x1)[None, :]).ravel()
        return box, ch

    def _colour(self, k: int, need: np.ndarray, end: np.ndarray) -> dict:
        """Sample ``k`` of the pixels ``need`` (ascending flat indices): values and features, from the
        samples kept from earlier renders, the rest rendered; what the render gives beyond ``need`` to
        pixels that reach index k only later (``end <= k``) is kept for them."""
        names, layer = ("values",) + self.feature_names, self._sc.layer.name
        got = {f: np.empty((len(need), 3 if f == "values" else BLENDER_FEATURES[f]), np.float32) for f in names}
        kept = self._cache.pop(k, None)
        hit = np.zeros(len(need), bool)
        if kept is not None:
            at = np.clip(np.searchsorted(kept["pixels"], need), 0, len(kept["pixels"]) - 1)
            hit = kept["pixels"][at] == need
            for f in names:
                got[f][hit] = kept[f][at[hit]]
            later = end[kept["pixels"]] <= k  # kept pixels that still wait for index k
            kept = {f: v[later] for f, v in kept.items()}
        if not hit.all():
            box, ch = self._render_box(k, need[~hit], probe=False)
            self.samples_rendered += len(box)
            full = {"values": _pass(ch, layer, "Combined", "RGB", self.scene_path).reshape(-1, 3)}
            for f in self.feature_names:
                full[f] = _pass(ch, layer, *_FEATURE_PASSES[f], self.scene_path).reshape(len(full["values"]), -1)
            for f in names:
                got[f][~hit] = full[f][need[~hit]]
            extra = box[end[box] <= k]
            if kept is not None:
                extra = np.setdiff1d(extra, kept["pixels"])
            if len(extra):
                new = {"pixels": extra, **{f: full[f][extra] for f in names}}
                if kept is not None:
                    order = np.argsort(np.concatenate([kept["pixels"], extra]))
                    new = {f: np.concatenate([kept[f], new[f]])[order] for f in new}
                kept = new
        if kept is not None and len(kept["pixels"]):
            self._cache[k] = kept
        return got

    def _film_positions(self, k: int, need: np.ndarray) -> np.ndarray:
        """Film positions (len(need), 2) of sample ``k`` of the pixels ``need``: a full-film probe render,
        kept while the kept probes stay under :data:`PROBE_CACHE_BYTES` (the lowest indices go first:
        ``first_index`` only grows)."""
        pos = self._positions.get(k)
        if pos is None:
            p = self.width * self.height
            _, ch = self._render_box(k, np.array([0, p - 1]), probe=True)
            pos = _probe_positions(ch, self._sc.layer.name, self.width, self.height, self.scene_path).reshape(p, 2)
            while self._positions and (len(self._positions) + 1) * pos.nbytes > PROBE_CACHE_BYTES:
                del self._positions[min(self._positions)]
            self._positions[k] = pos
        return pos[need]

    def render(self, request):
        """Cycles' samples for a request's counts (see the class notes); a reply in row-major pixel
        order, each pixel's samples in index order."""
        import time

        from ..core.requests import SampleBatch, SampleRequest

        if not isinstance(request, SampleRequest):
            raise InputError(self.name, "request", f"got {type(request).__name__}, expected a SampleRequest")
        if (request.width, request.height) != (self.width, self.height):
            raise InputError(self.name, "request width/height", f"{request.width}x{request.height}, expected "
                             f"{self.width}x{self.height}")
        if request.positions is not None and len(request.positions):
            raise RendererError(self.name, "positions", "Cycles renders each pixel's own sample sequence and cannot "
                                "evaluate film positions chosen by the method: use a method that asks for "
                                "samples per pixel (box, ci, splat, nfor, auto --sampling uniform)")
        t0 = time.perf_counter()
        p = self.width * self.height
        n = (np.zeros(p, np.int64) if request.counts is None
             else np.ascontiguousarray(request.counts, np.int64).ravel())
        first = (np.zeros(p, np.int64) if request.first_index is None
                 else np.ascontiguousarray(request.first_index, np.int64).ravel())
        end = first + n
        busy = n > 0
        if busy.any() and int(end.max()) > self.pattern_spp:
            raise RendererError(self.name, "first_index", f"a pixel needs sample {int(end.max()) - 1}, past the "
                                f"{self.pattern_spp} of the run's Cycles pattern (pattern_spp)")
        ks = range(int(first[busy].min()), int(end.max())) if busy.any() else range(0)
        # the reply: pixel by pixel in row order, each pixel's samples in index order; for one index k
        # its rows are those of the pixels that need k, in pixel order
        total = int(n.sum())
        pix = np.repeat(np.arange(p), n)
        kk = first[pix] + np.arange(total) - np.repeat(np.cumsum(n) - n, n)
        order = np.argsort(kk, kind="stable")
        bounds = np.searchsorted(kk[order], np.arange(ks.start, ks.stop + 1))
        pos = np.empty((total, 2), np.float32)
        val = np.empty((total, 3), np.float32)
        feats = {f: np.empty((total, BLENDER_FEATURES[f]), np.float32) for f in self.feature_names}
        colour = {}
        for i, k in enumerate(ks):  # the colour renders first, then the probes: one switch of scene each
            rows = order[bounds[i]:bounds[i + 1]]
            if len(rows):
                colour[k] = (rows, self._colour(k, pix[rows], end))
        for k, (rows, got) in colour.items():
            pos[rows] = self._film_positions(k, pix[rows])
            val[rows] = got["values"]
            for f in self.feature_names:
                feats[f][rows] = got[f]
        self.samples_delivered += total
        self.last_render_seconds = time.perf_counter() - t0
        out = {f: (v[:, 0] if v.shape[1] == 1 else v) for f, v in feats.items()}
        return SampleBatch(pos, val, out)
