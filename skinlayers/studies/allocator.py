"""The memory allocator a task needs, set by the task itself, however its worker was started.

glibc's malloc serves a large block from the heap or maps it anew (``mmap``), by a threshold it raises
by itself: after a mapped block of up to 32 MiB is freed, blocks of that size come from the heap, whose
top is trimmed only beyond twice that. A fit allocates and frees tensors of a few MiB thousands of
times, so with that dynamic threshold they are reused from the heap. Setting ``MALLOC_TRIM_THRESHOLD_``
(or any of glibc's malloc thresholds) in the environment turns the dynamic threshold off for the whole
process: Dask's nanny starts every worker with ``MALLOC_TRIM_THRESHOLD_=65536``, and then every tensor
above 128 KiB is mapped and unmapped anew, page faults and all, which doubled a 64² fit (docs/batch.md,
"Workers started outside skinlayers").

``use_task_allocator`` sets the thresholds, through glibc's ``mallopt``, to where the dynamic scheme
settles for such work (mapping from 32 MiB, trimming beyond 64 MiB) wherever the environment had
fixed them; elsewhere (a plain process, another C library) it changes nothing.
"""

from __future__ import annotations

import os

from ..model.render.memory import M_MMAP_THRESHOLD, M_TRIM_THRESHOLD, glibc

__all__ = ["FIXED_BY_ENVIRONMENT", "MMAP_THRESHOLD_BYTES", "TRIM_THRESHOLD_BYTES", "use_task_allocator"]

#: The top of glibc's dynamic mmap threshold on 64-bit (``DEFAULT_MMAP_THRESHOLD_MAX``: 4 MiB × sizeof(long)),
#: and the trim threshold the dynamic scheme pairs with it (twice the mmap threshold).
MMAP_THRESHOLD_BYTES = 32 * 1024 * 1024
TRIM_THRESHOLD_BYTES = 2 * MMAP_THRESHOLD_BYTES
#: Environment variables with which glibc fixes its thresholds (and stops adjusting them) at start.
FIXED_BY_ENVIRONMENT = ("MALLOC_TRIM_THRESHOLD_", "MALLOC_MMAP_THRESHOLD_", "MALLOC_TOP_PAD_", "MALLOC_MMAP_MAX_")
#: The same settings as ``GLIBC_TUNABLES`` (``glibc.malloc.<name>=…``).
_FIXING_TUNABLES = ("trim_threshold", "mmap_threshold", "top_pad", "mmap_max")


def use_task_allocator(environ: dict[str, str] | None = None) -> bool:
    """Where the environment fixed glibc's malloc thresholds (``FIXED_BY_ENVIRONMENT``, or their ``GLIBC_TUNABLES``), set them to
    ``MMAP_THRESHOLD_BYTES`` and ``TRIM_THRESHOLD_BYTES`` for this process. Returns whether it did."""
    environ = os.environ if environ is None else environ
    tunables = environ.get("GLIBC_TUNABLES", "")
    if not any(name in environ for name in FIXED_BY_ENVIRONMENT) and not any(
            f"glibc.malloc.{t}" in tunables for t in _FIXING_TUNABLES):
        return False
    libc = glibc()
    if libc is None:
        return False
    return bool(libc.mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)) and bool(
        libc.mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES))
