"""The demo beside other work (issue 45): ``skinlayers demo`` alone, beside one and beside two busy
processes, with the thread policy (``--threads auto``) and with torch's own default (two threads on two
cores, what the demo did before the policy), side by side in one run.

A busy process is a Python loop that never sleeps (one core's worth). Each row is appended to
``threads.csv`` as soon as it is measured and a rerun skips the rows already there, so the benchmark can
run in the background and be resumed. ``SKINLAYERS_BENCH_SIZES`` (default ``64``) picks the demo sizes,
e.g. ``64,256``; ``SKINLAYERS_BENCH_RUNS`` (default: every one) the runs, as ``busy:policy`` pairs, e.g.
``0:auto,0:torch default,1:auto``; ``SKINLAYERS_BENCH_WARM=0`` skips the untimed first demo that fills
the table cache.

    pytest -m bench tests/bench/test_bench_threads.py -s
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
from bench_io import append_rows, done_keys, out_dir

pytestmark = pytest.mark.bench

#: The thread settings compared: the policy, torch's default on this machine (as before the policy), and one
#: thread (alone, the floor of any run beside a busy process on two cores).
POLICIES = {"auto": "auto", "torch default": str(len(os.sched_getaffinity(0))), "one thread": "1"}
BUSY = (0, 1, 2)
_BUSY_LOOP = "while True: pass"
FIELDS = ["size", "busy", "policy", "threads_said", "wall_s"]


def _demo(size: int, threads: str, folder: Path) -> tuple[float, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "SKINLAYERS_THREADS")}
    start = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "skinlayers", "demo", "--size", str(size), "--threads", threads,
                           "-o", str(folder)], capture_output=True, text=True, env=env)
    wall = time.perf_counter() - start
    assert proc.returncode == 0, proc.stderr[-2000:]
    said = next((line.split(":", 1)[1].strip() for line in (proc.stdout + proc.stderr).splitlines()
                 if line.startswith("threads:")), "")
    return wall, said


def test_demo_beside_busy_processes(tmp_path):
    path = out_dir() / "threads.csv"
    done = done_keys(path, ("size", "busy", "policy"))
    sizes = [int(s) for s in os.environ.get("SKINLAYERS_BENCH_SIZES", "64").split(",")]
    runs = os.environ.get("SKINLAYERS_BENCH_RUNS")
    chosen = {tuple(r.split(":", 1)) for r in runs.split(",")} if runs else None
    for size in sizes:
        if os.environ.get("SKINLAYERS_BENCH_WARM", "1") != "0":
            _demo(size, "1", tmp_path / f"warm-{size}")  # tables built once, outside the timings
        for busy in BUSY:
            for name, threads in POLICIES.items():
                if (str(size), str(busy), name) in done or (chosen is not None and (str(busy), name) not in chosen):
                    continue
                loops = [subprocess.Popen([sys.executable, "-c", _BUSY_LOOP]) for _ in range(busy)]
                try:
                    time.sleep(0.5 if busy else 0.0)
                    wall, said = _demo(size, threads, tmp_path / f"d-{size}-{busy}-{threads}")
                finally:
                    for p in loops:
                        p.kill()
                        p.wait()
                append_rows(path, FIELDS, [{"size": size, "busy": busy, "policy": name, "threads_said": said, "wall_s": round(wall, 1)}])
