"""Benchmarks of the map fit (on demand: ``pytest -m bench tests/bench/test_bench_reconstruct.py -s``).

Each fit runs in a fresh process (``reconstruct_run.py``) so that its peak memory is its own; times
are process CPU seconds (robust to the other load on a shared machine) beside wall seconds. Writes to
``bench_results/`` (or ``$SKINLAYERS_BENCH_DIR``):

- ``reconstruct_methods.csv``: every optimiser on the same patch, grid and model (no pyramid, every map
  per pixel, the scale free: the paper's problem, so all see the same one): CPU time and renders to convergence, the residual reached, and the CPU time each took
  to reach the paper-style baseline's final loss;
- ``reconstruct_sizes.csv``: the default fit (coarse-to-fine from 64²) against patch size, 64² to
  256² (512² with ``SKINLAYERS_BENCH_512=1``), with peak memory and accuracy.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from bench_io import out_dir, write_csv

pytestmark = pytest.mark.bench

HERE = Path(__file__).resolve().parent



def run(cfg: dict, timeout: int = 7200) -> dict:
    cfg = {"cube_cache": str(out_dir() / "cubes"), "threads": 1, **cfg}
    proc = subprocess.run([sys.executable, str(HERE / "reconstruct_run.py"), json.dumps(cfg)], capture_output=True,
                          text=True, timeout=timeout)
    if proc.returncode != 0:
        raise RuntimeError(proc.stderr[-2000:])
    return json.loads(proc.stdout.strip().splitlines()[-1])



def _time_to(history: list, loss: float) -> float | None:
    """CPU seconds from the fit's start until its loss first fell to ``loss`` (None: never)."""
    for t, value, _ in history:
        if value <= loss:
            return t
    return None


def test_methods_side_by_side():
    """All optimisers on one 32² patch (Fitzpatrick IV), the grid fixed (no pyramid), paper's start
    and the homogeneous start for the default method."""
    base = {"size": 32, "preset": "IV exterior", "noise": 0.5, "truth_blur": "fft"}
    # the paper's problem for every method: every map per pixel, the scale free, no robust refit
    paper_model = {"map_cell_mm": dict.fromkeys(("C_m", "beta_m", "C_he", "C_bc", "C_hd"), 0.0), "free_scale": True, "robust_passes": 0}
    runs = [
        ("paper-fd", "paper"), ("adam", "homogeneous"), ("gn", "homogeneous"),
        ("gn-hom", "paper"), ("gn-hom", "homogeneous"),
    ]
    results = {}
    for method, start in runs:
        results[(method, start)] = run({**base, "settings": {"method": method, "start": start, "coarsest_px": 0, **paper_model}})
    target = results[("paper-fd", "paper")]["history"][-1][1]
    rows = []
    for (method, start), r in results.items():
        reach = _time_to(r["history"], target)
        rows.append({
            "method": method, "start": start, "cpu_s": round(r["cpu_s"], 2), "wall_s": round(r["wall_s"], 2),
            "forward": r["renders"]["forward"], "backward": r["renders"]["backward"],
            "iterations": r["levels"][0][1], "converged": r["levels"][0][2],
            "residual_rms": r["residual_rms"], "noise_rms": r["noise_rms"], "scale": r["scale"],
            "cpu_s_to_baseline_loss": reach, **{f"err_{k}": v for k, v in r["errors"].items()},
            "peak_rss_mb": round(r["peak_rss_mb"]),
        })
    write_csv("reconstruct_methods.csv", rows)
    for row in rows:
        print(row)
    ours = next(r for r in rows if r["method"] == "gn-hom" and r["start"] == "homogeneous")
    paper = next(r for r in rows if r["method"] == "paper-fd")
    assert ours["residual_rms"] <= paper["residual_rms"] * 1.001
    assert ours["cpu_s_to_baseline_loss"] is not None and ours["cpu_s_to_baseline_loss"] < paper["cpu_s"]


def test_time_against_patch_size():
    sizes = [64, 128, 256] + ([512] if os.environ.get("SKINLAYERS_BENCH_512") else [])
    rows = []
    for size in sizes:
        r = run({"size": size, "preset": "IV exterior", "noise": 1.0, "truth_blur": "fft" if size <= 64 else "pyramid"})
        rows.append({
            "size": size, "cpu_s": round(r["cpu_s"], 1), "wall_s": round(r["wall_s"], 1),
            "levels": json.dumps(r["levels"]), "forward": r["renders"]["forward"],
            "residual_rms": r["residual_rms"], "noise_rms": r["noise_rms"], "scale": r["scale"],
            "peak_rss_mb": round(r["peak_rss_mb"]), **{f"err_{k}": v for k, v in r["errors"].items()},
        })
        print(rows[-1])
    write_csv("reconstruct_sizes.csv", rows)
    assert all(r["residual_rms"] <= 1.2 * r["noise_rms"] for r in rows)
