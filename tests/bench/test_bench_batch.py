"""A study's throughput (issue 20): sessions an hour against Dask workers (1, 2) on this machine, and the
per-task overhead of Dask against a plain loop over the same sessions, side by side in one run.

``SKINLAYERS_BENCH_BATCH_SESSIONS`` (default 4) simulated sessions of the demo's scene at 64² (the default
rig's nine bands), made and calibrated once in ``bench_results/batch_sessions/``; each run then fits them
all afresh (``--steps reconstruct``; their ``_reconstruction`` folders removed first), one torch thread a
task as the batch runs them:

- ``loop``: ``process_session`` for each session in turn, in this process (no Dask);
- ``dask``: ``run_batch`` on ``skinlayers.studies.batch.local_cluster`` of 1 and of 2 worker processes. The cluster's start and
  the workers' first imports (``startup_s``) are timed apart: a study pays them once.

Dask's per-task overhead is the wall time of the one-worker run not spent inside the tasks, a task, and
its share of one 64² reconstruction (the loop's median task). The first task of a fresh worker process
also pays its imports and table loads (``first_task_s`` against ``later_task_median_s``): a study pays
that once a worker, not once a task. Rows are appended to ``batch.csv`` as they are measured.

    pytest -m bench tests/bench/test_bench_batch.py -s
"""

from __future__ import annotations

import os
import shutil
import statistics
import time
from pathlib import Path

import pytest
from bench_io import append_rows, out_dir

pytestmark = pytest.mark.bench

FIELDS = ["mode", "workers", "sessions", "startup_s", "wall_s", "sessions_per_hour", "first_task_s", "later_task_median_s",
          "dask_overhead_per_task_s", "overhead_share"]
SIZE = 64


def _sessions(count: int) -> Path:
    """``count`` simulated, calibrated 64² sessions (made once)."""
    import yaml

    from skinlayers.calibration import calibrate_session
    from skinlayers.demo import simulate_session
    from skinlayers.analyses.truths import demo_scene, session_rig
    from skinlayers.formats.cube import calibrated_dir

    folder = out_dir() / "batch_sessions"
    scene = folder / "scene.yaml"
    folder.mkdir(parents=True, exist_ok=True)
    scene.write_text(yaml.safe_dump(demo_scene()))
    for seed in range(count):
        session = folder / "study" / f"s{seed}"
        if not (session / "manifest.json").is_file():
            shutil.rmtree(session, ignore_errors=True)
            simulate_session(session, session_rig(SIZE), scene, seed, device="cpu")
        if not (calibrated_dir(session) / "calibration.json").is_file():
            calibrate_session(session, calibrated_dir(session))
    return folder / "study"


def _fresh(sessions) -> None:
    from skinlayers.studies.batch import reconstruction_dir

    for s in sessions:
        shutil.rmtree(reconstruction_dir(s.path), ignore_errors=True)


def _row(mode: str, workers: int, startup_s: float, wall_s: float, outcomes) -> dict:
    """A run's row: its wall time and rate, its first task's time and the later ones' median (the first
    task of a fresh process pays its imports and table loads: a study pays that once a worker)."""
    seconds = [o.seconds for o in outcomes]
    row = {"mode": mode, "workers": workers, "sessions": len(seconds), "startup_s": round(startup_s, 2), "wall_s": round(wall_s, 2),
           "sessions_per_hour": round(3600 * len(seconds) / wall_s, 1), "first_task_s": round(seconds[0], 2),
           "later_task_median_s": round(statistics.median(seconds[1:]), 2)}
    if workers == 1:  # Dask's own cost: the wall time not spent inside the tasks, a task
        row["dask_overhead_per_task_s"] = round((wall_s - sum(seconds)) / len(seconds), 3)
    return row


