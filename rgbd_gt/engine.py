"""Where `rgbd-gt run` does its work: in this process, in local worker processes (--workers N)
or as tasks on a Ray cluster (--ray auto|ADDRESS). Each scan is prepared once (the on-disk cache
beside the outputs, `prepared.py`), then every photo is one task that maps it. All engines run
the same steps into the same files (`workflow.run_photo`), so a run stopped on one resumes on
another."""

from __future__ import annotations

import os
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from rgbd_gt.errors import InputError
from rgbd_gt.heap import keep_freed_memory
from rgbd_gt.threads import size_thread_pools
from rgbd_gt.workflow import PhotoResult, RunConfig, ScanJob

CACHE_FOLDER = ".scan-cache"  # under the run's output folder: beside the outputs it serves


@dataclass
class PhotoTask:
    """One photo's steps: everything a worker needs, as plain picklable data."""

    photo: Path
    job: ScanJob
    prepared: Path  # the prepared scan's cache folder
    camera: object
    cfg: RunConfig
    export_failed: bool = False
    threads: int | None = None  # torch threads in this task (None: as configured)


@dataclass
class Prepared:
    """A scan's preparation: its cache folder, or why it failed; seconds it took."""

    job: ScanJob
    folder: Path | None = None
    error: str = ""
    unreadable: bool = False  # the error is the scan's own (unreadable, empty, non-finite): bad input of the run
    seconds: float = 0.0
    cached: bool = False
    points: int = 0
    steps: dict[str, float] = field(default_factory=dict)
    scan_key: dict | None = None  # the scan file's `file_key` as prepared


def prepare_job(job: ScanJob, cache_root: Path, progress: Callable[[str], None] = lambda m: None) -> Prepared:
    """Prepare a scan (or reopen its cache) and find its board when a photo still needs an
    initial pose; an InputError becomes the result's error (`unreadable` when the scan's own)."""
    from rgbd_gt.prepared import prepare_scan
    from rgbd_gt.steps import board_in_prepared
    from rgbd_gt.workflow import board_corners, board_spec

    start = time.perf_counter()
    out = Prepared(job)
    try:
        before = {p.name for p in cache_root.glob("*")} if cache_root.exists() else set()
        try:
            prepared = prepare_scan(job.scan, cache_root, progress)
        except InputError:
            out.unreadable = True
            raise
        out.cached = prepared.folder.name in before
        out.folder, out.points, out.scan_key = prepared.folder, len(prepared), prepared.key
        out.steps["scan"] = round(time.perf_counter() - start, 3)
        # a bundle's photos have their inits in the bundle file
        if job.init is None and job.bundle is None and any(not (job.out / p.stem / "init.yaml").exists() for p in job.photos):
            progress("finding the board")
            t = time.perf_counter()
            board_in_prepared(prepared, board_spec(job.board), board_corners(job.board))
            out.steps["board"] = round(time.perf_counter() - t, 3)
    except InputError as exc:
        out.error = str(exc)
    out.seconds = time.perf_counter() - start
    return out


@dataclass
class Rig:
    """A rig's joint solve in a run (`workflow.solve_rig`): its frames (job names), the verdict,
    or the error that stopped it."""

    frames: list[str]
    verdict: str | None = None
    error: str = ""


def rig_first(jobs: list[ScanJob], cfg: RunConfig, camera, cache_root: Path, out: Path,
              on_prepared: Callable[[Prepared], None], progress: Callable[[str], None]) -> tuple[dict, Rig | None]:
    """For a site that may be one rig's frames (`workflow.not_a_rig` said nothing against it):
    every scan prepared here first (on_prepared each), then, when there are two or more and they
    are a rig (cfg.rig, or null and every scan a sweep), its pose solved over all of them before
    any photo's steps. Returns the jobs prepared (by name) and the rig (None: not one)."""
    from rgbd_gt.prepared import open_prepared
    from rgbd_gt.workflow import solve_rig

    ready = {}
    for job in jobs:
        ready[job.name] = prepare_job(job, cache_root, progress)
        on_prepared(ready[job.name])
    frames = [p for p in ready.values() if not p.error]
    scans = [open_prepared(p.folder, p.job.scan) for p in frames]
    if len(frames) < 2 or not (cfg.rig or all(s.is_sweep() for s in scans)):
        return ready, None
    rig = Rig([p.job.name for p in frames])
    try:
        rig.verdict = solve_rig([p.job for p in frames], scans, camera, cfg, out, progress)[1]["verdict"]
    except InputError as exc:  # no frame is solved alone instead: a single sweep fixes its pose poorly
        rig.error = str(exc)
    return ready, rig


