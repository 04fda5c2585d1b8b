"""CLI registration of the experiment commands (``mcrecon experiment ...``, ``mcrecon bias``)."""

from __future__ import annotations


def register(sub) -> None:
    """Add the experiment sub-commands to the ``mcrecon`` parser."""
    return None
