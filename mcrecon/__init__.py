"""mcrecon: image-space adaptive sampling and reconstruction for Monte Carlo renderers.

The public API in one place::

    import mcrecon
    mcrecon.write_log(path, positions, values, width=W, height=H)
    log = mcrecon.read_log(path)
    image = mcrecon.reconstruct(log, method="gem", gamma=0.2)
    renderer = mcrecon.CallableRenderer(fn, width=W, height=H)   # fn(request) -> (positions, values)
    result = mcrecon.adapt(renderer, "gem", spp=32, log="run.h5")

``import mcrecon`` is cheap: each public name imports its module on first
use (PEP 562), so the command line starts without loading numba, SciPy or
the methods it does not need.
"""

from __future__ import annotations

from ._lazy import lazy_exports as _lazy_exports
from .errors import InputError, McreconWarning, RendererError

__version__ = "0.1.0"

__all__ = ["InputError", "RendererError", "McreconWarning", "write_log", "read_log", "append_log",
           "read_exr", "write_exr", "write_png_preview", "PixelStats", "SampleSet", "Reconstruction", "SampleRequest", "SampleBatch",
           "CallableRenderer", "reconstruct", "restoration", "adapt", "available_methods", "get_method", "__version__",
           # the public modules
           "adaptive", "core", "distributed", "experiments", "filters", "io", "methods", "offline", "renderers"]

#: Public name -> the module that defines it (imported on first access).
_LAZY = {
    "append_log": "io", "read_exr": "io", "read_log": "io", "write_exr": "io", "write_log": "io",
    "write_png_preview": "io",
    "available_methods": "methods", "get_method": "methods",
    "CallableRenderer": "renderers", "SampleBatch": "renderers", "SampleRequest": "renderers",
    "Reconstruction": "offline.reconstruction", "reconstruct": "offline.reconstruction",
    "SampleSet": "core.samples",
    "PixelStats": "core.stats",
}

#: Sub-modules reachable as attributes (``mcrecon.io.read_log``) without importing them first.
_SUBMODULES = frozenset({"adaptive", "cli", "core", "distributed", "errors", "experiments", "filters", "io",
                         "methods", "offline", "renderers", "restoration"})


__getattr__, __dir__ = _lazy_exports(__name__, _LAZY, _SUBMODULES, __all__)


