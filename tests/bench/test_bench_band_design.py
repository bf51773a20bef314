"""The chosen bands against the rig's own, through the whole pipeline (issue 19): ``design-bands`` with its
defaults for the rig the sessions are photographed with (the demo's rig at 64²), then simulated sessions
with each rig's bands (the demo's scene, the flash's power pinned to the current rig's so both are
photographed with the same flash), calibrated and fitted with the default settings, and each map's median
error against the simulation's truth — on seeds the search never saw (its prior is Table 2 with the
scene's spread; its model error is measured on the scene of seed 20), side by side in one run.

``SKINLAYERS_BENCH_DESIGN_SEEDS`` (default ``101,102``) picks the seeds, ``SKINLAYERS_BENCH_DESIGN_SIZE`` the
cube's side (default 64; 256 is the rig's own, four times the time); ``SKINLAYERS_BENCH_DESIGN_NOISE_ONLY=1``
designs from the camera's noise alone. Rows go to ``band_design.csv`` as they are measured (a rerun skips
the rig, bands and seed there).

    pytest -m bench tests/bench/test_bench_band_design.py -s
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import yaml
from bench_io import append_rows, done_keys, out_dir

pytestmark = pytest.mark.bench

FIELDS = ["rig", "bands_nm", "seed", "C_m", "beta_m", "C_he", "C_bc", "C_hd", "residual_rms", "size"]
SIZE = int(os.environ.get("SKINLAYERS_BENCH_DESIGN_SIZE", "64"))


def _session_errors(folder: Path, rig_path: Path | None, simulation: Path, seed: int) -> dict:
    from skinlayers.acquire.hardware.rig import load_rig
    from skinlayers.calibration import calibrate_session
    from skinlayers.demo import accuracy_against_truth, simulate_session
    from skinlayers.analyses.truths import MIN_RECTIFY_PX, demo_scene
    from skinlayers.reconstruct import load_fit_settings, reconstruct_cube

    rig = load_rig(rig_path, geometry={"cube_px": SIZE, "rectify_px": max(2 * SIZE, MIN_RECTIFY_PX)}, camera={"driver": "simulated"})
    scene = folder / "scene.yaml"
    folder.mkdir(parents=True, exist_ok=True)
    scene.write_text(yaml.safe_dump(demo_scene()))
    simulate_session(folder / "session", rig, scene, seed, device="cpu", simulation=simulation)
    calibrate_session(folder / "session", folder / "calibrated")
    reconstruct_cube(folder / "calibrated" / "cube.exr", folder / "reconstruction", load_fit_settings(None), device="cpu")
    accuracy = accuracy_against_truth(folder / "session", folder / "reconstruction", folder / "calibrated" / "cube.exr")
    row = {name: round(p["median_error"], 5) for name, p in accuracy["parameters"].items()}
    return {**row, "residual_rms": round(accuracy["residual_rms"], 5), "bands_nm": " ".join(f"{b.wavelength_nm:g}" for b in rig.bands)}


def test_chosen_bands_against_the_rigs_through_the_pipeline(tmp_path):
    from skinlayers.acquire.hardware.rig import load_rig
    from skinlayers.acquire.simulator.simulation_settings import load_simulation_settings
    from skinlayers.analyses.band_design import Radiometry, default_catalogue, design_bands, write_design
    from skinlayers.analyses.truths import session_rig

    base = out_dir() / "band_design"
    rig = session_rig(SIZE)
    design = design_bands(default_catalogue(), 9, rig, model_error=os.environ.get("SKINLAYERS_BENCH_DESIGN_NOISE_ONLY") != "1")
    paths = write_design(design, base / "design", rig, force=True)
    settings = load_simulation_settings(None).model_dump(mode="json")
    settings["sensor"]["white_electrons"] = float(Radiometry().white_electrons)  # the current rig's flash for both
    simulation = base / "simulation.yaml"
    simulation.write_text(yaml.safe_dump(settings, sort_keys=False))
    table = out_dir() / "band_design.csv"
    done = {(rig_name, bands, seed) for rig_name, bands, seed, size in done_keys(table, ("rig", "bands_nm", "seed", "size"))
            if int(size or 64) == SIZE}
    seeds = [int(s) for s in os.environ.get("SKINLAYERS_BENCH_DESIGN_SEEDS", "101,102").split(",")]
    for seed in seeds:
        for name, rig_path in (("current", None), ("chosen", paths["rig"])):
            bands = rig.bands if rig_path is None else load_rig(rig_path).bands
            if (name, " ".join(f"{b.wavelength_nm:g}" for b in bands), str(seed)) in done:
                continue
            row = {"rig": name, "seed": seed, "size": SIZE, **_session_errors(tmp_path / f"{name}-{seed}", rig_path, simulation, seed)}
            append_rows(table, FIELDS, [row])
    assert load_rig(paths["rig"]).bands  # the written rig loads
