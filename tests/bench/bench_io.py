"""Where the benchmarks write (``bench_results/``, or ``$SKINLAYERS_BENCH_DIR``) and how: one CSV writer.

Importable from every benchmark as ``bench_io`` (``tests/bench/conftest.py`` puts this folder on the path).
"""

from __future__ import annotations

import csv
import os
from pathlib import Path

__all__ = ["out_dir", "write_csv"]


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
