"""Refusing work that cannot fit in memory before it starts, with the numbers and what to change.

A command that would need more memory than the machine has left ends in the kernel's OOM killer or in
an allocation traceback hours later; here each large piece of work estimates what it needs from its
sizes (``model.renderer.render_bytes``, the calibration's stacks, …) and ``require_memory`` refuses it
when the estimate exceeds what is available, naming both and the setting to change.
"""

from __future__ import annotations

import math
import os

from .errors import InputError

__all__ = ["ResourceError", "available_memory_bytes", "format_bytes", "memory_budget_bytes", "plan_budget_bytes", "require_memory"]

#: Work may take at most this share of the memory available when it starts (the rest: the process's
#: own tensors, the allocator's slack, other programs).
USABLE_SHARE = 0.8


class ResourceError(InputError):
    """Work that would not fit in this machine's memory; the message names what it needs and what to change."""


def available_memory_bytes(device=None) -> int | None:
    """Memory available for new work: on a CUDA device its free memory, else the system's
    ``MemAvailable`` (Linux) or free physical pages; None where neither is known."""
    if device is not None and getattr(device, "type", str(device)).startswith("cuda"):
        import torch  # noqa: PLC0415

        free, _ = torch.cuda.mem_get_info(device)
        return int(free)
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None


def memory_budget_bytes(device=None) -> float:
    """The budget a render may use: ``SKINLAYERS_MEMORY_BUDGET_MB`` if set, else the usable share of the
    memory available now; infinite where neither is known."""
    text = os.environ.get("SKINLAYERS_MEMORY_BUDGET_MB")
    if text:
        try:
            value = float(text)
        except ValueError:
            value = -1.0
        if not value > 0:
            raise InputError(f"SKINLAYERS_MEMORY_BUDGET_MB: a size in MB greater than 0, got {text!r}")
        return value * 2**20
    available = available_memory_bytes(device)
    return math.inf if available is None else USABLE_SHARE * available


def plan_budget_bytes(device=None) -> float:
    """What a command may plan to add. ``SKINLAYERS_MEMORY_BUDGET_MB`` caps the whole process: what it
    holds already comes off, and of the rest the usable share (a render's peak lies within about 10% of
    its estimate either way: docs/renderer.md), so a render planned under a budget stays under it. Else
    the usable share of the memory available now (``memory_budget_bytes``)."""
    budget = memory_budget_bytes(device)
    if not os.environ.get("SKINLAYERS_MEMORY_BUDGET_MB") or (device is not None and getattr(device, "type", str(device)).startswith("cuda")):
        return budget
    return max(USABLE_SHARE * (budget - _resident_bytes()), 0.0)


def _resident_bytes() -> int:
    """This process's resident memory (Linux), 0 where unknown."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError, AttributeError):
        return 0


def format_bytes(n: float) -> str:
    """``n`` bytes in MB, GB or TB, to three digits."""
    for unit, size in (("TB", 1 << 40), ("GB", 1 << 30), ("MB", 1 << 20)):
        if n >= size:
            return f"{n / size:.3g} {unit}"
    return f"{n / (1 << 20):.2g} MB"


def require_memory(need_bytes: float, what: str, advice: str, device=None) -> None:
    """``ResourceError`` when ``need_bytes`` exceeds the memory budget (``memory_budget_bytes``): the one
    budget a command's plan and every check inside it compare against."""
    budget = memory_budget_bytes(device)
    if need_bytes > budget:
        source = ("SKINLAYERS_MEMORY_BUDGET_MB" if os.environ.get("SKINLAYERS_MEMORY_BUDGET_MB")
                  else f"{USABLE_SHARE:.0%} of the {format_bytes(budget / USABLE_SHARE)} available here")
        raise ResourceError(
            f"{what} needs about {format_bytes(need_bytes)} of memory; the budget is {format_bytes(budget)} ({source}). {advice}"
        )
