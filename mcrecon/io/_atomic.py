"""Atomic publication of a finished temporary file."""

import os

# mkstemp creates files 0600; published files get the permissions a plain open()
# would give under the process umask (read once: os.umask can only be read by setting it).
_UMASK = os.umask(0)
os.umask(_UMASK)


def publish(tmp, path) -> None:
    """chmod ``tmp`` like a normally created file, then rename it over ``path`` atomically."""
    os.chmod(tmp, 0o666 & ~_UMASK)
    os.replace(tmp, path)
