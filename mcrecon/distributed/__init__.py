"""Scale-out on Dask: many frames, huge logs and huge films.

* :mod:`.batch` -- :func:`reconstruct_many` (``mcrecon batch``): one EXR per log;
* :mod:`.ingestion` -- parallel ingestion of one huge log into pixel statistics;
* :mod:`.tiles` -- tiled reconstruction of one huge film with explicit halos;
* :mod:`.cluster` -- local clusters sized to the machine, or a scheduler's.
"""

from .cluster import local_client
from .batch import BatchResult, SUMMARY_NAME, reconstruct_frame, reconstruct_many
from .ingestion import ingest, row_ranges, tree_merge
from .tiles import map_tiles, reconstruct_tiled, tile_windows

__all__ = ['reconstruct_many', 'BatchResult', 'reconstruct_frame', 'SUMMARY_NAME', 'local_client', 'ingest',
           'row_ranges', 'tree_merge', 'reconstruct_tiled', 'map_tiles', 'tile_windows']

from .._lazy import public_dir as _public_dir  # noqa: E402

__dir__ = _public_dir(__name__)
