"""How many threads torch (and OpenCV) take for CPU work: one policy for every heavy command and the library.

Torch's CPU kernels split each operation over its intra-op threads and wait for the slowest. When a
core is busy with another program, the thread the kernel put there waits its turn, and every operation
waits with it: beside a busy process, threads on the busy core cost far more than they gain alone
(measured: docs/speed.md, "Threads"). So the policy takes the cores this process may use (its CPU affinity and a container's CPU quota) and, of
those, the ones that are idle now (sampled from ``/proc/stat``), at least one.

``SKINLAYERS_THREADS`` (a number, or ``auto``) sets the policy for the library and the commands;
``--threads N`` on a command overrides it. Without either, library calls leave torch's setting as the
caller made it, and the commands use ``auto``.
"""

from __future__ import annotations

import logging
import math
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import torch

from .errors import InputError

__all__ = ["THREADS_ENV", "THREADS_HELP", "ThreadChoice", "choose_threads", "command_threads", "idle_cpus",
           "library_threads", "usable_cpus", "use_threads"]

log = logging.getLogger(__name__)

THREADS_ENV = "SKINLAYERS_THREADS"
#: How long ``/proc/stat`` is watched to tell idle cores from busy ones (s): long enough for the
#: kernel's 100 Hz accounting to see a busy core, short beside any heavy command.
SAMPLE_S = 0.2
#: A core counts as free when at least this share of it was idle over the sample.
IDLE_SHARE = 0.5
#: The choice this process applied last (``use_threads``), None before any.
_applied: "ThreadChoice | None" = None


@dataclass(frozen=True)
class ThreadChoice:
    """The threads chosen and why (printed by the commands, kept in their records)."""

    threads: int
    usable_cpus: int
    idle_cpus: float | None
    reason: str

    def describe(self) -> str:
        return f"{self.threads} thread(s): {self.reason}"


def usable_cpus() -> int:
    """The cores this process may run on: its CPU affinity, capped by a cgroup CPU quota."""
    try:
        cpus = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        cpus = os.cpu_count() or 1
    quota = _cgroup_quota()
    return max(1, min(cpus, math.floor(quota)) if quota is not None else cpus)


def _cgroup_quota() -> float | None:
    """CPUs a cgroup (v2 ``cpu.max``, v1 ``cpu.cfs_quota_us``) allows this process; None when unlimited."""
    try:
        text = Path("/sys/fs/cgroup/cpu.max").read_text().split()
        if text and text[0] != "max":
            return max(int(text[0]) / int(text[1]), 1.0)
    except (OSError, ValueError, IndexError):
        pass
    try:
        quota = int(Path("/sys/fs/cgroup/cpu/cpu.cfs_quota_us").read_text())
        period = int(Path("/sys/fs/cgroup/cpu/cpu.cfs_period_us").read_text())
        if quota > 0 and period > 0:
            return max(quota / period, 1.0)
    except (OSError, ValueError):
        pass
    return None


def _cpu_times() -> dict[int, tuple[int, int]]:
    """Per core: (idle ticks, total ticks) from ``/proc/stat``."""
    times = {}
    with open("/proc/stat") as f:
        for line in f:
            if line.startswith("cpu") and line[3].isdigit():
                name, *fields = line.split()
                values = [int(v) for v in fields[:8]]
                times[int(name[3:])] = (values[3] + values[4], sum(values))
    return times


def idle_cpus(sample_s: float = SAMPLE_S) -> float | None:
    """How many of this process's cores were idle over the last ``sample_s`` seconds (each core counted
    when at least ``IDLE_SHARE`` of it was idle); None where ``/proc/stat`` cannot be read."""
    try:
        mine = os.sched_getaffinity(0)
        before = _cpu_times()
        time.sleep(sample_s)
        after = _cpu_times()
    except (AttributeError, OSError, ValueError, IndexError):
        return None
    free = 0
    for cpu in mine:
        if cpu in before and cpu in after:
            total = after[cpu][1] - before[cpu][1]
            idle = after[cpu][0] - before[cpu][0]
            free += total > 0 and idle / total >= IDLE_SHARE
    return float(free)


def _parse(value: str, source: str) -> int | None:
    """A thread count from ``value``: a whole number ≥ 1, or ``auto`` (None)."""
    text = str(value).strip().lower()
    if text in ("", "auto"):
        return None
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        raise InputError(f"{source}: threads must be a whole number of at least 1, or auto; got {value!r}")
    return n


def choose_threads(requested: int | str | None = None) -> ThreadChoice:
    """The policy: ``requested`` (``--threads``), else ``SKINLAYERS_THREADS``, else ``auto``: the usable
    cores that are idle now, at least one."""
    cpus = usable_cpus()
    asked = _parse(requested, "--threads") if requested is not None else None
    if asked is not None:
        return ThreadChoice(asked, cpus, None, "as asked (--threads)")
    env = os.environ.get(THREADS_ENV)
    from_env = _parse(env, THREADS_ENV) if requested is None and env is not None else None
    if from_env is not None:
        return ThreadChoice(from_env, cpus, None, f"as asked ({THREADS_ENV}={env})")
    free = idle_cpus()
    if free is None:
        return ThreadChoice(cpus, cpus, None, f"{cpus} usable core(s); their load is unknown here")
    n = max(1, min(cpus, int(free)))
    return ThreadChoice(n, cpus, free, f"{int(free)} of {cpus} usable core(s) idle")


def use_threads(choice: ThreadChoice) -> ThreadChoice:
    """Give torch (and OpenCV, when loaded) the chosen number of threads; the process keeps the choice
    (``library_threads`` then leaves it as it is)."""
    global _applied
    _applied = choice
    torch.set_num_threads(choice.threads)
    cv2 = sys.modules.get("cv2")
    if cv2 is not None:
        cv2.setNumThreads(choice.threads)
    return choice


#: The help of every heavy command's ``--threads``.
THREADS_HELP = (f"Torch threads: a number, or auto (default; or ${THREADS_ENV}): the usable cores idle now, "
                "at least one. A busy core makes every thread wait: docs/speed.md, \"Threads\".")


def command_threads(requested: str | None) -> ThreadChoice:
    """A heavy command's threads: chosen by the policy, given to torch and logged (``skinlayers -v``;
    the demo and reconstruct print them)."""
    choice = use_threads(choose_threads(requested))
    log.info("threads: %s", choice.describe())
    return choice


def library_threads() -> ThreadChoice | None:
    """At a library entry point (``fit_cube``, ``calibrate_session``): where ``SKINLAYERS_THREADS`` is set,
    the choice already made in this process (a command's ``--threads``, a batch task's), else the policy
    applied now; where it is not set, nothing changes (torch's setting stays as the caller made it)."""
    if os.environ.get(THREADS_ENV) is None:
        return None
    return _applied if _applied is not None else use_threads(choose_threads())
