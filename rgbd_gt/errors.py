"""The one exception type that the CLI turns into a single `error: ...` line and exit code 2."""

import os
import re
from pathlib import Path
from typing import Mapping


# NID and the L-BFGS driver: a pose (or every start of a level) that no longer sees the scan
LEFT_THE_SCAN = "the pose left the scan: fewer than 50 points in view"


class InputError(Exception):
    """Bad user input: a missing, corrupt or inconsistent file, or an impossible request.

    The message names the file (when there is one) and says what is wrong, in one line.
    """

    def __init__(self, message: str, path: object | None = None):
        super().__init__(f"{path}: {message}" if path is not None else message)


def file_problem(path: str | os.PathLike, what: str = "file") -> str | None:
    """None when `path` names an existing file, else "<what> not found" or "is a folder, not a
    <what>" (a path cut short or left empty in a config names its folder)."""
    path = Path(path)
    if path.is_file():
        return None
    return f"is a folder, not a {what}" if path.is_dir() else f"{what} not found"


def require_file(path: str | os.PathLike, what: str = "file") -> Path:
    """`path` as a Path; InputError (`file_problem`) unless it names an existing file."""
    problem = file_problem(path, what)
    if problem is not None:
        raise InputError(problem, path)
    return Path(path)


def require_listed(files: Mapping[str, str | os.PathLike], listing: str | os.PathLike) -> None:
    """InputError naming the file `listing` and the entry ("pair 2: image") of the first of
    `files` ({entry: path}) that is not an existing file (`file_problem`): a mistake in a list of
    files (a --pairs list, a bundle file) is found in the list, before any work."""
    for entry, p in files.items():
        if problem := file_problem(p):
            raise InputError(f"{entry} {p}: {problem}", listing)


def read_yaml(path: str | os.PathLike, text: str | None = None):
    """The YAML document in file `path` (or in `text`, already read from it); InputError
    "invalid YAML (line N: why)" when it does not parse. Bytes that are not UTF-8 read as U+FFFD."""
    import yaml

    try:
        return yaml.safe_load(Path(path).read_text(errors="replace") if text is None else text)
    except yaml.YAMLError as exc:
        # the problem and its line: the first line of the text is often only the context
        # ("while parsing a block mapping"), which names neither what is wrong nor where
        problem, mark = getattr(exc, "problem", None), getattr(exc, "problem_mark", None)
        why = f"line {mark.line + 1}: {problem}" if problem and mark else str(exc).splitlines()[0]
        raise InputError(f"invalid YAML ({why})", path) from None


# YAML 1.2's numbers that PyYAML (YAML 1.1) reads as text: an exponent without a dot (1e-3, 5e2)
_NUMBER_TEXT = re.compile(r"[-+]?(\.[0-9]+|[0-9]+(\.[0-9]*)?)[eE][-+]?[0-9]+")


def yaml_number(value: object) -> object:
    """`value` as a float where it is text YAML 1.2 reads as a number (`1e-3`, which PyYAML leaves
    a string), else unchanged: read where a file's key must hold a number, never for the whole
    file (a SHA-1 of digits and one e would become a float)."""
    return float(value) if isinstance(value, str) and _NUMBER_TEXT.fullmatch(value) else value


def numpy_text_problem(exc: Exception) -> str:
    """What numpy's text reader (`np.loadtxt`) says is wrong, without its advice to a programmer
    ("; use `usecols` to select a subset ..."), which names its own arguments, not the file."""
    return str(exc).split("; use `usecols`")[0]
