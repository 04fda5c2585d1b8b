"""All file I/O of mcrecon: sample logs (HDF5) and images (EXR, PNG)."""

from .samplelog import (FORMAT_VERSION, LogChunk, SampleLog, append_log, read_log, set_run_settings,
                        write_log)
from .images import read_exr, write_exr, write_png_preview, write_false_colour, tonemap_srgb
from .summary import summarize_log
from .pixel_exr import PixelStatsEXR, read_pixel_stats_exr

__all__ = ["FORMAT_VERSION", "LogChunk", "SampleLog", "append_log", "read_log", "write_log",
           "set_run_settings", "read_exr", "write_exr", "write_png_preview", "write_false_colour",
           "tonemap_srgb", "summarize_log", "PixelStatsEXR", "read_pixel_stats_exr"]
