"""Luminance weights (Rec. 709 / sRGB primaries).
"""

from __future__ import annotations


import numpy as np


__all__ = ['LUMINANCE_WEIGHTS']

LUMINANCE_WEIGHTS = np.array([0.2126, 0.7152, 0.0722])
