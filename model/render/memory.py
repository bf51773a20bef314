"""Process memory hygiene for large renders.

Rendering allocates and frees many image-sized temporaries. glibc's allocator keeps freed heap
memory for reuse and raises its mmap threshold dynamically, so the resident size of a long
differentiable render grows with fragmentation far beyond the tensors alive. Trimming costs time —
returned pages are faulted in again — so it is a choice for memory-bound runs, not a default (both
measured: docs/renderer.md, "Speed and memory").
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys

__all__ = ["M_MMAP_THRESHOLD", "M_TRIM_THRESHOLD", "glibc", "trim_heap_on_free"]

#: glibc's ``mallopt`` parameters (malloc.h).
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3


def glibc():
    """The C library when it is glibc on Linux (it has ``mallopt``), else None."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    except OSError:
        return None
    return libc if hasattr(libc, "mallopt") else None


def trim_heap_on_free() -> bool:
    """Ask glibc to return freed memory to the system at once; False where that is not glibc."""
    libc = glibc()
    return libc is not None and bool(libc.mallopt(M_TRIM_THRESHOLD, 0))
