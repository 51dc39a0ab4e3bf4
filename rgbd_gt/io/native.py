"""What C and C++ libraries print (libjpeg, libpng, libE57, Open3D) caught instead of shown.

They write to the process's stdout and stderr themselves, past Python: a user would see their
noise above the one `error:` line, and some of it is the only sign of a problem (libjpeg only
warns when a JPEG ends early).
"""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
from typing import Iterator


@contextlib.contextmanager
def native_output(fds: tuple[int, ...] = (1, 2)) -> Iterator[list[str]]:
    """Redirect the file descriptors `fds` meanwhile; the yielded list gets their lines at the end."""
    said: list[str] = []
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(fd) for fd in fds]
    with tempfile.TemporaryFile() as sink:
        for fd in fds:
            os.dup2(sink.fileno(), fd)
        try:
            yield said
        finally:
            for fd, copy in zip(fds, saved):
                os.dup2(copy, fd)
                os.close(copy)
            sink.seek(0)
            said.extend(sink.read().decode(errors="replace").splitlines())
