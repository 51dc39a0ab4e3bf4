"""Benchmarks: the paper's ICL-NUIM experiment (Sec. 4.1) and its baselines."""

import os
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as the CLI runs (rgbd_gt/cli.py says why)

from rgbd_gt.heap import keep_freed_memory  # noqa: E402

keep_freed_memory()  # as the CLI runs (rgbd_gt/heap.py)


def write_keeping(path: Path, text: str, marker: str = "\n## ") -> None:
    """Write a benchmark's document (atomically), keeping what a person wrote below it in the
    file there: everything from the first `marker` line on."""
    from rgbd_gt.io import atomic_output

    kept = path.read_text() if path.exists() else ""
    kept = kept[kept.find(marker):] if marker in kept else ""
    with atomic_output(path) as tmp:
        tmp.write_text(text + kept)
