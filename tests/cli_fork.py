"""A Python that has done the CLI's heavy imports once (torch, open3d, OpenCV: about 2 s of every
command on the CI machine) and forks one child per `rgbd-gt` call of the tests. Each child is a
process of its own, as `python -c "from rgbd_gt.cli import main; main()" ARGS` would be: its own
working folder, environment, stdin from /dev/null, stdout and stderr (file descriptors 1 and 2, so
what libraries print from C lands there too), exit code. What a fresh process alone shows (noise
printed while importing) is left to the tests that start one (test_fuzz, test_cli's help test).

Protocol: one JSON request a line on stdin ({"args", "cwd", "env", "out", "err"}), one JSON
answer a line on stdout ({"returncode"}). Run as `python tests/cli_fork.py`."""

from __future__ import annotations

import json
import os
import sys


def _child(req: dict) -> None:
    """In the forked child: become the command's process and run it; never returns."""
    code = 1
    try:
        os.chdir(req["cwd"])
        os.environ.clear()
        os.environ.update(req["env"])
        for fd, path, flags in ((0, os.devnull, os.O_RDONLY), (1, req["out"], os.O_WRONLY | os.O_CREAT | os.O_TRUNC),
                                (2, req["err"], os.O_WRONLY | os.O_CREAT | os.O_TRUNC)):
            f = os.open(path, flags, 0o644)
            os.dup2(f, fd)
            os.close(f)
        sys.argv = ["-c", *req["args"]]
        sys.path[0] = ""  # as `python -c` has it: the working folder, not this file's
        from rgbd_gt.cli import main

        main()  # ends the process itself, sys.exit's codes included (`cli._end`)
        code = 0
    except Exception:  # noqa: BLE001 - an uncaught exception: its traceback, exit 1
        sys.excepthook(*sys.exc_info())
    finally:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):
                pass
        os._exit(code)


def _threads() -> int:
    return len(os.listdir("/proc/self/task"))


def serve() -> None:
    # numpy's and OpenCV's OpenBLAS start their worker threads on import; OpenBLAS stops and
    # restarts them around a fork (pthread_atfork), so they are safe to fork with
    import cv2  # noqa: F401
    import numpy  # noqa: F401

    blas = _threads()
    import open3d  # noqa: F401 - the imports every child would otherwise repeat
    import torch  # noqa: F401

    import rgbd_gt.align.refine  # noqa: F401
    import rgbd_gt.cli  # noqa: F401
    import rgbd_gt.steps  # noqa: F401

    # any other thread's locks would be copied in whatever state they are in
    if _threads() != blas:
        raise SystemExit(f"cli_fork: {_threads() - blas} threads started by the imports; a fork would copy their locks")
    answers = sys.stdout
    for line in sys.stdin:
        req = json.loads(line)
        answers.flush()
        pid = os.fork()
        if pid == 0:
            _child(req)
        _, status = os.waitpid(pid, 0)
        answers.write(json.dumps({"returncode": os.waitstatus_to_exitcode(status)}) + "\n")
        answers.flush()


if __name__ == "__main__":
    serve()
