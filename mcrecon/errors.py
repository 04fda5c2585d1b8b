"""Errors and warnings raised at mcrecon's boundaries.

Every error about bad input names three things: where (the file, the
request, the argument), which field, and what was expected, so that the
CLI can print it as one line and a user knows what to fix.
"""

from __future__ import annotations

__all__ = ["InputError", "RendererError", "McreconWarning"]


class InputError(ValueError):
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

    def __init__(self, where: str, field: str, problem: str):
        self.where = str(where)
        self.field = str(field)
        self.problem = str(problem)
        super().__init__(f"{self.where}: {self.field}: {self.problem}")


class RendererError(RuntimeError):
    """A renderer failed to answer a request, or answered it wrongly.

    The adaptive driver raises it after the log holds every committed
    round, so the run can be resumed.
    """

    def __init__(self, renderer: str, field: str, problem: str):
        self.where = str(renderer)
        self.field = str(field)
        self.problem = str(problem)
        super().__init__(f"{self.where}: {self.field}: {self.problem}")


class McreconWarning(UserWarning):
    """A documented policy changed the data (e.g. non-finite samples dropped)."""