def adapt(renderer, method, *, spp, **kwargs):
    """Run adaptive rounds: ask a renderer for samples where they pay off, until the budget is spent.

    Each round the method plans a request (samples per pixel, or at film
    positions), the renderer answers it, the reply is validated and (with
    ``log``) committed to the sample log before the method sees it; at the
    end the method reconstructs the image.  A run with a log survives a
    kill: :func:`mcrecon.adaptive.run.resume` (``mcrecon adapt --resume
    LOG``) continues it with the same decisions.  This is
    :func:`mcrecon.adaptive.run.adapt`, imported on first use.

    Parameters
    ----------
    renderer : Renderer
        An object with ``width``, ``height``, ``channels`` and
        ``render(request) -> SampleBatch`` (:class:`mcrecon.renderers.Renderer`).
        A Python function ``fn(request) -> (positions, values)`` becomes
        one with ``mcrecon.CallableRenderer(fn, width=W, height=H)``; the
        package's others are ``mcrecon.renderers.command.CommandRenderer``
        (an external program exchanging HDF5 files),
        ``mcrecon.renderers.scenes.SceneRenderer`` (a built-in scene) and
        ``mcrecon.renderers.mitsuba.MitsubaRenderer`` (Mitsuba 3).
    method : str or Method
        A registered method name (``mcrecon.available_methods()``: ``gem``,
        ``awr``, ``ci`` and ``auto`` place their samples, the others take
        them uniformly; ``nfor`` needs a renderer that sends features) or
        a method object (``mcrecon.get_method("gem", gamma=0.1)``).
    spp : float
        The sample budget as average samples per pixel (in all
        ``round(spp * width * height)`` samples).
    seed : int, default 0
        Run seed: the whole run is reproducible from it.
    log : path-like, optional
        The sample log to create (``.h5``); every round is committed to it
        before the next request.  Refused if it exists, unless
        ``overwrite``.  Without it nothing is written and the run cannot
        be resumed.
    reference : ndarray (H, W, C), optional
        The exact image, for the per-round error (``track_error``) and the
        methods that read one; stored in the log.
    time_limit : float, optional
        Wall seconds; no new round starts after them (the run stops with
        ``stopped == "time_limit"`` and can be resumed).
    progress : bool, optional
        A progress bar on stderr; default: only on a terminal.
    nonfinite : {'drop', 'zero', 'raise'}, default 'drop'
        What happens to NaN/Inf sample values: left out of the statistics
        (and counted), taken as 0, or refused before they are committed.
    max_rounds : int, default 10000
        Rounds at most.
    track_error : bool, default True
        With a ``reference``: reconstruct after every round and record its
        relative MSE (not counted in the toolkit time).
    eps : float, default 0.01
        The ε of that relative MSE, (img - ref)² / (ref² + ε).
    metadata : mapping, optional
        Extra JSON metadata stored in the log.
    renderer_spec : mapping, optional
        How to build the renderer again on resume
        (:mod:`mcrecon.renderers.spec`); default: the renderer's own
        ``spec()`` when it has one.  A :class:`CallableRenderer` has none:
        resume it with ``resume(log, renderer)``.
    overwrite : bool, default False
        Replace an existing ``log``.
    storage_dtype : {'auto', 'float32', 'float64'}, default 'auto'
        Precision of the stored positions and values (``auto``: what the
        renderer sends).
    on_round : callable, optional
        Called with each round's record (a dict, as in
        ``AdaptiveResult.rounds``) once the round is committed.
    pipeline : bool, optional
        Render round k+1 while a toolkit thread commits round k (one round
        of lag, the same in every run); default: what the method declares.
        A renderer must then not change a reply's arrays after returning
        them.

    Returns
    -------
    AdaptiveResult
        ``image`` (H, W, C) float64, ``stats`` (the statistics of every
        committed sample), ``rounds`` (per round: samples, renderer,
        toolkit and wall seconds, error), ``stopped`` (``budget``,
        ``converged``, ``time_limit`` or ``max_rounds``), ``log``;
        ``diagnostics()`` gives the method's per-pixel maps.

    Raises
    ------
    InputError
        Bad arguments (a plain function as the renderer, an unknown
        method, a budget that is not a positive number, an existing
        ``log``), each naming the argument and the fix, before anything is
        rendered.
    RendererError
        The renderer failed or answered wrongly; every earlier round is
        committed, so a run with a log can be resumed.

    See Also
    --------
    mcrecon.adaptive.run.resume : continue a run from its log.
    mcrecon.reconstruct : an image from samples already taken.

    Examples
    --------
    >>> import numpy as np, mcrecon
    >>> from mcrecon.core.requests import jittered_positions
    >>> def render(request):
    ...     g = np.random.default_rng(request.round_index)
    ...     pos = np.zeros((0, 2))
    ...     if request.counts is not None:
    ...         pos = jittered_positions(request.counts, g)
    ...     if request.positions is not None:
    ...         pos = np.concatenate([pos, request.positions])
    ...     return pos, 0.5 + g.normal(0, 0.1, (len(pos), 3))
    >>> renderer = mcrecon.CallableRenderer(render, width=16, height=12)
    >>> result = mcrecon.adapt(renderer, "gem", spp=8)
    >>> result.image.shape, result.stopped
    ((12, 16, 3), 'budget')
    """
    from .adaptive.run import adapt as _adapt

    if callable(renderer) and not hasattr(renderer, "render"):
        raise InputError("adapt", "renderer", f"{getattr(renderer, '__name__', type(renderer).__name__)} is a plain "
                         "function; wrap it: mcrecon.CallableRenderer(fn, width=W, height=H), so the run knows "
                         "the film size and the channels")
    return _adapt(renderer, method, spp=spp, **kwargs)
