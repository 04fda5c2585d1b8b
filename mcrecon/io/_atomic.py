"""Atomic writes: the one place that turns a finished temporary file into the real one.

Every file mcrecon writes whole (logs, EXR and PNG images, request files,
Mitsuba renders) goes through :func:`atomic_path`: the content is written
to a temporary file beside the target and renamed over it only when
complete, so a reader never sees a half-written file and a crash leaves
the old file (or none), never a truncated one.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path
from typing import Iterator

# mkstemp creates files 0600; published files get the permissions a plain open()
# would give under the process umask (read once: os.umask can only be read by setting it).
_UMASK = os.umask(0)
os.umask(_UMASK)


def publish(tmp, path) -> None:
    """chmod ``tmp`` like a normally created file, then rename it over ``path`` atomically."""
    os.chmod(tmp, 0o666 & ~_UMASK)
    os.replace(tmp, path)


@contextlib.contextmanager
def atomic_path(path, *, suffix: str = "") -> Iterator[str]:
    """Yield a temporary path beside ``path``; publish it over ``path`` when the block ends normally.

    The parent directory is created.  If the block raises (or the process
    is interrupted), the temporary file is removed and ``path`` is left
    untouched.  ``suffix`` ends the temporary name (writers that infer the
    format from the extension, e.g. ``.exr``).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp" + suffix, dir=path.parent)
    os.close(fd)
    try:
        yield tmp
        publish(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
