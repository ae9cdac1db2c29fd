"""The training process keeps the memory it frees (glibc's malloc), for the next step to reuse.

A training step allocates and frees the same large temporaries every time: the dense anchor
targets (each sample's ``(ny * nx * anchors, 9)`` residuals and weights, stacked), the BEV maps
and their gradients, a few to a few tens of MB each. By default glibc serves an allocation above
its dynamic threshold (128 kB, raised to the largest freed one, at most 32 MB) by a fresh
``mmap`` and gives the top of the heap back to the system once more than twice that threshold is
free there, so each step touches new pages, and the kernel faults and zeroes every one of them
again. ``mallopt`` with a fixed 32 MB mmap threshold and a 1 GB trim threshold keeps those
allocations on the heap and the heap's pages in the process: the resident memory stays at the
step's peak (which it reaches every step anyway).

Only where the C library is glibc; elsewhere nothing changes.
"""
from __future__ import annotations

import ctypes
import ctypes.util

M_TRIM_THRESHOLD = -1      # glibc's malloc.h
M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD = 32 << 20  # glibc's largest (HEAP_MAX_SIZE / 2 on 64-bit)
TRIM_THRESHOLD = 1 << 30


def keep_freed_memory() -> bool:
    """Set glibc's mmap and trim thresholds as the module docstring says; whether it was set."""
    name = ctypes.util.find_library("c")
    try:
        mallopt = ctypes.CDLL(name).mallopt if name else None
    except (OSError, AttributeError):
        mallopt = None
    if mallopt is None:
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    return bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD))
