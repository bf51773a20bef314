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

__all__ = ["trim_heap_on_free"]

_M_TRIM_THRESHOLD = -1


def trim_heap_on_free() -> bool:
    """Ask glibc to return freed memory to the system at once; False where that is not glibc."""
    name = ctypes.util.find_library("c")
    if not name:
        return False
    try:
        libc = ctypes.CDLL(name)
        return bool(libc.mallopt(_M_TRIM_THRESHOLD, 0))
    except (OSError, AttributeError):
        return False
