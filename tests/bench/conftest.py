"""The benchmarks' shared helpers live in ``bench_io.py`` beside them; this folder goes on the import path
so that every benchmark imports the one copy (the test folders are not packages)."""

from __future__ import annotations

import sys
from pathlib import Path

_HERE = str(Path(__file__).resolve().parent)
if _HERE not in sys.path:
    sys.path.insert(0, _HERE)
