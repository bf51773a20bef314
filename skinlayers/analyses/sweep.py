"""The machinery the analyses share: a table of measured cases written row by row and resumed, the
progress with an estimate of the time left, the peak memory of a step, and the Pareto front.

``SweepTable`` owns one CSV: a fixed list of columns, a key (the columns that name a case), the rows
already measured. ``run`` measures only the cases whose key is not there yet and appends each row as
soon as it is measured, so an interrupted analysis continues where it stopped.
"""

from __future__ import annotations

import csv
import io
import math
import os
import resource
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Sequence

from ..formats.errors import InputError
from ..formats.files import atomic_write

__all__ = ["AnalysisResult", "PeakMemory", "SweepTable", "analysis_device", "cell_text", "echo_outputs", "pareto_front", "time_to_front"]

#: How often the peak-memory sampler reads the resident set (s).
SAMPLE_S = 0.005


class SweepTable:
    """The CSV at ``path`` with ``columns`` (in order), a case named by the values of ``key`` columns.

    A file whose header is not ``columns`` is refused (``InputError``: a table of another analysis or
    version): the user names a fresh folder or removes the file."""

    def __init__(self, path: str | Path, columns: Sequence[str], key: Sequence[str]) -> None:
        self.path, self.columns, self.key = Path(path), list(columns), list(key)
        missing = [k for k in self.key if k not in self.columns]
        if missing:
            raise ValueError(f"key columns {missing} are not columns of the table")
        self.rows: list[dict] = []
        if self.path.exists() and self.path.stat().st_size:
            with self.path.open(newline="") as f:
                reader = csv.DictReader(f)
                if reader.fieldnames != self.columns:
                    raise InputError(f"{self.path}: its columns are not this analysis's ({reader.fieldnames} against "
                                     f"{self.columns}); write into a new folder or remove the file")
                self.rows = list(reader)

    def key_of(self, row: dict) -> tuple[str, ...]:
        return tuple(cell_text(row.get(k)) for k in self.key)

    def done(self) -> set[tuple[str, ...]]:
        return {self.key_of(r) for r in self.rows}

    def append(self, row: dict) -> None:
        """Write ``row`` (unknown keys refused, missing ones empty) and keep it, as the file reads it back."""
        unknown = set(row) - set(self.columns)
        if unknown:
            raise ValueError(f"row has columns the table does not: {sorted(unknown)}")
        new = not self.path.exists() or not self.path.stat().st_size
        self.path.parent.mkdir(parents=True, exist_ok=True)
        text = {c: cell_text(row.get(c)) for c in self.columns}
        with self.path.open("a", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=self.columns)
            if new:
                writer.writeheader()
            writer.writerow(text)
            f.flush()
            os.fsync(f.fileno())
        self.rows.append(text)

    def rewrite(self) -> None:
        """Write every kept row again (after the caller changed them), atomically: never half a table."""
        buffer = io.StringIO()
        writer = csv.DictWriter(buffer, fieldnames=self.columns)
        writer.writeheader()
        writer.writerows({c: cell_text(r.get(c)) for c in self.columns} for r in self.rows)
        atomic_write(self.path, buffer.getvalue().encode())

    def run(self, cases: Iterable[dict], measure: Callable[[dict], dict], *, say: Callable[[str], None] | None = None,
            estimate_s: Callable[[dict], float] | None = None) -> "SweepProgress":
        """Measure each case (a dict holding at least the key columns) not yet in the table: ``measure(case)``
        returns the row's other columns. Progress and the time left go to ``say`` (stderr by default)."""
        todo = [c for c in cases if self.key_of(c) not in self.done()]
        progress = SweepProgress(len(todo), estimate_s, say or _stderr, self.key)
        for case in todo:
            progress.starting(case)
            start = time.perf_counter()
            row = {**case, **measure(case)}
            self.append(row)
            progress.finished(case, time.perf_counter() - start, todo)
        return progress


@dataclass
class SweepProgress:
    """Cases done of ``total``, seconds spent, and the estimate of what is left (the remaining cases'
    ``estimate_s`` scaled by how the measured cases ran against theirs; their mean without one)."""

    total: int
    estimate_s: Callable[[dict], float] | None
    say: Callable[[str], None]
    key: Sequence[str] = ()
    done: int = 0
    spent_s: float = 0.0
    estimated_done_s: float = 0.0

    def starting(self, case: dict) -> None:
        self.say(f"[{self.done + 1}/{self.total}] {_label({k: case[k] for k in self.key} if self.key else case)} …")

    def finished(self, case: dict, seconds: float, todo: list[dict]) -> None:
        self.done += 1
        self.spent_s += seconds
        left_cases = todo[self.done:]
        if self.estimate_s is not None:
            self.estimated_done_s += self.estimate_s(case)
            ratio = self.spent_s / self.estimated_done_s if self.estimated_done_s > 0 else 1.0
            left = ratio * sum(self.estimate_s(c) for c in left_cases)
        else:
            left = self.spent_s / self.done * len(left_cases)
        self.say(f"    {seconds:.1f} s; {self.done}/{self.total} done, about {_duration(left)} left")


