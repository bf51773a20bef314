"""Benchmark: the whole pipeline on skin rendered by transport against skin rendered by diffusion
(run on demand: ``pytest -m bench tests/bench/test_transport_session.py -s``).

``skinlayers demo --size 32`` twice with the same seed, scene and rig: once with the simulator's
diffusion truth (the fit's own physics, at higher fidelity), once with ``--physics transport`` (the
Monte Carlo reference, ``SKINLAYERS_SESSION_PHOTONS`` photons per wavelength node, default 200,000).
The fit's error against the truth maps in the second is what the fit's physics costs on skin it did not
make, plus the Monte Carlo's own noise (written beside it). Writes ``transport_session.csv``
(``bench_io``): per physics and parameter the median error, the truth's and the fit's medians, the
residual and the cube's noise, the truth's median standard error, the time per band and the photons
per cube pixel.
"""

from __future__ import annotations

import json
import os
import statistics

import pytest
from typer.testing import CliRunner

from bench_io import out_dir, write_csv  # noqa: E402 (tests/bench/conftest.py puts it on the path)

from skinlayers.cli import app

pytestmark = pytest.mark.bench

PHOTONS = int(os.environ.get("SKINLAYERS_SESSION_PHOTONS", 200_000))
SIZE = 32


def test_the_pipeline_on_transport_truth_against_diffusion_truth():
    rows = []
    for physics in ("diffusion", "transport"):
        folder = out_dir() / f"transport_session_{physics}"
        args = ["demo", "--size", str(SIZE), "--out", str(folder), "--device", "cpu", "--physics", physics]
        result = CliRunner().invoke(app, args + (["--photons", str(PHOTONS)] if physics == "transport" else []))
        assert result.exit_code == 0, (result.output, result.exception)
        accuracy = json.loads((folder / "accuracy.json").read_text())
        truth = json.loads((folder / "session" / "truth" / "simulation.json").read_text())["truth_physics"]
        common = {"physics": physics, "residual_rms": round(accuracy["residual_rms"], 5),
                  "cube_noise_rms": round(accuracy.get("cube_noise_rms", float("nan")), 5),
                  "capture_s": accuracy["times_s"]["capture_s"], "reconstruct_s": accuracy["times_s"]["reconstruct_s"]}
        if physics == "transport":
            seconds = list(truth["seconds_per_band"].values())
            common.update(photons_per_node=PHOTONS, photons_per_cube_pixel_per_node=round(PHOTONS / SIZE**2, 1),
                          truth_std_error_median=round(statistics.median(truth["std_error_median_per_band"].values()), 5),
                          seconds_per_band_median=round(statistics.median(seconds), 1), seconds_per_band_max=round(max(seconds), 1))
        for name, p in accuracy["parameters"].items():
            rows.append({"parameter": name, "median_error": round(p["median_error"], 4), "error_kind": p["error_kind"],
                         "truth_median": p["truth_median"], "fit_median": p["fit_median"], **common})
    write_csv("transport_session.csv", rows, f"{PHOTONS:,} photons per node, {SIZE}² cube")
    assert all(r["median_error"] >= 0 for r in rows)