def photo_task(task: PhotoTask, progress: Callable[[str], None] = lambda step: None) -> PhotoResult:
    """Run one photo's steps; bad input becomes a failed result, as in a local run."""
    from rgbd_gt.prepared import open_prepared
    from rgbd_gt.workflow import run_photo

    keep_freed_memory()  # a worker's or Ray task's process, as the CLI's (rgbd_gt/heap.py)
    if task.threads:
        import torch

        torch.set_num_threads(task.threads)
    try:
        prepared = open_prepared(task.prepared, task.job.scan)
        result = run_photo(task.photo, prepared, task.camera, task.job, task.cfg, progress, task.export_failed)
    except InputError as exc:
        result = PhotoResult(task.photo.name, status="failed", error=str(exc))
    result.scan = task.job.name
    return result


def failed(job: ScanJob, error: str) -> list[PhotoResult]:
    return [PhotoResult(p.name, status="failed", error=error, scan=job.name) for p in job.photos]


def run_local(tasks: list[PhotoTask], workers: int, on_result: Callable[[PhotoResult], None],
              on_step: Callable[[str], None]) -> list[PhotoResult]:
    """The tasks in this process (workers 1) or in `workers` local processes, in order."""
    if workers <= 1:
        results = []
        for t in tasks:
            results.append(photo_task(t, on_step))
            on_result(results[-1])
        return results
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    threads = max(1, (os.cpu_count() or 1) // workers)  # the cores shared out: no oversubscription
    with _thread_pools_of(threads), ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as pool:
        futures = [pool.submit(photo_task, PhotoTask(**{**t.__dict__, "threads": threads})) for t in tasks]
        results = []
        for f in futures:
            results.append(f.result())
            on_result(results[-1])
    return results


@contextmanager
def _thread_pools_of(threads: int):
    """Processes started inside size their OpenMP and BLAS pools to `threads` (unless the user
    set them), as Ray does for its tasks. With two workers on 2 cores, each with pools of 2
    threads whose idle threads spin, ten photos took 126 s instead of 94 s."""
    before = size_thread_pools(threads)
    try:
        yield
    finally:
        for k, v in before.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def check_ray_address(address: str) -> None:
    """InputError unless `address` is 'auto' or a HOST:PORT where something answers: Ray itself
    retries an unreachable address for minutes."""
    import socket

    if address == "auto":
        return
    host, _, port = address.split("://")[-1].rpartition(":")
    if not (port.isdigit() and 0 < int(port) < 65536):
        raise InputError(f"--ray {address!r}: give HOST:PORT of the cluster's head (a port 1-65535), or auto")
    try:
        socket.create_connection((host or "127.0.0.1", int(port)), timeout=10).close()
    except OSError as exc:
        raise InputError(f"--ray {address}: no Ray cluster answers there ({exc}); give HOST:PORT of its head, "
                         "or auto") from None


def connect_ray(address: str):
    """ray, connected to the cluster at `address` ('auto': the one running on this machine)."""
    try:
        import ray
    except ImportError:
        raise InputError("--ray needs the ray package (pip install ray)") from None
    import logging

    check_ray_address(address)
    try:
        ray.init(address=address, logging_level=logging.ERROR, log_to_driver=False, configure_logging=True)
    except (ConnectionError, RuntimeError, ValueError) as exc:
        raise InputError(f"--ray {address}: cannot connect to a Ray cluster ({str(exc).splitlines()[0]})") from None
    return ray


def run_ray(jobs: list[ScanJob], make_tasks: Callable[[Prepared], list[PhotoTask]], cache_root: Path, address: str,
            on_prepared: Callable[[Prepared], None], on_result: Callable[[PhotoResult], None]) -> list[PhotoResult]:
    """Every scan prepared by one Ray task, then every photo of it one task; the prepared scan is
    shared through the cache folder, which every node must see at the same path (docs/scale.md).
    Results in the order of the jobs' photos."""
    ray = connect_ray(address)
    try:
        # a worker that dies (a node lost) is retried on another; bad input is a result, not an error
        prepare = ray.remote(num_cpus=1, max_retries=2)(prepare_job)
        photo = ray.remote(num_cpus=1, max_retries=2)(photo_task)
        pending = {prepare.remote(job, cache_root): k for k, job in enumerate(jobs)}
        results: dict[tuple[int, int], PhotoResult] = {}
        index: dict = {}
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            ref = done[0]
            k = pending.pop(ref)
            value = ray.get(ref)
            if isinstance(value, Prepared):
                on_prepared(value)
                if value.error:
                    for j, r in enumerate(failed(value.job, value.error)):
                        results[(k, j)] = r
                        on_result(r)
                    continue
                for j, task in enumerate(make_tasks(value)):
                    ref = photo.remote(PhotoTask(**{**task.__dict__, "threads": 1}))
                    pending[ref] = k
                    index[ref] = j
            else:
                results[(k, index.pop(ref))] = value
                on_result(value)
        return [results[key] for key in sorted(results)]
    finally:
        ray.shutdown()
