"""The display transform of previews and of the LDR metrics (exposure in stops, sRGB).
"""

from __future__ import annotations


import numpy as np


__all__ = ['tonemap_srgb']

def tonemap_srgb(image, *, exposure: float = 0.0) -> np.ndarray:
    """Display values in [0, 1]: scale by 2**exposure, sRGB curve, clip.

    Only for previews; never applied to data that is saved as EXR.
    """
    x = np.asarray(image, dtype=np.float64) * (2.0 ** float(exposure))
    x = np.nan_to_num(x, nan=0.0, posinf=1.0, neginf=0.0)
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
