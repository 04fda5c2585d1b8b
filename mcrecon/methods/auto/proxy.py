"""Whether ``auto``'s collaborative regressions can win a frame, judged on a few tiles before the whole image.

The regression candidates (``nfor``, ``nfor_own`` and the ``mix`` of ``nfor_own`` with ``dnlm``) cost
about half of auto's time with features, yet on most scenes the selection gives them almost no pixel
(docs/methods/auto.md, "Cost").  :func:`regression_share` runs auto's candidates and its whole choice on
a mosaic of a few deterministic tiles, each grown by the regressions' reach so that their values at the
tile's interior are the whole image's, and returns the share of the interiors' pixels a regression
candidate takes, with the candidate of least summed estimate over the interiors.  The caller computes the
regressions over the whole image where that share is meaningful or a regression's sum is the least
(:meth:`Verdict.computes`).  On images too small for a few tiles to cost well under the regressions themselves the
proxy does not run (None) and the regressions are computed.
"""

from __future__ import annotations

import math
import warnings
from typing import NamedTuple

import numpy as np

from ...core.halves import Halves
from ...core.safeguard import sample_range_bounds
from ...core.stats import PixelStats
from ...errors import McreconWarning
from .blend import BLEND_SIZE
from .features import Candidate, seed_prefiltered
from .selection import summed_estimates

__all__ = ["HALO", "MAX_AREA", "MIN_TILES", "REGRESSION_SHARE", "REGRESSIONS", "TILE", "TILE_SHARE", "Verdict",
           "is_regression", "proxy_windows", "regression_share"]

#: The feature candidates the proxy decides on: the two regressions of :func:`.features._regressions` and
#: the mixes built from them.
REGRESSIONS = ("nfor", "nfor_own", "mix")
#: The share of the tiles' pixels the regression candidates must take for the regressions to be computed
#: over the whole image (``regression_proxy=REGRESSION_SHARE``) where the tiles' summed estimates do not
#: make one of them the default or its blend partner (:meth:`Verdict.computes`).  On the corpus's 22
#: feature scenes (128^2, 32 spp, four 32^2 tiles) the tiles gave them at least 0.73 on the five where
#: they matter and at most 0.066 on the other 17; the option is off by default (docs/methods/auto.md,
#: "Cost").
REGRESSION_SHARE = 0.1
#: Side of a tile's interior (pixels).
TILE = 64
#: Pixels a tile is grown by on every side: the regression's reach (its window radius 9, the
#: collaborative reprojection's radius 9 and the NL-means patch radius 3), so the regressions' values
#: on the interior are the whole image's (the prefiltered features are cropped from the whole image's).
HALO = 21
#: Share of the image's ``TILE`` x ``TILE`` cells the proxy samples (at least :data:`MIN_TILES`).
TILE_SHARE = 0.05
#: The fewest tiles the proxy judges by.
MIN_TILES = 4
#: The largest share of the image the grown tiles may cover: beyond it the proxy would cost about as much
#: as the regressions themselves, and they are computed without it.
MAX_AREA = 0.25

#: The R2 sequence's steps (Roberts 2018): the k-th tile's centre, a low-discrepancy spread over the image.
_PHI2 = 1.324717957244746
_STEP = (1.0 / _PHI2, 1.0 / (_PHI2 * _PHI2))


class Verdict(NamedTuple):
    """What the proxy's tiles say of the regressions.

    ``share``: the share of the interiors' pixels auto's choice gives a regression candidate.  ``least``,
    ``runner_up``: the two candidates of least summed estimate over the interiors, the pixel mean left
    out (the global prior's statistic: capped leave-one-out relative estimates summed over the pixels
    that vote); ``steady``: whether ``least`` is a black box, whose blend partners are other black boxes;
    ``others``: the next candidates in that order the blend may also take (up to
    :data:`~.blend.BLEND_SIZE` in all).
    """

    share: float
    least: str
    runner_up: str
    steady: bool
    others: tuple = ()

    def computes(self, threshold: float) -> bool:
        """Whether the regressions are computed over the whole image: where their share reaches
        ``threshold``, or where the tiles' sums make one of them the whole image's global default or its
        blend partner.

        The whole image's global prior makes a regression its default where its sum is the least and
        undercuts the best colour candidate's by ``Z_GLOBAL`` standard errors of the summed difference;
        the difference grows with the pixels summed and its error only with their square root, so a
        frame clears the margin that its few tiles may not, and the tiles' choice then gives the
        regressions almost nothing (a defocused checkerboard at 512^2: 0.14 % of the tiles, 99.7 % of the
        frame).  The default is blended with the next candidates (:mod:`.blend`), which a regression can be
        while it takes no pixel of its own (a defocused Cycles scene at 128^2: 2.5 % of the frame's
        choice, 12 % of its error).  So the least sum is read without the margin, and the runner-up and
        the next candidates as the blend reads them (among black boxes where the default is one)."""
        if self.share >= threshold or is_regression(self.least):
            return True
        return not self.steady and any(is_regression(n) for n in (self.runner_up,) + tuple(self.others))


def is_regression(name: str) -> bool:
    """Whether the candidate ``name`` is a regression candidate (:data:`REGRESSIONS`; ``mix33`` etc.)."""
    return name in ("nfor", "nfor_own") or name.startswith("mix")


