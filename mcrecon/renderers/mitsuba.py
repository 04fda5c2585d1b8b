"""Mitsuba 3 bridge: answer mcrecon sample requests with a real path tracer.

:class:`MitsubaRenderer` implements the :class:`~mcrecon.renderers.protocol.Renderer`
protocol on top of Mitsuba 3's vectorised ``llvm_ad_rgb`` variant.  Every
sample is one path traced through one chosen film position, so the
adaptive methods can place samples anywhere on the film, and the log holds
the renderer's true per-sample radiance (no pixel filter, no clamping).

How one sample is computed (the recipe measured in ``shared/NOTES.md``)::

    s = independent_sampler.clone(); s.seed(dr.opaque(mi.UInt32, seed), N)
    ray, w = sensor.sample_ray_differential(time, 0, Point2f(x / W, y / H), aperture)
    L, _, _ = integrator.sample(scene, s, ray, None, True)
    dr.eval(L * w)  # once per batch

Per-sample features (on by default, ``features="none"`` to switch off): the
primary ray of every sample is intersected once more and the hit's
``albedo`` (3), shading ``normal`` (3, world space) and ``depth`` (1, the
hit's camera-space z) are evaluated in the same ``dr.eval`` as
the radiance (see :data:`MITSUBA_FEATURES` and ``docs/mitsuba.md``)::

    si = scene.ray_intersect(Ray3f(ray)); bsdf = si.bsdf(ray)
    albedo = bsdf.eval_diffuse_reflectance(si)  (1 where the BSDF has no diffuse lobe)
    normal = si.sh_frame.n; depth = dot(si.p - camera, axis)   (each 0 where the ray hits nothing)

Film coordinates are mcrecon's: ``x`` the column, ``y`` the row counted
from the *top*; Mitsuba's normalised film position ``(x / W, y / H)`` uses
the same orientation as the rows of ``mi.render``'s output (checked by
``tests/test_mitsuba.py`` against ``mi.render`` on an asymmetric scene).

Mitsuba is optional (``pip install "mcrecon[mitsuba]"`` or
``bash data_tools/install_mitsuba.sh``); this module imports it lazily.
Loading the LLVM backend can *abort the process* (libLLVM 15/16), so
:func:`mitsuba_available` probes in a subprocess and
:class:`MitsubaRenderer` runs that probe before its first import.

References
----------
.. [1] W. Jakob, S. Speierer, N. Roussel, M. Nimier-David, D. Vicini,
   T. Zeltner, B. Nicolet, M. Crespo, V. Leroy, Z. Zhang, "Mitsuba 3
   renderer", 2022, https://mitsuba-renderer.org.
.. [2] W. Jakob, S. Speierer, N. Roussel, D. Vicini, "Dr.Jit: A
   Just-In-Time Compiler for Differentiable Rendering", ACM Trans. Graph.
   41(4), 2022.
"""

from __future__ import annotations

import importlib.util
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Mapping

import numba
import numpy as np

from ..errors import InputError, RendererError
from ..core.requests import SampleBatch, SampleRequest, place_in_pixels
# the feature names are part of the spec format (a spec records them): defined there, part of this interface
from .spec_format import MITSUBA_FEATURES, check_mitsuba_features, mitsuba_spec
from . import mitsuba_logs as _logs
from .mitsuba_logs import _check_int, _to_float32_positions, dump_uniform_log, render_reference  # noqa: F401

__all__ = ["MitsubaRenderer", "mitsuba_available", "render_reference", "dump_uniform_log",
           "SUPPORTED_VARIANTS", "MITSUBA_FEATURES", "drjit_cache_dir"]

#: Variants whose ``integrator.sample`` is vectorised and returns RGB
#: (a ``Color3f``).  ``scalar_rgb`` would need one Python call per sample
#: (~0.1 M samples/s); spectral/mono variants return other quantities.
SUPPORTED_VARIANTS = ("llvm_ad_rgb", "cuda_ad_rgb")

#: Seconds the availability probe may take (import + one kernel compile,
#: normally 1-3 s; generous because CI machines are shared).
PROBE_TIMEOUT = 180.0

