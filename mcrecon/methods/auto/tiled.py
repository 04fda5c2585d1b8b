"""auto in tiles: the film's whole-image decisions made once, each tile's selection local.

auto's result at a pixel reads the whole film through a few decisions:
OIDN (in HDR mode it scales its input by an exposure over the image it is
given), the regressions' feature scales (each prefiltered feature plane's
mean and deviation), dnlm's unit (the irradiance's mean magnitude), the
global prior's default (each candidate's estimate summed over the film,
the thin vote's counts and the black boxes' crossed votes, the guards'
block sums, the blend's weights).  Everything else is a
function of a neighbourhood.  :func:`film_pass` makes those decisions on the
film and stores what the tiles read:

* pass 0, on the film's inputs: the halves' prefiltered features (their
  scales from them), dnlm's units and OIDN's candidates, each run once on
  the whole film (from a log, band by band into film-sized files: the
  prefiltered features, OIDN's float32 inputs and the planes its scores
  read; OIDN then runs on the film's inputs mapped from the files and its
  scores are made band by band, :func:`_pass0_read`);
* pass 1, tile by tile (each grown by the candidates' reach,
  :meth:`~.method.AutoMethod.candidate_reach`): every candidate's image and
  estimate, the pixel means, their variance, the counts and the top of the
  sample range, each tile's inner pixels written to film-sized files on disk
  (float32 as the selection holds the candidates, float64 for the rest);
* the global prior's default (:func:`~.selection.prior_default`) on those
  files, read as memory maps: the untiled sums in the untiled order.

The tiles' selection (pass 2, :meth:`~.method.AutoMethod.reconstruct_run`)
reads its grown tile's candidates from the files and applies the default.
"""

from __future__ import annotations

import copy
import dataclasses
import os
import shutil
import tempfile
import weakref

import numpy as np

from .features import Candidate

__all__ = ["FilmPlanes", "Film", "film_pass"]


def selection_reach(smooth: float, guard: float) -> int:
    """The reach of auto's selection on its candidates, composed: the clamp's variance (a 5 x 5 pool of a
    3 x 3 one: 3 px), the smoothed estimates and the global prior's local tests (``smooth``'s kernel,
    truncated at 3 sigma), the region guard's smoothing of the chosen estimates (``guard * smooth``), the
    sample range and the medians of the 3 x 3 neighbourhoods read after them (4), and a margin of 12:
    37 px by default."""
    def radius(sigma):   # MaskedSmoothing's kernel
        return int(3.0 * float(sigma) + 0.5)
    return radius(guard * smooth) + radius(smooth) + 3 + 4 + 12