def proxy_windows(height: int, width: int, *, tile: int | None = None, halo: int | None = None,
                  share: float | None = None, min_tiles: int | None = None,
                  max_area: float | None = None) -> list[tuple[int, int]] | None:
    """The top-left corners ``(y0, x0)`` of the proxy's tile interiors, or None where the proxy is not worth it.

    Each interior is ``tile`` x ``tile``, its grown window (``halo`` on every side) inside the image.  The
    k-th tile is centred on the k-th point of the R2 low-discrepancy sequence, so the tiles spread over the
    image and the same image size always gives the same tiles.  None where the image cannot hold a grown
    tile or the grown tiles would cover more than ``max_area`` of it.  Defaults: the module's constants.
    """
    tile = TILE if tile is None else int(tile)
    halo = HALO if halo is None else int(halo)
    share = TILE_SHARE if share is None else float(share)
    min_tiles = MIN_TILES if min_tiles is None else int(min_tiles)
    max_area = MAX_AREA if max_area is None else float(max_area)
    side = tile + 2 * halo
    if side > height or side > width:
        return None
    cells = (height // tile) * (width // tile)
    n = max(min_tiles, math.ceil(share * cells))
    if n * side * side > max_area * height * width:
        return None
    out = []
    for k in range(n):
        fy, fx = (0.5 + (k + 1) * _STEP[1]) % 1.0, (0.5 + (k + 1) * _STEP[0]) % 1.0
        y0 = min(max(int(fy * height) - tile // 2, halo), height - halo - tile)
        x0 = min(max(int(fx * width) - tile // 2, halo), width - halo - tile)
        if (y0, x0) not in out:
            out.append((y0, x0))
    return out


def _stack(parts: list[PixelStats]) -> PixelStats:
    """Statistics of equal-width crops stacked top to bottom (features stacked alike)."""
    d = dict(parts[0].__dict__)
    for name in ("count", "mean", "m2", "min", "max", "sub_sum", "sub_count"):
        if d.get(name) is not None:
            d[name] = np.concatenate([getattr(p, name) for p in parts], axis=0)
    d["height"] = sum(p.height for p in parts)
    d["features"] = {n: _stack([p.features[n] for p in parts]) for n in parts[0].features}
    out = PixelStats.__new__(PixelStats)
    out.__dict__.update(d)
    return out


def _mosaic(a: np.ndarray, outer: list[tuple[int, int, int, int]]) -> np.ndarray:
    return np.concatenate([a[y0:y1, x0:x1] for y0, y1, x0, x1 in outer], axis=0)


def _least_summed(cands: list[Candidate], y, v, count, hi, inner, safeguard) -> list[str]:
    """The candidates' names by summed estimate over the pixels ``inner`` that vote, least first, the
    pixel mean left out: the global prior's statistic (:func:`.selection.summed_estimates`, without its
    significance test) on the interiors."""
    sums = summed_estimates(cands, y, v, count, hi, safeguard, within=inner)[-1]
    if sums is None:
        sums = [0.0] * len(cands)
    named = {c.name: s for s, c in zip(sums, cands) if c.name != "box"}
    return sorted(named, key=lambda n: (named[n], list(named).index(n)))


def regression_share(method, stats: PixelStats, halves: Halves, nonfinite: str, given: list[Candidate],
                     prefiltered=None, *, steady=(), windows=None, tile: int | None = None,
                     halo: int | None = None) -> Verdict | None:
    """What auto's choice on a few tiles says of the regression candidates (None: no proxy).

    ``method``: the :class:`~.method.AutoMethod`; its candidates and choice run on the mosaic of the grown
    tiles (``windows`` default :func:`proxy_windows`) as on a frame of its own, with the OIDN candidates
    ``given`` (whole-image ones, computed before: OIDN's receptive field is the whole image) cropped into
    it, and the halves' prefiltered feature planes ``prefiltered`` (a pair, whole-image ones) cropped into
    it where computed, so the regressions' values on the interiors are the whole image's.  The selection
    itself (the global prior's sums, the region guard) sees only the mosaic: its decisions there are
    the proxy's, not the whole image's.  ``steady``: the names of the candidates the global prior blends
    only with each other (auto's black boxes).  Returns the share of the interiors' pixels the choice
    gives a regression candidate and the two candidates of least summed estimate over them
    (:class:`Verdict`).
    """
    h, w = stats.count.shape
    tile = TILE if tile is None else int(tile)
    halo = HALO if halo is None else int(halo)
    if windows is None:
        windows = proxy_windows(h, w, tile=tile, halo=halo)
    if not windows:
        return None
    outer = [(y0 - halo, y0 + tile + halo, x0 - halo, x0 + tile + halo) for y0, x0 in windows]
    crop = lambda st: _stack([st.crop(*o) for o in outer])  # noqa: E731
    ma, mb = crop(halves.a), crop(halves.b)
    mh = Halves.from_pair(ma, mb, sampler=halves.sampler)
    if prefiltered is not None:
        for st, pf in zip((ma, mb), prefiltered):
            if pf is not None:
                seed_prefiltered(st, _mosaic(pf, outer))
    black = [Candidate(c.name, _mosaic(c.image, outer), _mosaic(c.mse, outer), c.feature) for c in given]
    side = tile + 2 * halo
    ms = crop(stats)
    run = method.start(side, len(outer) * side, stats.channels)
    inner = np.zeros((len(outer) * side, side), bool)
    for i in range(len(outer)):
        inner[i * side + halo:i * side + halo + tile, halo:halo + tile] = True
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", McreconWarning)
        computed = method._candidates(ms, mh, nonfinite, given=black)
        cands = list(computed[0])  # the selection replaces its default by a blend in its own list
        order = _least_summed(cands, *computed[1:], sample_range_bounds(ms)[1], inner,
                              method.params["safeguard"])
        method._select(run, ms, mh, nonfinite, candidates=computed)
    choice = run.diagnostics["choice"].astype(np.int64)
    regress = np.array([is_regression(n) for n in run.candidate_names])
    order += ["", ""]
    return Verdict(float(regress[choice[inner]].mean()), order[0], order[1], order[0] in steady,
                   tuple(n for n in order[2:BLEND_SIZE] if n))
