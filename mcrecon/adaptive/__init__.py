"""Adaptive runs: rounds of plan -> request -> render -> validate -> commit, resumable from their log.

* :mod:`.run` -- :func:`adapt`, :func:`resume`, :class:`AdaptiveResult`;
* :mod:`.context` -- :class:`~.context.RunContext`, the run's parts, schedule and accounting, assembled
  once by ``adapt`` and ``resume`` alike; :class:`~.context.RunClock`;
* :mod:`.schedule` -- round seeds, the driver's initial pass, planning a round, pipelining declarations;
* :mod:`.rounds` -- one round (render, validate, commit) and the sequential and pipelined loops.
"""

from .run import AdaptiveResult, adapt, resume
from .schedule import STORAGE_DTYPES, method_pipelines, round_seeds

__all__ = ["adapt", "resume", "AdaptiveResult", "round_seeds", "STORAGE_DTYPES", "method_pipelines"]

from .._lazy import public_dir as _public_dir  # noqa: E402

__dir__ = _public_dir(__name__)