_WHERE = "MitsubaRenderer"
_INSTALL_HINT = ("install it with `bash data_tools/install_mitsuba.sh` (Debian: apt-get install libllvm19; "
                 "pip install mitsuba)")
_PROBE_CACHE: dict[str, tuple[bool, str]] = {}
_PROBE_MARK = "MCRECON_MITSUBA_PROBE_OK"


# ---------------------------------------------------------------- import

def drjit_cache_dir() -> str:
    """The directory Dr.Jit caches compiled kernels in, creating it.

    ``DRJIT_CACHE_DIR`` when already set; otherwise
    ``$XDG_CACHE_HOME/mcrecon/drjit`` (``~/.cache/...``), or a per-user
    directory under the system temp dir when the home is not writable.
    Dr.Jit's default (``~/.drjit``) lies outside any run or cache tree.
    """
    env = os.environ.get("DRJIT_CACHE_DIR")
    if env:
        return env
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    candidates = [os.path.join(base, "mcrecon", "drjit"),
                  os.path.join(tempfile.gettempdir(), f"mcrecon-drjit-{os.getuid() if hasattr(os, 'getuid') else 0}")]
    for cand in candidates:
        try:
            os.makedirs(cand, exist_ok=True)
            if os.access(cand, os.W_OK):
                return cand
        except OSError:
            continue
    return candidates[-1]


def _import_mitsuba(variant: str):
    """Import mitsuba + drjit with the kernel cache set, select ``variant``."""
    # Dr.Jit reads DRJIT_CACHE_DIR when its JIT initialises: set it first.
    os.environ["DRJIT_CACHE_DIR"] = drjit_cache_dir()
    try:
        import drjit as dr
        import mitsuba as mi
    except ImportError as exc:
        raise RendererError(_WHERE, "mitsuba", f"cannot import mitsuba ({exc}); {_INSTALL_HINT}") from None
    if variant not in mi.variants():
        raise InputError(_WHERE, "variant", f"{variant!r} is not built into this mitsuba "
                         f"{mi.__version__}; available: {', '.join(mi.variants())}")
    mi.set_variant(variant)
    return mi, dr


# ------------------------------------------------------- availability probe

def _llvm_version(dr) -> str:
    try:
        return ".".join(str(v) for v in dr.detail.llvm_version())
    except Exception:  # not an LLVM variant, or an older Dr.Jit
        return "?"


def _probe_main(variant: str) -> None:  # runs in the probe subprocess
    t0 = time.perf_counter()
    _mi, dr = _import_mitsuba(variant)
    # Printed before rendering: with libLLVM 15/16 the render aborts the
    # process, and the parent still learns which LLVM was loaded.
    print(f"MCRECON_MITSUBA_LLVM {_llvm_version(dr)}", flush=True)
    r = MitsubaRenderer(None, width=4, height=4, variant=variant, probe=False)
    req = SampleRequest(4, 4, counts=np.full((4, 4), 2, np.int64), seed=1)
    batch = r.render(req)
    v = np.asarray(batch.values)
    if v.shape != (32, 3) or not np.isfinite(v).all() or not (v > 0).any():
        print(f"probe rendered bad values: shape {v.shape}, finite {np.isfinite(v).all()}", flush=True)
        sys.exit(3)
    print(f"{_PROBE_MARK} {_mi.__version__} {time.perf_counter() - t0:.2f}", flush=True)


