"""A command's outputs: every path checked before work starts, all written together at the end.

Commands write each output into a staging folder beside its target and name it only when the
command has succeeded (`Outputs.commit`), so an error at any point leaves no output behind and
every earlier output as it was. A folder in an output path that does not exist yet is created
at commit, not before: a failed command leaves no empty folders either.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import uuid
from pathlib import Path
from typing import Iterable, Mapping, Sequence

from rgbd_gt.errors import InputError, file_problem


def _existing_ancestor(path: Path, option: str) -> Path:
    """The nearest folder above `path` that exists; InputError when a file stands in the way."""
    for parent in path.parents:
        if parent.exists():
            if not parent.is_dir():
                raise InputError(f"{option}: cannot write under {parent}: it is a file, not a folder", path)
            return parent
    return Path(".")


class Outputs:
    """Plan, stage and commit a command's outputs.

        outs = Outputs({"--scan": scan, ...})  # inputs by option: checked to exist
        pose = outs.file(output, "-o", (".yaml", ".yml"))  # checked now, nothing made yet
        ...  # more checks
        with outs:  # makes the staging folders; commits when the block ends, discards on error
            write_pose(pose, ...)
    """

    def __init__(self, inputs: Mapping[str, str | os.PathLike | None] | Iterable[str | os.PathLike | None]):
        """inputs: the paths no output may overwrite; given as {option: path}, each (but None) is
        checked now to name an existing file, so that a wrong one is named with its option."""
        if isinstance(inputs, Mapping):
            for option, p in inputs.items():
                if p is not None and (problem := file_problem(p)):
                    raise InputError(f"{option}: {problem}", p)
            inputs = inputs.values()
        self.inputs = [Path(p) for p in inputs if p is not None]
        self.staged: list[tuple[Path, Path, bool]] = []  # (staged path, target, is a folder)
        self._whole: set[Path] = set()  # staged folders whose entries replace the target's wholesale
        self._stage_dirs: list[Path] = []

    def _check(self, path: Path, option: str, folder: bool) -> Path:
        path = Path(path)
        if str(path) in ("", "."):
            raise InputError(f"{option}: an output path is needed")
        for inp in self.inputs:
            if path.resolve() == inp.resolve() or (path.exists() and inp.exists() and path.samefile(inp)):
                raise InputError(f"{option}: the output would overwrite the input {inp}", path)
        for _, other, _ in self.staged:
            if path.resolve() == other.resolve():
                raise InputError(f"{option}: the same path is given for two outputs", path)
            if path.resolve() in other.resolve().parents or other.resolve() in path.resolve().parents:
                raise InputError(f"{option}: one output lies inside another ({other})", path)
        if not folder and path.is_dir():
            raise InputError(f"{option}: is a folder; give a file name", path)
        if folder and path.exists() and not path.is_dir():
            raise InputError(f"{option}: is a file; give a folder", path)
        base = _existing_ancestor(path, option)
        try:  # a folder made and removed: access() says yes to root on read-only and virtual file systems (/proc)
            Path(tempfile.mkdtemp(prefix=".rgbd-gt-probe-", dir=base)).rmdir()
        except OSError as exc:
            raise InputError(f"{option}: cannot write in {base} ({exc.strerror or exc})", path) from None
        return base

    def _stage(self, base: Path) -> Path:
        stage = base / f".rgbd-gt-{uuid.uuid4().hex[:12]}"
        self._stage_dirs.append(stage)
        return stage

    def file(self, path: str | os.PathLike, option: str, suffixes: Sequence[str] | None = None) -> Path:
        """Check an output file; returns where to write it now (same name, in a staging folder).

        suffixes: the file names it may end with (lower case, with the dot), None for any.
        """
        path = Path(path)
        base = self._check(path, option, folder=False)
        if suffixes is not None and path.suffix.lower() not in suffixes:
            raise InputError(f"{option}: must end with {' or '.join(suffixes)}", path)
        stage = self._stage(base) / path.name
        self.staged.append((stage, path, False))
        return stage

    def folder(self, path: str | os.PathLike, option: str, whole: bool = False) -> Path:
        """Check an output folder; returns an empty staging folder whose files go into it at commit
        (beside what the folder already holds; a file of the same name is replaced). whole: each
        folder at the staging folder's top replaces the one of its name wholesale, so that nothing
        of an earlier run's folder stays among the new files (a data set's photos)."""
        path = Path(path)
        stage = self._stage(self._check(path, option, folder=True)) / (path.name or "out")
        self.staged.append((stage, path, True))
        if whole:
            self._whole.add(stage)
        return stage

    def checked_folder(self, path: str | os.PathLike | None, option: str) -> Path | None:
        """Check a folder the command writes into itself (a cache, atomically by its own means):
        nothing is staged. None (the option not given) passes."""
        if path is None:
            return None
        self._check(Path(path), option, folder=True)
        return Path(path)

    def commit(self) -> None:
        """Move every staged output to its target."""
        try:
            for stage, target, is_folder in self.staged:
                if is_folder:
                    target.mkdir(parents=True, exist_ok=True)
                    if stage in self._whole:
                        for src in sorted(stage.iterdir()):
                            _replace_whole(src, target / src.name)
                        continue
                    for src in sorted(stage.rglob("*")):
                        dst = target / src.relative_to(stage)
                        if src.is_dir():
                            dst.mkdir(exist_ok=True)
                        else:
                            os.replace(src, dst)
                elif stage.exists():  # an optional output that was not made stays absent
                    target.parent.mkdir(parents=True, exist_ok=True)
                    os.replace(stage, target)
        finally:
            self.discard()

    def discard(self) -> None:
        """Remove every staged output (the targets are untouched)."""
        for d in self._stage_dirs:
            shutil.rmtree(d, ignore_errors=True)
        self._stage_dirs = []

    def __enter__(self) -> "Outputs":
        for stage, _, is_folder in self.staged:
            (stage if is_folder else stage.parent).mkdir(parents=True, exist_ok=True)
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.commit()
        else:
            self.discard()


def _replace_whole(src: Path, dst: Path) -> None:
    """Move src to dst, whatever dst held: an old folder is set aside first and removed after."""
    old = None
    if dst.is_dir() and not dst.is_symlink():
        old = dst.with_name(f".rgbd-gt-old-{uuid.uuid4().hex[:12]}")
        os.replace(dst, old)
    elif dst.exists() and src.is_dir():
        dst.unlink()
    os.replace(src, dst)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def hold_folder(path: Path, option: str):
    """Take the folder `path` (made if missing) for this process: an exclusive advisory lock on
    its `.run.lock`, held while the returned file object stays open (at the latest, until the
    process ends). A second run on the same output folder is refused rather than computing and
    writing the same photos beside the first."""
    import fcntl

    path.mkdir(parents=True, exist_ok=True)
    f = open(path / ".run.lock", "a+")
    try:
        fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        f.seek(0)
        pid = f.read().strip() or "unknown"
        f.close()
        raise InputError(f"{option}: another rgbd-gt run (pid {pid}) is writing this folder: wait for it to end, "
                         "or give another output", path) from None
    except OSError:  # a file system without locks (some network mounts): run unguarded, as before there were any
        return f
    f.truncate(0)
    f.write(f"{os.getpid()}\n")
    f.flush()
    return f
