import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from rgbd_gt.heap import keep_freed_memory
from rgbd_gt.threads import size_thread_pools

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("RGBD_GT_DATA", ROOT.parent / "shared" / "data"))


def _share_the_cores() -> None:
    """Under pytest-xdist (`make test` runs `-n auto`) each worker, and the commands it starts,
    gets its share of the cores: pools of every core in every worker spin against each other
    (the same reason as `engine._thread_pools_of`). Set before anything imports torch or numpy."""
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    if workers > 1:
        size_thread_pools(max(1, (os.cpu_count() or 1) // workers))


_share_the_cores()
keep_freed_memory()  # as the CLI runs (rgbd_gt/heap.py)


def _need(sub: str) -> Path:
    path = DATA / sub
    if not path.exists():
        pytest.skip(f"real test data not found at {path} (the shared data folder beside the repo)")
    return path


@pytest.fixture
def e57_dir() -> Path:
    return _need("e57")


@pytest.fixture
def icl_dir() -> Path:
    return _need("icl_nuim_livingroom1")


@pytest.fixture
def checkerboard_dir() -> Path:
    return _need("checkerboard")


def _made_once(tmp_path_factory, name: str, make) -> Path:
    """A folder that `make(folder)` fills, made once for the whole suite: under pytest-xdist each
    worker has a session of its own, and each made the same scenes and rig solves again (a
    minute of the suite's time on 2 cores). The first worker to ask makes it under a file lock;
    the others wait for it and read it. Nothing may change it afterwards."""
    from filelock import FileLock

    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent  # the run's folder, which all its workers share
    folder = root / "made-once" / name
    folder.parent.mkdir(exist_ok=True)
    with FileLock(f"{folder}.lock"):
        if not (folder / ".done").exists():  # a worker that died midway left no .done
            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir()
            make(folder)
            (folder / ".done").touch()
    return folder


@pytest.fixture(scope="session")
def synth_scene(tmp_path_factory):
    """synth_scene(dest, seed, photos=1, rig=None) -> dest: a copy of the small synthetic scene of
    that seed (with rig 'stereo': `photos` shots of a stereo rig), made once (about 3 s each), so
    that a test may change its files."""

    def make(folder: Path, seed: int, photos: int, rig: str | None) -> None:
        proc = run_cli("synth", folder, "--size", "small", "--seed", seed, "--photos", photos, *(["--rig", rig] if rig else []))
        assert proc.returncode == 0, proc.stderr

    def copy(dest: Path, seed: int, photos: int = 1, rig: str | None = None) -> Path:
        src = _made_once(tmp_path_factory, f"synth{seed}x{photos}{rig or ''}", lambda f: make(f, seed, photos, rig))
        shutil.copytree(src, dest, dirs_exist_ok=True, ignore=shutil.ignore_patterns(".done"))
        return dest

    return copy


@pytest.fixture(scope="session")
def rig_run(synth_scene, tmp_path_factory):
    """A stereo rig's 2 shots (small synthetic scene, seed 0) solved together by `refine --bundle`:
    (scene folder, output folder). Shared by every test that asks: read it, do not change it."""

    def make(folder: Path) -> None:
        d = synth_scene(folder / "scene", 0, photos=2, rig="stereo")
        proc = run_cli("refine", "--bundle", d / "bundle.yaml", "-o", folder / "out", "--device", "cpu", "--repeats", "1")
        assert proc.returncode == 0, proc.stderr + proc.stdout

    folder = _made_once(tmp_path_factory, "rig", make)
    return folder / "scene", folder / "out"


_ZYGOTE: list = []  # the cli_fork server of this session, once started


def _zygote() -> subprocess.Popen | None:
    """The session's `tests/cli_fork.py` server (started on first use), or None where it cannot
    run (no fork) or RGBD_GT_TESTS_FRESH=1 asks for a fresh interpreter per call."""
    if os.environ.get("RGBD_GT_TESTS_FRESH") == "1" or not hasattr(os, "fork"):
        return None
    if not _ZYGOTE or _ZYGOTE[0].poll() is not None:
        _ZYGOTE[:] = [subprocess.Popen([sys.executable, str(ROOT / "tests" / "cli_fork.py")], stdin=subprocess.PIPE,
                                       stdout=subprocess.PIPE, text=True, cwd=ROOT)]
    return _ZYGOTE[0]


def run_cli(*args, cwd=None, timeout: float = 600, fresh: bool = False) -> subprocess.CompletedProcess:
    """Run the real `rgbd-gt` entry point in a process of its own (exit codes and stderr as a user
    sees them): a child forked from a Python that has the heavy imports done (tests/cli_fork.py),
    or with fresh (or RGBD_GT_TESTS_FRESH=1) a fresh interpreter, which shows what importing prints."""
    import json
    import select
    import tempfile

    argv = [sys.executable, "-c", "from rgbd_gt.cli import main; main()", *map(str, args)]
    server = None if fresh else _zygote()
    if server is None:
        return subprocess.run(argv, capture_output=True, text=True, cwd=cwd, timeout=timeout)
    with tempfile.TemporaryDirectory() as tmp:
        req = {"args": argv[3:], "cwd": str(cwd or os.getcwd()), "env": dict(os.environ),
               "out": f"{tmp}/stdout", "err": f"{tmp}/stderr"}
        server.stdin.write(json.dumps(req) + "\n")
        server.stdin.flush()
        ready, _, _ = select.select([server.stdout], [], [], timeout)
        if not ready:  # the call ran past its time: a fresh server for the next call
            server.kill()
            raise subprocess.TimeoutExpired(argv, timeout)
        line = server.stdout.readline()
        if not line:
            raise RuntimeError(f"tests/cli_fork.py ended (exit code {server.wait()}): its stderr says why")
        read = lambda name: Path(tmp, name).read_text() if Path(tmp, name).exists() else ""  # noqa: E731
        return subprocess.CompletedProcess(argv, json.loads(line)["returncode"], read("stdout"), read("stderr"))


def assert_one_line_error(proc: subprocess.CompletedProcess, *needles: str) -> None:
    assert proc.returncode == 2, (proc.returncode, proc.stdout, proc.stderr)
    lines = [l for l in proc.stderr.splitlines() if l.strip()]
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("error: "), proc.stderr
    assert "Traceback" not in proc.stderr + proc.stdout
    for n in needles:
        assert n in lines[0], (n, lines[0])