def mitsuba_available(variant: str = "llvm_ad_rgb", *, timeout: float = PROBE_TIMEOUT,
                      refresh: bool = False) -> tuple[bool, str]:
    """Whether the Mitsuba bridge can render here, without risking this process.

    Mitsuba's LLVM backend aborts the whole process (SIGABRT) on the first
    render when it finds libLLVM 15 or 16, so the check imports Mitsuba and
    renders a 4x4 Cornell box through :class:`MitsubaRenderer` in a
    *subprocess* with a time-out.  The answer is cached per variant for the
    life of this process.

    Parameters
    ----------
    variant : str
        Mitsuba variant to check (``"llvm_ad_rgb"``).
    timeout : float
        Seconds the probe may take.
    refresh : bool
        Probe again even if an answer is cached.

    Returns
    -------
    (bool, str)
        Whether it works, and why (the Mitsuba version, or the failure with
        the last lines of the probe's error output and how to fix it).
    """
    if not refresh and variant in _PROBE_CACHE:
        return _PROBE_CACHE[variant]
    if importlib.util.find_spec("mitsuba") is None or importlib.util.find_spec("drjit") is None:
        ans = (False, f"the Python package mitsuba is not installed; {_INSTALL_HINT}")
        _PROBE_CACHE[variant] = ans
        return ans
    root = str(Path(__file__).resolve().parents[2])
    code = (f"import sys; sys.path.insert(0, {root!r}); "
            f"from mcrecon.renderers.mitsuba import _probe_main; _probe_main({variant!r})")
    env = dict(os.environ)
    env["DRJIT_CACHE_DIR"] = drjit_cache_dir()
    try:
        proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                              timeout=timeout, env=env, stdin=subprocess.DEVNULL)
    except subprocess.TimeoutExpired:
        ans = (False, f"the Mitsuba probe ({variant}) did not finish within {timeout:g} s")
        _PROBE_CACHE[variant] = ans
        return ans
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith(_PROBE_MARK)]
    llvm = [ln.split()[-1] for ln in proc.stdout.splitlines() if ln.startswith("MCRECON_MITSUBA_LLVM ")]
    llvm_s = f", libLLVM {llvm[-1]}" if llvm and llvm[-1] != "?" else ""
    if proc.returncode == 0 and lines:
        _, version, secs = lines[-1].split()
        ans = (True, f"mitsuba {version}, variant {variant}{llvm_s} (probe rendered in {secs} s)")
    else:
        # The last line holds the exception (or LLVM's last words before an abort).
        out = (proc.stderr.strip() or proc.stdout.strip()).splitlines()
        tail = out[-1].strip()[:400] if out else ""
        if proc.returncode < 0:
            try:
                sig = signal.Signals(-proc.returncode).name
            except ValueError:
                sig = str(-proc.returncode)
            what = f"the Mitsuba probe ({variant}{llvm_s}) was killed by {sig}"
            if sig == "SIGABRT":
                what += " (typical of libLLVM 15/16: Dr.Jit needs libllvm19)"
        else:
            what = f"the Mitsuba probe ({variant}{llvm_s}) exited with status {proc.returncode}"
        ans = (False, f"{what}: {tail or '(no output)'}; {_INSTALL_HINT}")
    _PROBE_CACHE[variant] = ans
    return ans


# ------------------------------------------------------------- the renderer

def _resize_scene_dict(d: Mapping, width: int | None, height: int | None) -> dict:
    """Copy of a Mitsuba scene dict with every sensor's film resized."""
    def copy_dicts(x):
        # Nested dicts are copied; leaves (Mitsuba transforms, which cannot
        # be deep-copied, arrays, numbers) are shared.
        return {k: copy_dicts(v) for k, v in x.items()} if isinstance(x, Mapping) else x

    d = copy_dicts(d)
    for value in d.values():
        if isinstance(value, dict) and isinstance(value.get("film"), dict):
            if width is not None:
                value["film"]["width"] = int(width)
            if height is not None:
                value["film"]["height"] = int(height)
    return d


