"""All file I/O of mcrecon: sample logs (HDF5) and images (EXR, PNG).

The names below import their module on first use (PEP 562): reading a
log does not load the image writers, nor writing an EXR h5py.
"""

from .._lazy import lazy_exports as _lazy_exports

__all__ = ["FORMAT_VERSION", "LogChunk", "SampleLog", "append_log", "read_log", "write_log",
           "set_run_settings", "read_exr", "write_exr", "write_png_preview", "write_false_colour",
           "tonemap_srgb", "summarize_log", "PixelStatsEXR", "read_pixel_stats_exr", "read_seed_set"]

#: Public name -> the sub-module that defines it.
_LAZY = {
    **dict.fromkeys(("FORMAT_VERSION", "LogChunk"), "logformat"),
    **dict.fromkeys(("SampleLog", "read_log"), "reader"),
    **dict.fromkeys(("append_log", "set_run_settings", "write_log"), "writer"),
    **dict.fromkeys(("read_exr", "write_exr", "write_png_preview", "write_false_colour", "tonemap_srgb"), "images"),
    "summarize_log": "summary",
    "PixelStatsEXR": "pixel_exr", "read_pixel_stats_exr": "pixel_exr", "read_seed_set": "seed_sets",
}


#: Sub-modules reachable as attributes without importing them first.
_SUBMODULES = frozenset(("reader", "writer", "lock", "logformat", "images", "summary", "pixel_exr", "seed_sets", "_atomic"))


__getattr__, __dir__ = _lazy_exports(__name__, _LAZY, _SUBMODULES, __all__)
