"""Offline reconstruction: the one input dispatcher and :func:`reconstruct`.

* :mod:`.inputs` -- :func:`gather_inputs`: any source into the inputs a method declares;
* :mod:`.pixel_files` -- pixel-statistics EXRs and half-buffer pairs of them as sources;
* :mod:`.reconstruction` -- :func:`reconstruct`, :class:`Reconstruction`.
"""

from .inputs import gather_inputs, statistics_for
from .pixel_files import read_pixel_file_source
from .reconstruction import Reconstruction, reconstruct

__all__ = ["reconstruct", "Reconstruction", "gather_inputs", "statistics_for", "read_pixel_file_source"]

from .._lazy import public_dir as _public_dir  # noqa: E402

__dir__ = _public_dir(__name__)
