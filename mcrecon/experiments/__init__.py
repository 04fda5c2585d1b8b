"""Experiments that reproduce the papers' measurements and write reports.

Modules: ``convergence`` (error against spp and wall time), ``stability``
(extreme inputs), ``gallery``, ``error_rate`` (GEM Sec. 4.3),
``statistics`` (Tamstorf & Jensen's normality test and bootstrap bias).
They are imported on use (``from mcrecon.experiments.convergence import
run_convergence``): each pulls in plotting and scene code.
"""

__all__: list[str] = []


from .._lazy import public_dir as _public_dir

__dir__ = _public_dir(__name__)