def candidate_reach(params: dict, gauss: bool) -> int:
    """Pixels of context auto's candidates at a pixel read, OIDN's and the prefiltered features given (the
    film's): the widest Gaussian of the SURE bank (``gauss``) on the variance's 5 x 5 pool (2 px more), the
    regressions (window 9, its fits' windows 9, patch 3: 21), dnlm (window 7, patch 3), NL-means
    (``nlm_radius + nlm_patch``), the cross-bilateral filters (window 5, patch 3), and a margin of 4: 55 px
    by default (the 8-scale bank's 49 + 2)."""
    from ...filters.gaussian import final_sigmas, pixel_kernel
    bank = max([(pixel_kernel(s).size - 1) // 2 for s in final_sigmas(params["scales"])], default=0) if gauss else 0
    return int(max(bank + 2, 2 * 9 + 3, 7 + 3, params["nlm_radius"] + params["nlm_patch"], 5 + 3) + 4)


class FilmPlanes:
    """Film-sized arrays in files of a temporary directory (removed with this object), written a window at
    a time and read back a window at a time (or whole, as memory maps).

    Each write and read maps its file for that call alone: pages a process has mapped count in its resident
    set while they stay mapped, so files held open would bring the film back into memory."""

    def __init__(self, height: int, width: int):
        self.shape = (int(height), int(width))
        self.dir = tempfile.mkdtemp(prefix="mcrecon-auto-tiles-")
        self._cleanup = weakref.finalize(self, shutil.rmtree, self.dir, True)
        self.paths: dict = {}

    def put(self, name: str, window, a: np.ndarray) -> None:
        """Write ``a`` (the window's pixels, (h, w, ...)) at ``window`` = ``(y0, y1, x0, x1)`` of plane
        ``name``, created on first use with ``a``'s trailing shape and dtype; a float64 window into a
        float32 plane turns the plane float64 (its earlier windows as they were stored)."""
        y0, y1, x0, x1 = window
        path = self.paths.get(name)
        old = None if path is None else np.load(path, mmap_mode="r")
        if old is None or (old.dtype != a.dtype and a.dtype == np.float64):
            path = os.path.join(self.dir, f"{name}.{a.dtype}.npy")
            m = np.lib.format.open_memmap(path, mode="w+", dtype=a.dtype, shape=self.shape + a.shape[2:])
            if old is not None:
                m[...] = old
            self.paths[name] = path
        else:
            m = np.load(path, mmap_mode="r+")
        del old
        m[y0:y1, x0:x1] = a
        m.flush()
        del m

    def create(self, name: str, trailing: tuple, dtype) -> np.memmap:
        """A new plane ``name`` of ``trailing`` shape beyond the film's and ``dtype``, as a writable memory map
        of its file (for a writer of the whole film, e.g. OIDN's output; flushed and let go by the caller)."""
        path = os.path.join(self.dir, f"{name}.{np.dtype(dtype)}.npy")
        self.paths[name] = path
        return np.lib.format.open_memmap(path, mode="w+", dtype=dtype, shape=self.shape + tuple(trailing))

    def get(self, name: str, window=None) -> np.ndarray:
        """Plane ``name``: a contiguous copy of ``window``, or the film's as a memory map (copy on write:
        the file stays as written), mapped while the caller holds it."""
        m = np.load(self.paths[name], mmap_mode="c")
        if window is None:
            return m
        y0, y1, x0, x1 = window
        return np.ascontiguousarray(m[y0:y1, x0:x1])

    def __contains__(self, name) -> bool:
        return name in self.paths

    @property
    def whole(self) -> tuple:
        """The film's window ``(0, height, 0, width)``."""
        return (0, self.shape[0], 0, self.shape[1])


class _Mapped:
    """A candidate of the film whose image and estimate are mapped from the files each time they are read
    (:class:`FilmPlanes.get`), so that reading every candidate's estimate in turn holds one at a time."""

    def __init__(self, planes: FilmPlanes, k: int, name: str, feature: bool, crossed):
        self.planes, self.k, self.name, self.feature, self.crossed = planes, k, name, feature, crossed

    @property
    def image(self) -> np.ndarray:
        return self.planes.get(f"image{self.k}")

    @property
    def mse(self) -> np.ndarray:
        return self.planes.get(f"mse{self.k}")


@dataclasses.dataclass(eq=False)
class Film:
    """What the tiles of one film are given: the planes (:class:`FilmPlanes`), the candidates' names,
    flags and crossed votes, the global prior's default (None: no prior), the regressions' feature scales
    of each half, and which planes pass 0 stored (OIDN's candidates, each half's prefiltered features)."""

    planes: FilmPlanes
    names: list = dataclasses.field(default_factory=list)
    features: list = dataclasses.field(default_factory=list)
    crossed: list = dataclasses.field(default_factory=list)
    default: object = None
    scales: tuple = (None, None)
    units: tuple = (None, None)
    black: list = dataclasses.field(default_factory=list)     # OIDN's candidates: (name, feature, crossed)
    prefiltered: bool = False

    def candidates(self, window=None) -> list:
        """The candidates over ``window`` (copies, as the selection holds them), or the film's (each image
        and estimate mapped from its file where it is read)."""
        if window is None:
            return [_Mapped(self.planes, k, n, f, c)
                    for k, (n, f, c) in enumerate(zip(self.names, self.features, self.crossed))]
        return [Candidate(n, self.planes.get(f"image{k}", window), self.planes.get(f"mse{k}", window), f, c)
                for k, (n, f, c) in enumerate(zip(self.names, self.features, self.crossed))]

    def tile_inputs(self, window, where: str) -> tuple:
        """A tile's ``(candidates, pixel means, their variance, counts)`` over ``window`` (its place in the
        film: :attr:`~.method.AutoRun.window`), as the selection reads them."""
        if window is None:
            from ...errors import InputError
            raise InputError(where, "window", "a tiled auto reconstructs tiles of its film (the run's window); "
                             "reconstruct the film with mcrecon.reconstruct(..., tile=N)")
        get = self.planes.get
        return self.candidates(window), get("y", window), get("v", window), get("count", window)

    def black_boxes(self, window) -> list:
        """OIDN's candidates over ``window``, computed on the film in pass 0."""
        return [Candidate(n, self.planes.get(f"oidn_image{k}", window), self.planes.get(f"oidn_mse{k}", window),
                          f, c) for k, (n, f, c) in enumerate(self.black)]

    def seed(self, halves, window) -> None:
        """Give a tile's halves the film's prefiltered features over ``window``
        (:func:`~.features.seed_prefiltered`): the regressions and OIDN's albedo read the film's values."""
        from .features import seed_prefiltered

        if self.prefiltered and halves is not None:
            for i, hf in enumerate(halves):
                seed_prefiltered(hf, self.planes.get(f"prefiltered{i}", window))


def _plane_scales(planes) -> tuple:
    """The regressions' ``(mean, deviation)`` of each prefiltered feature plane of a half (H, W, D), the film's
    (:func:`~mcrecon.filters.regression.feature_scale`)."""
    from ...filters.regression import feature_scale
    return tuple(feature_scale(planes[..., d]) for d in range(planes.shape[2]))


def _pass0(method, inputs, film: Film) -> None:
    """OIDN's candidates, the halves' prefiltered features and dnlm's units on the film's inputs (a
    :class:`~mcrecon.methods.MethodInputs` of the whole film), as the untiled run computes them."""
    from .features import dnlm_scale, prefiltered_features, release_prefiltered
    from .proxy import REGRESSIONS

    halves = inputs.halves if method.requires.samples else None   # a dual-buffer candidate among them
    if halves is None:
        return
    stats = inputs.stats if inputs.stats is not None else halves.merged()
    aux = method._aux_replaces_oidn(stats)
    fnames = method._feature_names
    with_features = bool(fnames) and bool(halves.a.features)
    regress = set(REGRESSIONS) & set(fnames)
    if with_features and (aux or regress):
        pf = [prefiltered_features(hf) for hf in halves]
        for i, p in enumerate(pf):
            film.planes.put(f"prefiltered{i}", film.planes.whole, p)
        if regress:
            film.scales = tuple(_plane_scales(p) for p in pf)
        film.prefiltered = True
        del pf
    if with_features and ("dnlm" in fnames or "mix" in fnames):
        film.units = tuple(dnlm_scale(hf) for hf in halves)
    _oidn(method, stats, halves, aux, film)
    release_prefiltered(*halves)


def _oidn(method, stats, halves, aux: bool, film: Film, aux_planes=None) -> None:
    """OIDN's candidates of the film (``stats``, ``halves``: its statistics, the colour's at least), as
    :meth:`~.method.AutoMethod._candidates` computes them, stored in ``film``; ``aux``: with the albedo and
    normal (``aux_planes``: each half's, :func:`~.blackbox.oidn_aux`; None: the halves' own)."""
    from ...core.halves import mean_variances
    from .blackbox import oidn_candidate, oidn_runs
    from .passes import _stored

    v, va, vb = mean_variances(stats, halves)
    black = [dataclasses.replace(c, image=_stored(c.image), mse=_stored(c.mse))   # as the selection holds them
             for name, ax, only in oidn_runs(method._names, aux)
             for c in oidn_candidate(name, stats, v, halves, aux=ax, halves_only=only, variances=(va, vb),
                                     aux_planes=aux_planes if ax else None)]
    for k, c in enumerate(black):
        film.planes.put(f"oidn_image{k}", film.planes.whole, c.image)
        film.planes.put(f"oidn_mse{k}", film.planes.whole, c.mse)
        film.black.append((c.name, c.feature, c.crossed))


#: Rows of context the halves' feature prefilter reads (its window 5 and patch 3, NFOR's Sec. 5.1).
PREFILTER_REACH = 5 + 3


#: Rows of context OIDN's scores read on its images and the colour's planes (the crossed vote's 3 x 3
#: neighbourhoods: :func:`~.blackbox.oidn_scores`).
SCORE_REACH = 1


def _pass0_read(method, reader, film: Film) -> None:
    """Pass 0 from a reader of the film a window at a time (:class:`~mcrecon.offline.tiles.FilmReader`), band
    by band (each band's rows grown by the prefilter's reach, from a row of the NL-means kernels' bands:
    the film's planes bit for bit): the halves' prefiltered features, the magnitudes of dnlm's irradiance
    (:func:`~mcrecon.filters.demodulation.irradiance_magnitude`) and OIDN's inputs (:func:`_oidn_inputs`)
    go to the files; then the feature scales and dnlm's units from the files, and OIDN's candidates from
    them (:func:`_oidn_planes`).  No read asks for more than a band."""
    from ...filters.demodulation import irradiance_magnitude, magnitude_scale
    from ...filters.nlmeans import BAND
    from .blackbox import aux_names
    from .features import _filled, feature_slices, prefiltered_features, release_prefiltered
    from .proxy import REGRESSIONS

    if not method.requires.samples:   # no dual-buffer candidate: no halves
        return
    h, w = film.planes.shape
    fnames = method._feature_names
    regress = set(REGRESSIONS) & set(fnames)
    colour = copy.copy(method)   # the same samples' colour alone
    object.__setattr__(colour, "_feature_names", ())
    aux = units = False
    slices, names = None, []
    for y0, y1 in reader.bands:
        by0, by1 = max(0, y0 - PREFILTER_REACH) // BAND * BAND, min(h, y1 + PREFILTER_REACH)
        halves = reader.read((by0, by1, 0, w), method=method if fnames else colour).halves
        rows = (y0, y1, 0, w)
        cut = slice(y0 - by0, y1 - by0)
        planes = [(), ()]   # each half's albedo and normal for oidn_aux
        if fnames and halves.a.features:
            aux = "oidn_aux" in fnames and "albedo" in halves.a.features
            units = ("dnlm" in fnames or "mix" in fnames) and "albedo" in halves.a.features
            for i, hf in enumerate(halves):
                if aux or regress:
                    pf = prefiltered_features(hf)[cut]
                    film.planes.put(f"prefiltered{i}", rows, pf)
                    slices = feature_slices(hf)
                    names = aux_names(slices) if aux else []
                    planes[i] = tuple(pf[..., slices[n]] for n in names)
                    del pf
                if units:   # dnlm's unit's magnitudes (demodulation_scale, as dnlm_scale takes it)
                    alb = hf.features["albedo"]
                    film.planes.put(f"irradiance{i}", rows, irradiance_magnitude(_filled(hf.mean, hf.count)[cut],
                                                                                 _filled(alb.mean, alb.count)[cut]))
        _oidn_inputs(film, halves.without_features(), rows, cut, tuple(planes) if aux else None)
        release_prefiltered(*halves)
        del halves, planes
    if slices is not None:
        film.prefiltered = True
        if regress:
            film.scales = tuple(_plane_scales(film.planes.get(f"prefiltered{i}")) for i in range(2))
    if units:
        film.units = tuple(magnitude_scale(film.planes.get(f"irradiance{i}")) for i in range(2))
    _oidn_planes(method, reader.bands, aux, len(names), film)


def _oidn_inputs(film: Film, halves, rows, cut, aux_planes) -> None:
    """Write what OIDN's candidates read of a band's colour statistics (``halves``, grown by at least
    :data:`SCORE_REACH`; ``rows`` of the film, ``cut`` of the band) to the film's files: OIDN's inputs as
    OIDN reads them (float32: all the samples' and each half's pixel means, empty pixels filled, and with
    ``aux_planes``, each half's albedo and normal, their merge for all the samples), and the planes its
    scores read (:func:`~.blackbox.oidn_scores`, float64: the pixel means, their variance and counts, each
    half's means, counts, their variance and the top of its sample range)."""
    from ...core.halves import mean_variances
    from ...core.safeguard import sample_range_bounds
    from .blackbox import CROSSED, _colour, _merged_aux

    put = film.planes.put
    stats = halves.merged()
    v, va, vb = mean_variances(stats, halves)
    y = _colour(stats)
    put("oidn_in", rows, y[cut].astype(np.float32))
    put("col_y", rows, y[cut])
    put("col_v", rows, v[cut])
    put("col_n", rows, stats.count[cut])
    for i, (hf, vh) in enumerate(zip(halves, (va, vb))):
        put(f"oidn_in{i}", rows, _colour(hf)[cut].astype(np.float32))
        put(f"col_m{i}", rows, hf.mean[cut])
        put(f"col_n{i}", rows, hf.count[cut])
        put(f"col_v{i}", rows, vh[cut])
        if CROSSED:
            put(f"col_hi{i}", rows, sample_range_bounds(hf)[1][cut])
    if aux_planes is not None:
        a, b = aux_planes
        for k, p in enumerate(_merged_aux(a, b, halves.a.count[cut], halves.b.count[cut])):
            put(f"oidn_aux_{k}", rows, p.astype(np.float32))
        for i, half in enumerate(aux_planes):
            for k, p in enumerate(half):
                put(f"oidn_aux{i}_{k}", rows, p.astype(np.float32))


def _oidn_planes(method, bands, aux: bool, n_aux: int, film: Film) -> None:
    """OIDN's candidates of the film from its files (:func:`_oidn_inputs`), as :func:`_oidn` computes them
    from the film's statistics, bit for bit: each OIDN run on the film's float32 inputs (its output to the
    files), then its scores (:func:`~.blackbox.oidn_scores`) band by band (``bands``, each grown by
    :data:`SCORE_REACH`), the candidates' stored images and estimates and the crossed vote's terms to the
    files, the crossed vote summed over the film's terms in the film's order.  In memory: an OIDN run's
    inputs and output (float32, 12 bytes a pixel each, the albedo and normal with the aux) and OIDN's
    scratch (:data:`~.blackbox.OIDN_MEMORY_MB`), then a band's planes."""
    from .blackbox import CROSSED, oidn_filter, oidn_image, oidn_runs, oidn_scores
    from .passes import _stored
    from .selection import crossed_total

    h, w = film.planes.shape
    get, put, whole = film.planes.get, film.planes.put, film.planes.whole
    runs = oidn_runs(method._names, aux)
    for name, ax, only in runs:   # OIDN's images: on all the samples (not with halves_only), on each half
        for part, suffix in (("", ""), ("0", "0"), ("1", "1")):
            if only and not part:
                continue
            planes = tuple(get(f"oidn_aux{suffix}_{k}") for k in range(n_aux)) if ax else ()
            out = film.planes.create(f"{name}_den{part}", (3,), np.float32)
            oidn_filter(get(f"oidn_in{part}"), planes, clean_aux=ax, out=out)
            out.flush()
            del planes, out
    kinds = []
    for y0, y1 in bands:
        g0, g1 = max(0, y0 - SCORE_REACH), min(h, y1 + SCORE_REACH)
        win, rows, cut = (g0, g1, 0, w), (y0, y1, 0, w), slice(y0 - g0, y1 - g0)
        y, v, count = get("col_y", win), get("col_v", win), get("col_n", win)
        halves = tuple((get(f"col_m{i}", win), get(f"col_n{i}", win), get(f"col_v{i}", win),
                        get(f"col_hi{i}", win) if CROSSED else None) for i in range(2))
        k = 0
        kinds = []
        for g, (name, ax, only) in enumerate(runs):
            img = None if only else oidn_image(y, get(f"{name}_den", win))
            fa, fb = (oidn_image(halves[i][0], get(f"{name}_den{i}", win)) for i in range(2))
            cands, terms = oidn_scores(name, img, fa, fb, y, v, count, halves, aux=ax)
            for c in cands:
                put(f"oidn_image{k}", rows, _stored(c.image[cut]))
                put(f"oidn_mse{k}", rows, _stored(c.mse[cut]))
                kinds.append((c.name, c.feature, g))
                k += 1
            for i, (r, votes) in enumerate(terms or ()):
                put(f"crossed{g}_r{i}", rows, r[cut])
                put(f"crossed{g}_votes{i}", rows, votes[cut])
            del img, fa, fb, cands, terms
    crossed = [crossed_total([(get(f"crossed{g}_r{i}"), get(f"crossed{g}_votes{i}")) for i in range(2)])
               if CROSSED else None for g in range(len(runs))]
    film.black.extend((n, f, crossed[g]) for n, f, g in kinds)


def film_pass(method, inputs, each_tile) -> Film:
    """The film's decisions and stores for auto's tiles (the module's docstring): passes 0 and 1 and the
    global prior's default.

    ``inputs``: the film's :class:`~mcrecon.methods.MethodInputs`, or a reader of it a window at a time
    (:class:`~mcrecon.offline.tiles.FilmReader`: ``read(window)``, ``shape``); ``each_tile(halo)``: the
    film's tiles grown by ``halo`` as ``(outer, inner, inputs of outer)``, read band by band."""
    from ...core.safeguard import sample_range_bounds
    from .blackbox import BLACK_BOXES, _guards
    from .onesided import one_sided
    from .selection import prior_default

    if each_tile is None:
        from ...errors import InputError
        raise InputError(method.where, "tile", "auto's tiles need the film's pass over its tiles first; tile it "
                         "with mcrecon.reconstruct(..., tile=N) (reconstruct --tile N)")
    h, w, _ = inputs.shape
    film = Film(FilmPlanes(h, w))
    if hasattr(inputs, "read"):
        _pass0_read(method, inputs, film)
    else:
        _pass0(method, inputs, film)
    for outer, inner, sub in each_tile(method.candidate_reach()):
        oy0, _, ox0, _ = outer
        y0, y1, x0, x1 = inner
        cut = (slice(y0 - oy0, y1 - oy0), slice(x0 - ox0, x1 - ox0))
        stats = sub.stats if sub.stats is not None else sub.halves.merged()
        film.seed(sub.halves, outer)
        cands, y, v, count = method._candidates(stats, sub.halves, sub.nonfinite, given=film.black_boxes(outer),
                                                scales=film.scales, units=film.units)
        names = [c.name for c in cands]
        if not film.names:
            film.names, film.features = names, [c.feature for c in cands]
            film.crossed = [c.crossed for c in cands]
        for k, c in enumerate(cands):
            film.planes.put(f"image{k}", inner, c.image[cut])
            film.planes.put(f"mse{k}", inner, c.mse[cut])
        hi = sample_range_bounds(stats)[1]
        heavy = one_sided(stats)
        heavy = np.zeros(count.shape, bool) if heavy is None else heavy
        for name, a in (("y", y), ("v", v), ("count", count), ("hi", hi), ("heavy", heavy)):
            film.planes.put(name, inner, np.asarray(a)[cut])
        del cands, y, v, count, hi, stats, sub
    p = method.params
    if p["global_prior"] is not None and len(film.names) > 1 and p["smooth"] > 0:
        cands = film.candidates()
        get = film.planes.get
        film.default = prior_default(cands, get("y"), get("v"), get("count"), get("hi"), p["safeguard"],
                                     _guards(cands), steady=[k for k, n in enumerate(film.names) if n in BLACK_BOXES],
                                     heavy=get("heavy"))
        del cands
    return film
