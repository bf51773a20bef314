"""What the benchmarks share: where their CSV files go (``bench_results/``, or ``$SKINLAYERS_BENCH_DIR``)."""

from __future__ import annotations

import csv
import os
from pathlib import Path

import pytest


@pytest.fixture
def bench_csv():
    """``bench_csv(name, rows)``: write ``rows`` (dicts with the same keys) as CSV and print them."""

    def write(name: str, rows: list[dict]) -> Path:
        folder = Path(os.environ.get("SKINLAYERS_BENCH_DIR", "bench_results"))
        folder.mkdir(parents=True, exist_ok=True)
        path = folder / name
        with path.open("w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
        print(f"\n{path}:")
        for row in rows:
            print("  " + ", ".join(f"{k}={v}" for k, v in row.items()))
        return path

    return write
