"""The C heap of this process: freed blocks kept for their next use. Imports nothing heavy.

glibc's malloc maps every block over 32 MB afresh (smaller ones too, until its threshold has
adapted) and hands it back to the kernel when freed, so each of the aligner's big temporaries
(a level's windows over NID's bins: 19 KITTI frames x 3 poses x 2.8k points x 16 bins in
float64, 20-50 MB) is zeroed by the kernel page by page on first touch, at every evaluation.
KITTI's 19-frame joint solve on one thread: 3.9 million page faults and 9.4 s of system time
in 82 s; with the blocks kept, 0.3 million and 1.6 s. `rgbd-gt run` on those frames: solve
43 -> 33 s, peak memory 1.54 -> 1.41 GB, the pose the same to the bit (docs/lidar-method.md,
"The heap")."""

from __future__ import annotations

import ctypes
import sys

_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # glibc's malloc.h


def keep_freed_memory(largest: int = 128 << 20, kept: int = 256 << 20) -> bool:
    """Ask glibc's malloc to serve blocks up to `largest` bytes from its heap, and to keep up to
    `kept` bytes freed at the heap's top, for this process (and the processes it forks). Blocks
    larger than that (a 40-million-point scan's arrays) are mapped and returned as before.
    Returns whether it was set: False where the C library is not glibc (nothing changes)."""
    if sys.platform != "linux":
        return False
    libc = ctypes.CDLL(None)
    if not hasattr(libc, "gnu_get_libc_version"):  # musl has a mallopt that does nothing
        return False
    return bool(libc.mallopt(_M_MMAP_THRESHOLD, largest)) and bool(libc.mallopt(_M_TRIM_THRESHOLD, kept))