class MitsubaRenderer:
    """A Mitsuba 3 scene as an mcrecon renderer (one path sample per film position).

    Parameters
    ----------
    scene : None, str, path-like or dict
        ``None``: Mitsuba's built-in Cornell box (``mi.cornell_box()``,
        path tracer with 8 bounces), its film resized to ``width`` x
        ``height`` (default 128 x 128).  A path: a Mitsuba scene XML file,
        loaded with ``params`` (use them to set the film size when the file
        declares parameters such as ``resx``/``resy``).  A dict: a Mitsuba
        scene dict (``mi.load_dict``); every sensor film in it is resized
        to ``width``/``height`` when given.
    width, height : int, optional
        Film size in pixels.  For a scene file they must equal the file's
        film (crop) size; omitted, the file's size is used.
    variant : str
        A vectorised RGB Mitsuba variant, one of :data:`SUPPORTED_VARIANTS`.
    spp_per_pass : int
        Memory bound: one kernel launch evaluates at most
        ``spp_per_pass * width * height`` samples; larger requests are split
        into passes.  The default 16 keeps a 512 x 512 pass at 4 M samples.
    max_depth : int, optional
        Path length of the tracer.  ``None`` keeps the scene's integrator;
        otherwise a ``path`` integrator with this ``max_depth`` (-1 =
        unbounded) replaces it.
    params : mapping, optional
        Scene parameters passed to ``mi.load_file`` (scene files only).
    probe : bool
        Run :func:`mitsuba_available` (a subprocess, cached per process)
        before importing Mitsuba here, so a broken LLVM raises a clear
        :class:`~mcrecon.errors.RendererError` instead of aborting this
        process.
    features : "all", "none" or sequence of str
        Per-sample features of the primary hit sent with every sample
        (``SampleBatch.features``): ``albedo`` (N, 3), ``normal`` (N, 3)
        and ``depth`` (N,), all float32; default all three.  See the notes.

    Attributes
    ----------
    width, height : int
    channels : tuple of str
        ``("R", "G", "B")``: linear radiance in the variant's RGB space.
    name : str
    last_render_seconds : float
        Time the last :meth:`render` spent inside Mitsuba/Dr.Jit (tracing,
        kernel compilation, launches, copying results out).  The adaptive
        driver counts it as renderer time and the rest of the call (our
        jittered positions and their float32 film coordinates, unless
        :meth:`prepare` computed them ahead) as toolkit time.
    last_call_seconds : float
        Wall time of the whole last :meth:`render` call.
    total_render_seconds : float
        Sum of ``last_render_seconds`` over all calls.
    n_rendered : int
        Samples rendered so far.

    Notes
    -----
    * The random numbers of a request are fixed by ``request.seed``,
      ``request.round_index`` and ``spp_per_pass``: the jittered positions
      come from ``numpy.random.default_rng([seed, round_index])``, each
      pass gets its own 32-bit Mitsuba seed from
      ``numpy.random.SeedSequence([seed, round_index, pass])``.  The seed
      is handed to Dr.Jit as an opaque variable, so a new seed or a new
      batch size reuses the compiled kernel.
    * Paths use an ``independent`` sampler whatever the scene's sampler:
      stratified/low-discrepancy samplers assume every pixel gets the same
      sample count in one wavefront, which adaptive requests break.  The
      bridge declares it (``sampler = "independent"``,
      docs/renderer-protocol.md): it does not continue a pixel's sequence
      from ``first_index``.
    * Ray differentials are switched off, so a sample is the radiance
      through its point (the limit ``mi.render`` converges to as spp grows,
      where it scales differentials by 1/sqrt(spp)); with differentials a
      sample's texture filtering would depend on a nominal pixel footprint.
    * The reply lists the samples for ``request.counts`` first (sorted by
      pixel, row-major), then one sample per ``request.positions`` row, in
      request order, with the requested positions returned exactly.
    * Features are those of the primary ray's first hit (the same ray the
      path starts with, so they share its depth of field and motion blur):
      ``albedo`` is ``BSDF.eval_diffuse_reflectance`` where the hit's BSDF
      has a diffuse lobe (diffuse, plastic, principled, blends: its diffuse
      reflectance, textures included), and 1 where it has none (dielectric,
      thin dielectric, conductors): Mitsuba returns 0 there for smooth
      BSDFs and the BSDF's value at normal incidence times pi for rough
      ones (25 for a rough conductor with alpha 0.1), neither an albedo;
      1 is what Open Image Denoise asks for on specular surfaces of
      unknown reflectivity.  ``normal`` is the world-space shading normal
      ``si.sh_frame.n``; ``depth`` the hit's camera-space z (its distance
      from the camera along the viewing axis, as pbrt-v4's ``P.Z``; the
      camera's transform at construction), not ``si.t``, which Mitsuba
      measures from the near-clip plane.  A ray that hits nothing gets 0
      in every feature.

    References
    ----------
    .. [1] W. Jakob et al., "Mitsuba 3 renderer", 2022,
       https://mitsuba-renderer.org.
    """

    #: What a pixel's samples are (docs/renderer-protocol.md): Mitsuba's independent sampler (class notes).
    sampler = "independent"

    #: Every reply's arrays are new (never a buffer the renderer fills again): the driver keeps them
    #: for the log while the next round renders, without a copy (renderers without it are copied).
    fresh_replies = True

    channels = ("R", "G", "B")

    def __init__(self, scene=None, *, width: int | None = None, height: int | None = None,
                 variant: str = "llvm_ad_rgb", spp_per_pass: int = 16, max_depth: int | None = None,
                 params: Mapping | None = None, probe: bool = True, features="all"):
        # --- validate every option before touching Mitsuba
        self.features = check_mitsuba_features(features)
        width = _check_int("width", width, minimum=1, allow_none=True)
        height = _check_int("height", height, minimum=1, allow_none=True)
        if not isinstance(variant, str) or variant not in SUPPORTED_VARIANTS:
            raise InputError(_WHERE, "variant", f"got {variant!r}, expected one of {', '.join(SUPPORTED_VARIANTS)} "
                             "(vectorised RGB variants)")
        self.spp_per_pass = _check_int("spp_per_pass", spp_per_pass, minimum=1)
        self.max_depth = _check_int("max_depth", max_depth, minimum=1, allow_none=True, extra=(-1,))
        if params is not None and not isinstance(params, Mapping):
            raise InputError(_WHERE, "params", f"got {type(params).__name__}, expected a mapping of scene parameters")
        if scene is None:
            kind = "cornell"
            width = 128 if width is None else width
            height = 128 if height is None else height
        elif isinstance(scene, Mapping):
            kind = "dict"
        elif isinstance(scene, (str, os.PathLike)):
            kind = "file"
            scene = Path(scene)
            if not scene.is_file():
                raise InputError(str(scene), "scene", f"{'is a directory' if scene.is_dir() else 'no such file'}; "
                                 "expected a Mitsuba scene XML file, a scene dict, or None for the built-in "
                                 "Cornell box")
        else:
            raise InputError(_WHERE, "scene", f"got {type(scene).__name__}, expected None (Cornell box), "
                             "a path to a Mitsuba scene XML file, or a Mitsuba scene dict")
        if params and kind != "file":
            raise InputError(_WHERE, "params", "only used with a scene file")
        # what spec() can say: the Cornell box or a scene file, without params, at the default variant,
        # depth and passes
        self._spec_scene = (None if kind == "cornell" else str(scene.resolve()) if kind == "file" and not params
                            else False)
        self._spec_defaults = (variant == "llvm_ad_rgb" and max_depth is None and spp_per_pass == 16)
        self.variant = variant
        if probe:
            ok, reason = mitsuba_available(variant)
            if not ok:
                raise RendererError(_WHERE, "mitsuba", reason)
        mi, dr = _import_mitsuba(variant)
        self._mi, self._dr = mi, dr

        # --- load the scene
        try:
            if kind == "cornell":
                self._scene = mi.load_dict(_resize_scene_dict(mi.cornell_box(), width, height))
                self.scene_name = "cornell_box"
            elif kind == "dict":
                self._scene = mi.load_dict(_resize_scene_dict(scene, width, height))
                self.scene_name = str(scene.get("id", "scene_dict")) if hasattr(scene, "get") else "scene_dict"
            else:
                self._scene = mi.load_file(str(scene), **dict(params or {}))
                self.scene_name = str(scene)
        except Exception as exc:
            where = str(scene) if kind == "file" else _WHERE
            raise InputError(where, "scene", f"Mitsuba could not load it: {type(exc).__name__}: "
                             f"{str(exc).strip().splitlines()[-1] if str(exc).strip() else ''}") from None
        sensors = self._scene.sensors()
        if not sensors:
            raise InputError(self.scene_name, "sensor", "the scene has no sensor (camera)")
        self._sensor = sensors[0]
        film = self._sensor.film()
        fw, fh = (int(v) for v in film.crop_size())
        from ..io.logformat import MAX_PIXELS  # a film no log or image holds (Mitsuba loads a width of 0)
        if min(fw, fh) < 1 or fw * fh > MAX_PIXELS:
            raise InputError(self.scene_name, "film width/height", f"{fw}x{fh}: expected at least 1x1 and at "
                             f"most {MAX_PIXELS} pixels; set the film's width and height in the scene")
        if (width is not None and width != fw) or (height is not None and height != fh):
            raise InputError(self.scene_name, "width/height",
                             f"requested {width}x{height} but the scene's film is {fw}x{fh}; set the film size "
                             "in the scene (e.g. params={'resx': W, 'resy': H} if it declares them) or omit "
                             "width/height")
        self.width, self.height = fw, fh
        if self.max_depth is None:
            self._integrator = self._scene.integrator()
            if self._integrator is None:
                self._integrator = mi.load_dict({"type": "path"})
        else:
            self._integrator = mi.load_dict({"type": "path", "max_depth": self.max_depth})
        # See the class notes: an independent sampler for ragged wavefronts.
        self._sampler = mi.load_dict({"type": "independent"})
        self._shutter_open = float(self._sensor.shutter_open())
        self._shutter_time = float(self._sensor.shutter_open_time())
        self._needs_aperture = bool(self._sensor.needs_aperture_sample())
        # Camera-space depth: the camera's position and unit viewing axis (its +z) in world space.
        m = np.asarray(self._sensor.world_transform().matrix, np.float64).reshape(4, 4)
        axis = m[:3, 2] / np.linalg.norm(m[:3, 2])
        self._camera_origin, self._camera_axis = tuple(map(float, m[:3, 3])), tuple(map(float, axis))
        self.name = f"mitsuba:{Path(self.scene_name).name}"
        self.last_render_seconds = 0.0
        self.last_call_seconds = 0.0
        self.total_render_seconds = 0.0
        self.n_rendered = 0
        # film positions computed ahead by prepare(): id(request) -> (request, data)
        self._prepared: dict = {}
        self._prepared_lock = threading.Lock()

    def __repr__(self) -> str:
        return (f"MitsubaRenderer({self.scene_name!r}, {self.width}x{self.height}, variant={self.variant!r}, "
                f"spp_per_pass={self.spp_per_pass}, features={','.join(self.features) or 'none'!r})")

    @property
    def pass_size(self) -> int:
        """Samples per kernel launch."""
        return self.spp_per_pass * self.width * self.height

    # ------------------------------------------------------------ tracing
    def _trace(self, uv: np.ndarray, seed32: int, out: np.ndarray, feats: Mapping[str, np.ndarray]) -> None:
        """Radiance of one path through each film position into ``out`` (n, 3) float32.

        ``uv`` (2, n) float32: the normalised film positions (x / W, y / H).
        ``feats``: name -> (n, k) float32 views to fill with the primary
        hit's features (see the class notes), evaluated with the radiance.
        """
        mi, dr = self._mi, self._dr
        mi.set_variant(self.variant)  # process-global: another renderer may have switched it
        n = int(uv.shape[1])
        s = self._sampler.clone()
        # An opaque seed is a kernel parameter; a Python int would be baked
        # into the kernel as a literal and force a recompilation per call.
        s.seed(dr.opaque(mi.UInt32, seed32), n)
        p = mi.Point2f(mi.Float(uv[0]), mi.Float(uv[1]))
        # Same sampler dimensions as Mitsuba's own render loop, minus the
        # pixel jitter (we give the film positions).
        aperture = s.next_2d() if self._needs_aperture else mi.Point2f(0.5, 0.5)
        t = mi.Float(self._shutter_open)
        if self._shutter_time > 0:
            t = t + s.next_1d() * self._shutter_time
        ray, weight = self._sensor.sample_ray_differential(t, 0.0, p, aperture)
        ray.has_differentials = False
        L, _valid, _aux = self._integrator.sample(self._scene, s, ray, None, True)
        L = L * weight
        got = self._primary_features(ray, tuple(feats)) if feats else {}
        # One evaluation for the radiance and the features: one kernel launch.
        dr.eval(L, *got.values())
        # One channel at a time: converting the Color3f as a whole launches
        # an extra interleaving kernel whose size is compiled in.
        for c in range(3):
            out[:, c] = np.asarray(L[c], dtype=np.float32)
        for name, dst in feats.items():
            x = got[name]
            if dst.shape[1] == 1:
                dst[:, 0] = np.asarray(x, dtype=np.float32)
            else:
                for c in range(dst.shape[1]):
                    dst[:, c] = np.asarray(x[c], dtype=np.float32)

    def _primary_features(self, ray, names) -> dict:
        """Dr.Jit expressions (not evaluated) of the features of the primary ray's first hit."""
        mi, dr = self._mi, self._dr
        si = self._scene.ray_intersect(mi.Ray3f(ray))
        hit = si.is_valid()
        out = {}
        if "albedo" in names:
            bsdf = si.bsdf(ray)
            # eval_diffuse_reflectance is an albedo only for BSDFs with a diffuse lobe
            # (0 for smooth glass/metal, unbounded for rough ones): 1 elsewhere (class notes).
            diffuse = mi.has_flag(bsdf.flags(), mi.BSDFFlags.Diffuse)
            a = dr.select(diffuse, bsdf.eval_diffuse_reflectance(si, hit), mi.Color3f(1.0))
            out["albedo"] = dr.select(hit, a, mi.Color3f(0.0))
        if "normal" in names:
            out["normal"] = dr.select(hit, si.sh_frame.n, mi.Vector3f(0.0))
        if "depth" in names:
            # camera-space z of the hit (as pbrt's P.Z), not si.t: Mitsuba starts camera rays on the
            # near-clip plane, so si.t falls short of the distance by near_clip / cos(angle)
            z = dr.dot(si.p - mi.Point3f(*self._camera_origin), mi.Vector3f(*self._camera_axis))
            out["depth"] = dr.select(hit, z, mi.Float(0.0))
        return out

    def _film_positions(self, request: SampleRequest):
        """(positions (n, 2) float64, normalised film positions (2, n) float32) of a request.

        The jittered positions for ``counts`` (from ``default_rng([seed,
        round_index])``), then the requested ``positions``, written into one
        array (no concatenation), and their float32 ``(x / W, y / H)`` in
        the same pass over them (:func:`_normalised`).
        """
        seed, rnd = int(request.seed), int(request.round_index)
        nc, npos = request.n_from_counts, request.n_from_positions
        pos = np.empty((nc + npos, 2), np.float64)
        if nc:
            rng = np.random.default_rng([seed & 0xFFFFFFFFFFFFFFFF, rnd & 0xFFFFFFFFFFFFFFFF])
            # the numbers of jittered_positions(request.counts, rng), drawn into place
            rng.random(out=pos[:nc])
            place_in_pixels(pos[:nc], np.ascontiguousarray(request.counts, np.int64).ravel(), self.width)
        if npos:
            pos[nc:] = request.positions
        return pos, _normalised(pos, self.width, self.height)

    def prepare(self, request: SampleRequest) -> None:
        """Compute a request's film positions ahead of :meth:`render` (optional; any thread).

        A pipelined :func:`mcrecon.adapt` calls it from its toolkit thread
        right after planning a round, while this renderer still renders the
        round before: the jittered positions and their float32 conversion
        then overlap the rendering instead of delaying the next kernel
        launch.  Pure numpy/numba (no Mitsuba call); :meth:`render` of the
        same request object uses them and returns exactly what it returns
        without ``prepare`` (tested).
        """
        if not isinstance(request, SampleRequest) or (request.width, request.height) != (self.width, self.height):
            return  # render() reports it
        data = self._film_positions(request)
        with self._prepared_lock:
            self._prepared[id(request)] = (request, data)
            while len(self._prepared) > 2:  # a run that stopped before rendering a prepared round
                self._prepared.pop(next(iter(self._prepared)))

    def _take_prepared(self, request):
        with self._prepared_lock:
            got = self._prepared.pop(id(request), None)
        if got is not None and got[0] is request:
            return got[1]
        return None

    def spec(self) -> dict | None:
        """How to build this renderer again (:func:`mcrecon.renderers.spec_format.mitsuba_spec`), or None when a
        spec cannot say it (a scene dict, scene parameters, another variant, depth or pass size)."""
        if self._spec_scene is False or not self._spec_defaults:
            return None
        return mitsuba_spec(self._spec_scene, width=self.width, height=self.height,
                            features=",".join(self.features) or "none")

    def render(self, request: SampleRequest) -> SampleBatch:
        """Answer a request: jittered samples for ``counts``, then ``positions`` in order.

        Parameters
        ----------
        request : SampleRequest
            Its ``width``/``height`` must be this renderer's.

        Returns
        -------
        SampleBatch
            positions (N, 2) float64, values (N, 3) float32 and the
            features (float32: albedo and normal (N, 3), depth (N,)).
        """
        return self._render(request, self.features)

    def _render(self, request: SampleRequest, features: tuple[str, ...]) -> SampleBatch:
        """:meth:`render` with the features ``features`` (a subset of ``self.features``; the
        reference renders none)."""
        t_call = time.perf_counter()
        if not isinstance(request, SampleRequest):
            raise InputError(self.name, "request", f"got {type(request).__name__}, expected a SampleRequest")
        if (request.width, request.height) != (self.width, self.height):
            raise InputError(self.name, "request width/height",
                             f"{request.width}x{request.height}, this scene's film is {self.width}x{self.height}")
        seed, rnd = int(request.seed), int(request.round_index)
        prepared = self._take_prepared(request)
        pos, uv = prepared if prepared is not None else self._film_positions(request)
        n = pos.shape[0]
        values = np.empty((n, 3), np.float32)
        feats = {name: np.empty((n, MITSUBA_FEATURES[name]), np.float32) for name in features}
        render_s = 0.0
        step = self.pass_size
        n_pass = -(-n // step)
        if n_pass:
            seeds = np.random.SeedSequence([seed & 0xFFFFFFFFFFFFFFFF, rnd & 0xFFFFFFFFFFFFFFFF, 0x6D697473]) \
                .generate_state(n_pass, np.uint32)
        for k in range(n_pass):
            a, b = k * step, min(n, (k + 1) * step)
            t0 = time.perf_counter()
            try:
                self._trace(uv[:, a:b], int(seeds[k]), values[a:b], {f: v[a:b] for f, v in feats.items()})
            except Exception as exc:
                raise RendererError(self.name, "render", f"Mitsuba failed on pass {k} of round {rnd}: "
                                    f"{type(exc).__name__}: {exc}") from exc
            render_s += time.perf_counter() - t0
        self.last_render_seconds = render_s
        self.total_render_seconds += render_s
        self.n_rendered += n
        self.last_call_seconds = time.perf_counter() - t_call
        # depth as (N,): one component, stored as /features/depth of shape (N,)
        return SampleBatch(pos, values, {f: (v[:, 0] if v.shape[1] == 1 else v) for f, v in feats.items()})


@numba.njit(cache=True, nogil=True)
def _normalised(pos, width, height):
    """(2, n) float32 ``(x / W, y / H)``: float64 division, then rounding to float32 (as numpy's
    ``(pos[:, 0] / W).astype(np.float32)``), each row contiguous for Dr.Jit."""
    n = pos.shape[0]
    out = np.empty((2, n), np.float32)
    fw = float(width)
    fh = float(height)
    for k in range(n):
        out[0, k] = np.float32(pos[k, 0] / fw)
        out[1, k] = np.float32(pos[k, 1] / fh)
    return out


# ---------------------------------------------------- reference and logs
# (in mitsuba_logs, re-exported here: they are part of this module's interface; they build their renderers
# with this module's class, handed over here, so that mitsuba_logs never imports this module back)
_logs._renderer_class = MitsubaRenderer
