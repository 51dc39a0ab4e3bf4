"""The one exception type that the CLI turns into a single `error: ...` line and exit code 2."""


class InputError(Exception):
    """Bad user input: a missing, corrupt or inconsistent file, or an impossible request.

    The message names the file (when there is one) and says what is wrong, in one line.
    """

    def __init__(self, message: str, path: object | None = None):
        super().__init__(f"{path}: {message}" if path is not None else message)
