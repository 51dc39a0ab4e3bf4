"""The one exception type that the CLI turns into a single `error: ...` line and exit code 2."""

import os
from pathlib import Path


class InputError(Exception):
    """Bad user input: a missing, corrupt or inconsistent file, or an impossible request.

    The message names the file (when there is one) and says what is wrong, in one line.
    """

    def __init__(self, message: str, path: object | None = None):
        super().__init__(f"{path}: {message}" if path is not None else message)


def require_file(path: str | os.PathLike) -> Path:
    """`path` as a Path; InputError "file not found" unless it names an existing file."""
    path = Path(path)
    if not path.is_file():
        raise InputError("file not found", path)
    return path
