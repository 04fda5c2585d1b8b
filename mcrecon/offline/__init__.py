"""Offline reconstruction: the one input dispatcher and :func:`reconstruct`.

* :mod:`.inputs` -- :func:`gather_inputs`: any source into the inputs a method declares;
* :mod:`.reconstruction` -- :func:`reconstruct`, :class:`Reconstruction`.
"""

from .inputs import gather_inputs, statistics_for
from .reconstruction import Reconstruction, reconstruct

__all__ = ["reconstruct", "Reconstruction", "gather_inputs", "statistics_for"]

from .._lazy import public_dir as _public_dir  # noqa: E402

__dir__ = _public_dir(__name__)