def test_batch_throughput_against_workers():
    from distributed import Client

    from skinlayers.studies.batch import BatchOptions, local_cluster, process_session, read_study, run_batch
    from skinlayers.formats.threads import use_threads, choose_threads

    count = int(os.environ.get("SKINLAYERS_BENCH_BATCH_SESSIONS", "4"))
    sessions = read_study(_sessions(count))
    options = BatchOptions(steps=("reconstruct",), device="cpu")
    rows = []
    _fresh(sessions)
    start = time.perf_counter()
    outcomes = [process_session(s, options) for s in sessions]
    rows.append(_row("loop", 1, 0.0, time.perf_counter() - start, outcomes))
    use_threads(choose_threads(2))
    assert all(o.status == "done" for o in outcomes), [o.error for o in outcomes]
    for workers in (1, 2):
        _fresh(sessions)
        start = time.perf_counter()
        with local_cluster(workers) as cluster, Client(cluster) as client:
            client.run(lambda: __import__("skinlayers.reconstruct.mapfit.fit"))  # the workers' first imports, as a study pays once
            startup = time.perf_counter() - start
            start = time.perf_counter()
            result = run_batch(sessions, options, out_dir() / "batch_study", client=client)
            rows.append(_row("dask", workers, startup, time.perf_counter() - start, list(result.outcomes.values())))
        assert result.count("done") == count, [o.error for o in result.outcomes.values()]
    loop_task_s = rows[0]["later_task_median_s"]
    for row in rows:
        if "dask_overhead_per_task_s" in row and row["mode"] == "dask":
            row["overhead_share"] = round(row["dask_overhead_per_task_s"] / loop_task_s, 4)
    append_rows(out_dir() / "batch.csv", FIELDS, rows)


def _wait_for(path: Path, what: str, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not path.is_file():
        if time.monotonic() > deadline:
            raise TimeoutError(f"{what} did not start within {timeout_s:.0f} s")
        time.sleep(0.2)


def test_a_hand_started_worker_runs_at_a_plain_process_speed(tmp_path):
    """Issue 58: a 64² session through ``batch --scheduler`` on a ``dask worker`` started by hand (with the
    nanny's ``MALLOC_TRIM_THRESHOLD_=65536``, as Dask leaves it) against a plain ``skinlayers reconstruct``,
    one thread each, side by side; rows ``hand_worker`` and ``plain`` in ``batch.csv`` (``wall_s``: the
    command's or the batch's wall time, imports included on both sides)."""
    import subprocess
    import sys

    from distributed import Client

    from skinlayers.studies.batch import BatchOptions, read_study, run_batch

    sessions = read_study(_sessions(1))[:1]
    dask = [sys.executable, "-m"]
    scheduler_file = tmp_path / "scheduler.json"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    procs = [subprocess.Popen([*dask, "distributed.cli.dask_scheduler", "--scheduler-file", str(scheduler_file),
                               "--no-dashboard"], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    rows = []
    try:
        _wait_for(scheduler_file, "dask scheduler")
        procs.append(subprocess.Popen([*dask, "distributed.cli.dask_worker", "--scheduler-file", str(scheduler_file),
                                       "--nthreads", "1", "--nworkers", "1", "--no-dashboard"], env=env,
                                      stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        with Client(scheduler_file=str(scheduler_file), timeout="60s") as client:
            client.wait_for_workers(1, timeout=60)
            nanny_env = client.run(lambda: os.environ.get("MALLOC_TRIM_THRESHOLD_"))
            _fresh(sessions)
            start = time.perf_counter()
            result = run_batch(sessions, BatchOptions(steps=("reconstruct",), device="cpu"), tmp_path / "study", client=client)
            rows.append({"mode": "hand_worker", "workers": 1, "sessions": 1, "wall_s": round(time.perf_counter() - start, 2),
                         "first_task_s": round(result.outcomes[sessions[0].name].seconds, 2)})
        assert result.count("done") == 1, [o.error for o in result.outcomes.values()]
        assert set(nanny_env.values()) == {"65536"}, nanny_env  # the worker runs with the setting it is measured against
    finally:
        for p in reversed(procs):
            p.terminate()
            p.wait(timeout=30)
    _fresh(sessions)
    start = time.perf_counter()
    subprocess.run([sys.executable, "-m", "skinlayers", "reconstruct", str(sessions[0].path), "--threads", "1", "--device", "cpu"],
                   check=True, capture_output=True)
    rows.append({"mode": "plain", "workers": 1, "sessions": 1, "wall_s": round(time.perf_counter() - start, 2)})
    rows[0]["overhead_share"] = round(rows[0]["wall_s"] / rows[1]["wall_s"] - 1.0, 4)
    append_rows(out_dir() / "batch.csv", FIELDS, rows)
    print(rows)
