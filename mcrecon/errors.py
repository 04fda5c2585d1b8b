"""Errors and warnings raised at mcrecon's boundaries.

Every error about bad input names three things: where (the file, the
request, the argument), which field, and what was expected, so that the
CLI can print it as one line and a user knows what to fix.
"""

from __future__ import annotations

import re

__all__ = ["InputError", "RendererError", "McreconWarning", "the_one"]


#: Characters that would break the one line of a message: line and paragraph breaks, other C0/C1
#: controls (an escape sequence from a file would be run by the terminal).
_UNPRINTABLE = re.compile("[\x00-\x1f\x7f-\x9f\u2028\u2029]")


def one_line(text) -> str:
    """``text`` with every control character written as an escape (``\\n``, ``\\x1b``): a name read from a
    file (a dataset, a channel, a path) may hold a newline, and a message that names it stays one line."""
    text = str(text)
    if not _UNPRINTABLE.search(text):
        return text
    return _UNPRINTABLE.sub(lambda m: repr(m.group())[1:-1], text)


class _Located:
    """An error that says where, which field and what was expected: ``"where: field: problem"``.

    The three parts are kept as given; the message shows them on one line (:func:`one_line`), which is
    where every error's text is formatted.
    """

    def __init__(self, where: str, field: str, problem: str):
        self.where = str(where)
        self.field = str(field)
        self.problem = str(problem)
        super().__init__(f"{one_line(self.where)}: {one_line(self.field)}: {one_line(self.problem)}")

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



def the_one(where: str, field: str, found, *, none: str, several: str):
    """The one item of ``found``, or an :class:`InputError` that names the fix.

    ``none`` is the problem when ``found`` is empty; ``several`` when it
    holds more than one, formatted with ``{found}`` (the items, comma
    separated) and ``{first}`` (the first of them, for an example).
    """
    found = list(found)
    if not found:
        raise InputError(where, field, none)
    if len(found) > 1:
        raise InputError(where, field, several.format(found=", ".join(map(str, found)), first=found[0]))
    return found[0]


class RendererError(_Located, RuntimeError):
    """A renderer failed to answer a request, or answered it wrongly.

    The adaptive driver raises it after the log holds every committed
    round, so the run can be resumed.  ``where`` names the renderer.
    """


class McreconWarning(UserWarning):
    """A documented policy changed the data (e.g. non-finite samples dropped)."""
