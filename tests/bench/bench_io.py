"""Where the benchmarks write (``bench_results/``, or ``$SKINLAYERS_BENCH_DIR``) and how: one CSV writer.

Importable from every benchmark as ``bench_io`` (``tests/bench/conftest.py`` puts this folder on the path).
"""

from __future__ import annotations

import csv
import os
from pathlib import Path

__all__ = ["append_rows", "done_keys", "out_dir", "write_csv"]


def out_dir() -> Path:
    """The benchmarks' output folder (created)."""
    folder = Path(os.environ.get("SKINLAYERS_BENCH_DIR", "bench_results"))
    folder.mkdir(parents=True, exist_ok=True)
    return folder


def write_csv(name: str, rows: list[dict], context: str = "") -> Path:
    """Write ``rows`` as ``name`` in ``out_dir()`` (columns: every key, in order of first appearance) and
    print them, after ``context`` if given."""
    path = out_dir() / name
    keys = list(dict.fromkeys(k for row in rows for k in row))
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=keys)
        writer.writeheader()
        writer.writerows(rows)
    print(f"\n{path}" + (f" ({context})" if context else "") + ":")
    for row in rows:
        print("  " + ", ".join(f"{k}={v}" for k, v in row.items()))
    return path


def append_rows(path: Path, fields: list[str], rows: list[dict]) -> None:
    """Append ``rows`` to the CSV at ``path`` (its header first when new) and print them: a benchmark that
    writes row by row can be stopped and resumed."""
    new = not path.exists()
    with path.open("a", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=fields)
        if new:
            writer.writeheader()
        writer.writerows(rows)
    for row in rows:
        print("  " + ", ".join(f"{k}={v}" for k, v in row.items()), flush=True)


def done_keys(path: Path, key: tuple[str, ...]) -> set[tuple[str, ...]]:
    """The ``key`` columns' values of every row already in the CSV at ``path`` (empty when there is none)."""
    if not path.exists():
        return set()
    with path.open() as f:
        return {tuple(r[k] for k in key) for r in csv.DictReader(f)}

