"""Errors and warnings raised at mcrecon's boundaries.

Every error about bad input names three things: where (the file, the
request, the argument), which field, and what was expected, so that the
CLI can print it as one line and a user knows what to fix.
"""

from __future__ import annotations

__all__ = ["InputError", "RendererError", "McreconWarning"]


class _Located:
    """An error that says where, which field and what was expected: ``"where: field: problem"``."""

    def __init__(self, where: str, field: str, problem: str):
        self.where = str(where)
        self.field = str(field)
        self.problem = str(problem)
        super().__init__(f"{self.where}: {self.field}: {self.problem}")

    def __reduce__(self):  # pickled as built (Dask workers send errors back)
        return type(self), (self.where, self.field, self.problem)


class InputError(_Located, ValueError):
    """Bad input at a boundary: a file, a CLI argument, an option value.

    Parameters
    ----------
    where : str
        The file path, request or argument the problem is in.
    field : str
        The dataset, attribute, option or column that is wrong.
    problem : str
        What is wrong and what was expected (the fix).
    """



class RendererError(_Located, RuntimeError):
    """A renderer failed to answer a request, or answered it wrongly.

    The adaptive driver raises it after the log holds every committed
    round, so the run can be resumed.  ``where`` names the renderer.
    """


class McreconWarning(UserWarning):
    """A documented policy changed the data (e.g. non-finite samples dropped)."""
