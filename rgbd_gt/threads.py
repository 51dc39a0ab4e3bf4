"""The size of the OpenMP and BLAS thread pools, said through the environment: these pools are
made when a library loads, so only the environment reaches them. Imports nothing heavy, so that
it can run before numpy or torch loads (tests/conftest.py)."""

from __future__ import annotations

import os

POOLS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def size_thread_pools(threads: int) -> dict[str, str | None]:
    """Ask for pools of `threads` threads in this process's environment, where the user has not
    set a size. Returns each variable's value before (None: unset), to put back."""
    before = {k: os.environ.get(k) for k in POOLS}
    for k in POOLS:
        os.environ.setdefault(k, str(threads))
    return before