def _label(case: dict) -> str:
    return ", ".join(str(v) for v in case.values() if v not in (None, ""))


def _duration(seconds: float) -> str:
    return f"{seconds:.0f} s" if seconds < 90 else f"{seconds / 60:.1f} min"


def _stderr(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def cell_text(value) -> str:
    """A value as the CSV holds it (and as it reads back): floats to 6 significant digits."""
    if value is None:
        return ""
    if isinstance(value, bool):
        return str(value)
    if isinstance(value, float):
        return "nan" if math.isnan(value) else f"{value:.6g}"
    return str(value)


# -- peak memory ------------------------------------------------------------------------------------------


def _rss_mb() -> float | None:
    """This process's resident set now (MB), where the system says (Linux's /proc)."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError, IndexError):
        return None


class PeakMemory:
    """The peak resident memory a block adds over what the process held when it started (MB), sampled
    every ``SAMPLE_S`` by a thread (torch's kernels release the GIL); where the resident set cannot be
    read, the growth of the process's lifetime peak (0 when the block stays under an earlier peak).
    On CUDA, ``torch.cuda.max_memory_allocated`` over the block is the device's (``device_mb``)."""

    def __init__(self, device: str = "cpu") -> None:
        self.device = device
        self.peak_mb = 0.0
        self.device_mb: float | None = None

    def __enter__(self) -> "PeakMemory":
        self._base = _rss_mb()
        self._base_max = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        self._top = self._base or 0.0
        self._stop = threading.Event()
        if self._base is not None:
            self._thread = threading.Thread(target=self._sample, daemon=True)
            self._thread.start()
        if self.device.startswith("cuda"):
            import torch  # noqa: PLC0415

            torch.cuda.reset_peak_memory_stats()
        return self

    def _sample(self) -> None:
        while not self._stop.wait(SAMPLE_S):
            now = _rss_mb()
            if now is not None and now > self._top:
                self._top = now

    def __exit__(self, *exc) -> None:
        self._stop.set()
        if self._base is not None:
            self._thread.join()
            now = _rss_mb() or 0.0
            self.peak_mb = max(self._top, now) - self._base
        else:
            self.peak_mb = max(0.0, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 - self._base_max)
        if self.device.startswith("cuda"):
            import torch  # noqa: PLC0415

            self.device_mb = torch.cuda.max_memory_allocated() / 2**20


# -- the Pareto front --------------------------------------------------------------------------------------


def pareto_front(cost: Sequence[float], error: Sequence[float]) -> list[bool]:
    """Which points no other point dominates, both ``cost`` and ``error`` to be small: a point is
    dominated by one at most as costly and at most as wrong, better in at least one. Equal points are
    all on the front; a point with a non-finite value is not."""
    pts = list(zip(cost, error))
    finite = [math.isfinite(c) and math.isfinite(e) for c, e in pts]
    out = []
    for i, (c, e) in enumerate(pts):
        if not finite[i]:
            out.append(False)
            continue
        out.append(not any(finite[j] and c2 <= c and e2 <= e and (c2 < c or e2 < e) for j, (c2, e2) in enumerate(pts)))
    return out


def time_to_front(cost: Sequence[float], error: Sequence[float], i: int) -> float:
    """How much longer point ``i`` takes than the fastest point at most as wrong (1: it is that point or
    as fast; 1.1: 10% slower than the front at its error)."""
    fastest = min(c for c, e in zip(cost, error) if math.isfinite(c) and math.isfinite(e) and e <= error[i])
    return cost[i] / fastest


# -- the commands' shared rules -----------------------------------------------------------------------------


def analysis_device(device: str) -> str:
    """An analysis command's ``--device``: cpu, cuda or auto (CUDA when there is one); anything else, or cuda
    where there is none, is the user's error (``InputError``)."""
    import torch  # noqa: PLC0415

    if device not in ("cpu", "cuda", "auto"):
        raise InputError(f"--device {device!r}: expected cpu, cuda or auto")
    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if device == "cuda" and not torch.cuda.is_available():
        raise InputError("--device cuda: no CUDA device here; use cpu or auto")
    return device


def echo_outputs(table: Path, summary: Path, charts: Sequence[Path], seconds: float) -> None:
    """Where an analysis wrote its table, summary and charts, and how long it took (stdout)."""
    print(f"table: {table}\nsummary: {summary}")
    for path in charts:
        print(f"chart: {path}")
    print(f"{seconds:.0f} s")


@dataclass
class AnalysisResult:
    """What an analysis wrote (its table, its summary file, its charts), the summary itself and its time."""

    table: Path
    summary_path: Path
    charts: list[Path]
    summary: dict = field(default_factory=dict)
    seconds: float = 0.0
