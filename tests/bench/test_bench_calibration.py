"""Benchmark of the calibration (on demand: ``pytest -m bench tests/bench/test_bench_calibration.py -s``).

Calibrates one default-size simulated session — the default rig (nine bands, cube 256, rectify 512; the
1648×1184 sensor) and simulator, as ``skinlayers capture --sim`` makes it — several times and reports
where the time goes: the pipeline's stages (``calibration.json``'s ``timings_s``) and, inside the
window stage, the coarse outline, the derivative-peak edge points and the edge model. The session is
simulated first (about 2.5 min) unless ``SKINLAYERS_BENCH_SESSION`` names one to reuse.
``SKINLAYERS_BENCH_RUNS`` (default 3) sets the repetitions. Writes ``calibration_speed.csv`` to
``bench_results/`` (or ``$SKINLAYERS_BENCH_DIR``): per stage the median seconds over the runs and its
share of the total.
"""

from __future__ import annotations

import os
import platform
import statistics
import time
from pathlib import Path

import pytest
import torch

from skinlayers.calibration import CalibrationSettings, calibrate_session
from skinlayers.calibration import window as window_module

from bench_io import write_csv

pytestmark = pytest.mark.bench



def _session(tmp_path: Path) -> Path:
    given = os.environ.get("SKINLAYERS_BENCH_SESSION")
    if given:
        return Path(given)
    from skinlayers.acquire.session import AutoOperator, run_session
    from skinlayers.acquire.hardware.simdevices import SimulatedCamera, SimulatedWheel
    from skinlayers.acquire.simulator.simulated import SimulatedBench

    bench = SimulatedBench(seed=0, device="cpu")
    wheel = SimulatedWheel(bench.rig.wheel.position_count, time_scale=0.0)
    folder = tmp_path / "session"
    run_session(folder, bench.rig_as_used(), wheel, SimulatedCamera(bench, wheel), AutoOperator(bench.set_target), simulated=True)
    return folder


def test_calibration_speed(tmp_path, monkeypatch):
    session = _session(tmp_path)
    parts: dict[str, float] = {}

    def timed(name, fn):
        def wrapper(*args, **kwargs):
            start = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                parts[name] = parts.get(name, 0.0) + time.perf_counter() - start

        return wrapper

    # the window stage's parts, timed where find_window calls them
    monkeypatch.setattr(window_module, "_coarse_quad", timed("window: coarse outline", window_module._coarse_quad))
    monkeypatch.setattr(window_module, "_fit_sides", timed("window: edge points", window_module._fit_sides))
    monkeypatch.setattr(window_module, "fit_edge_line", timed("window: edge model", window_module.fit_edge_line))
    runs = int(os.environ.get("SKINLAYERS_BENCH_RUNS", "3"))
    stages: dict[str, list[float]] = {}
    for k in range(runs):
        parts.clear()
        result = calibrate_session(session, tmp_path / f"out{k}", CalibrationSettings())
        for name, seconds in {**result.timings_s, **parts}.items():
            stages.setdefault(name, []).append(seconds)
    total = statistics.median(stages["total"])
    rows = []
    for name, values in stages.items():
        seconds = statistics.median(values)
        rows.append({"stage": name, "median_s": round(seconds, 3), "min_s": round(min(values), 3),
                     "share": f"{seconds / total:.1%}", "runs": runs})
    cube = result.cube
    context = (f"{platform.processor() or platform.machine()}, torch threads {torch.get_num_threads()}, "
               f"OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')}; "
               f"{cube.shape[0]} bands, cube {cube.shape[1]}², session {session}")
    write_csv("calibration_speed.csv", rows, context)
    assert stages["total"] and all(v >= 0 for values in stages.values() for v in values)
    assert cube.shape == (9, 256, 256)
