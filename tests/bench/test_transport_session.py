"""Benchmark: sessions whose skin the Monte Carlo rendered, calibrated and fitted with each model
(run on demand: ``pytest -m bench tests/bench/test_transport_session.py -s``).

For each of ``SEEDS`` (seeds no default was tuned on), a 32² session (``SKINLAYERS_SESSION_SIZE``)
of the demo's scene (smooth variation, ten freckles, a scar, a vein; no hairs) is captured by the
simulated rig with ``truth.physics: transport`` (``SKINLAYERS_SESSION_PHOTONS`` photons per
wavelength node, default 150,000, and as many for the homogeneous twin's kernel), calibrated once,
and reconstructed twice: with the fit's model on ``profiles: diffusion`` (DWRR08's) and on
``profiles: transport``. The error of each against the truth maps is what the fit's physics costs on
light it did not make. Writes ``transport_session.csv`` (``bench_io``): per seed, model and
parameter the median error, the truth's and the fit's medians, the median σ; the residual, the
cube's noise against its truth, the truth's own Monte Carlo standard error, the capture's and the
fit's seconds. ``SKINLAYERS_SESSION_REUSE=1`` keeps sessions already captured in the output folder
(only the fits rerun).
"""

from __future__ import annotations

import json
import os
import statistics
import time

import pytest
import torch
import yaml

from bench_io import out_dir, write_csv

from skinlayers.acquire.hardware.rig import load_rig
from skinlayers.calibration import calibrate_session
from skinlayers.demo import accuracy_against_truth, simulate_session
from skinlayers.analyses.truths import MIN_RECTIFY_PX, demo_scene
from skinlayers.formats.cube import CUBE_NAME
from skinlayers.reconstruct import load_fit_settings, reconstruct_cube

pytestmark = pytest.mark.bench

PHOTONS = int(os.environ.get("SKINLAYERS_SESSION_PHOTONS", 150_000))
SEEDS = tuple(int(s) for s in os.environ.get("SKINLAYERS_SESSION_SEEDS", "21,22,23").split(","))
#: The cube's side (``SKINLAYERS_SESSION_SIZE``): 32 by default; the Monte Carlo's time hardly
#: depends on it (the photons are per wavelength node), its noise per pixel grows with it.
SIZE = int(os.environ.get("SKINLAYERS_SESSION_SIZE", 32))
#: The fit's model, each way: the ``model:`` overrides of the fit settings.
MODELS = {"diffusion": {"profiles": "diffusion"}, "transport": {"profiles": "transport"}}


def _folder(seed: int):
    """A seed's session folder in the output folder (sizes other than 32 keep their own)."""
    return out_dir() / (f"transport_session_{seed}" + ("" if SIZE == 32 else f"_{SIZE}px"))


def _csv(name: str) -> str:
    """A CSV's name, with the size unless it is 32 (the published tables)."""
    return name if SIZE == 32 else name.replace(".csv", f"_{SIZE}px.csv")


def _rig():
    """The rig at the sessions' cube size, its camera simulated (as ``skinlayers demo --size`` makes it)."""
    return load_rig(geometry={"cube_px": SIZE, "rectify_px": max(2 * SIZE, MIN_RECTIFY_PX)}, camera={"driver": "simulated"})


def _session(folder, seed: int) -> dict:
    """Capture (unless kept) and calibrate one transport session; its truth's record and the seconds."""
    session, calibrated = folder / "session", folder / "calibrated"
    seconds = {}
    if not (os.environ.get("SKINLAYERS_SESSION_REUSE") and (calibrated / CUBE_NAME).exists()):
        folder.mkdir(parents=True, exist_ok=True)
        rig = _rig()
        scene = folder / "scene.yaml"
        scene.write_text(yaml.safe_dump(demo_scene(), sort_keys=False))
        start = time.perf_counter()
        simulate_session(session, rig, scene, seed, "cpu", {"physics": "transport", "photons": PHOTONS})
        seconds["capture_s"] = round(time.perf_counter() - start, 1)
        calibrate_session(session, calibrated)
    truth = json.loads((session / "truth" / "simulation.json").read_text())["truth_physics"]
    return {"truth": truth, **seconds}


def _kept(seed: int):
    """A session captured by the first test (skip if absent): its folder, calibrated cube and scene."""
    from skinlayers.acquire.simulator.scene import scene_from_dict
    from skinlayers.formats.cube import read_cube

    folder = _folder(seed)
    if not (folder / "calibrated" / CUBE_NAME).exists():
        pytest.skip(f"{folder}: run test_sessions_rendered_by_transport_fitted_with_each_model first")
    return folder, read_cube(folder / "calibrated" / CUBE_NAME), scene_from_dict(yaml.safe_load((folder / "scene.yaml").read_text()))


def _own_render(rig, scene, seed: int, overrides: dict) -> torch.Tensor:
    """The model's own render of the truth maps (the simulator's diffusion path with these model settings)."""
    from skinlayers.acquire.simulator.simulated import SimulatedBench
    from skinlayers.model.settings import ModelSettings

    return SimulatedBench(rig, scene, seed=seed, model_settings=ModelSettings(**overrides), device="cpu").truth_reflectance().float()


def _fit(folder, cube_path, name: str, settings) -> dict:
    """Fit ``cube_path`` into ``folder / name`` with ``settings``: its accuracy against the session's truth."""
    reconstruction = folder / name
    reconstruct_cube(cube_path, reconstruction, settings, device="cpu", force=True)
    return accuracy_against_truth(folder / "session", reconstruction, cube_path)


def _map_rows(accuracy: dict, keys: dict) -> list[dict]:
    """A row per map: ``keys``, the median error, the fit's median over the truth's, the residual."""
    return [{**keys, "parameter": name, "median_error": round(p["median_error"], 4),
             "fit_over_truth_median": round(p["fit_median"] / p["truth_median"], 4) if name != "beta_m" else "",
             "residual_rms": round(accuracy["residual_rms"], 5)} for name, p in accuracy["parameters"].items()]


def test_sessions_rendered_by_transport_fitted_with_each_model():
    rows = []
    for seed in SEEDS:
        folder = _folder(seed)
        made = _session(folder, seed)
        truth = made["truth"]
        for model, overrides in MODELS.items():
            reconstruction = folder / f"reconstruction_{model}"
            settings = load_fit_settings(None, model=overrides)
            start = time.perf_counter()
            reconstruct_cube(folder / "calibrated" / CUBE_NAME, reconstruction, settings, device="cpu", force=True)
            fit_s = round(time.perf_counter() - start, 1)
            accuracy = accuracy_against_truth(folder / "session", reconstruction, folder / "calibrated" / CUBE_NAME)
            common = {"seed": seed, "model": model, "residual_rms": round(accuracy["residual_rms"], 5),
                      "cube_noise_rms": round(accuracy.get("cube_noise_rms", float("nan")), 5),
                      "truth_std_error_median": round(statistics.median(truth["std_error_median_per_band"].values()), 5),
                      "photons_per_node": PHOTONS, "capture_s": made.get("capture_s", ""), "fit_s": fit_s,
                      "pixels": accuracy["pixels"], "high_residual_pixels": accuracy["high_residual_pixels"]}
            for name, p in accuracy["parameters"].items():
                rows.append({**common, "parameter": name, "median_error": round(p["median_error"], 4), "error_kind": p["error_kind"],
                             "truth_median": p["truth_median"], "fit_median": p["fit_median"], "sigma_median": p["sigma_median"]})
            print(seed, model, {n: round(p["median_error"], 3) for n, p in accuracy["parameters"].items()}, common)
    write_csv(_csv("transport_session.csv"), rows, f"{PHOTONS:,} photons per node, {SIZE}² cube, seeds {SEEDS}")
    assert all(r["median_error"] >= 0 for r in rows)


def test_what_the_fit_makes_of_the_truth_without_noise():
    """The sessions above (kept in the output folder), their truth fitted with no camera at all:
    the Monte Carlo's truth reflectance (its own standard error 0.1–0.2%) and the transport model's
    own render of the same maps (the simulator's diffusion path with ``profiles: transport``), both
    as cubes with the session's header and mask, fitted with ``profiles: transport``. The first minus
    the second is what the model's remaining difference from transport costs the fit; the second is
    the fit's own floor. Writes ``transport_session_noiseless.csv``."""
    import numpy as np

    from skinlayers.formats.cube import Cube, write_cube
    from skinlayers.formats.exr import read_exr

    rows = []
    rig = _rig()
    for seed in SEEDS:
        folder, cube, scene = _kept(seed)
        channels, _ = read_exr(folder / "session" / "truth" / "reflectance.exr")
        mc = torch.stack([torch.as_tensor(np.asarray(channels[f"R_{w:g}"])) for w in cube.header.wavelengths_nm]).float()
        own = _own_render(rig, scene, seed, MODELS["transport"])
        ratio = own.double() / mc.double()
        centre = ratio[:, SIZE // 4: 3 * SIZE // 4, SIZE // 4: 3 * SIZE // 4].reshape(ratio.shape[0], -1).median(1).values
        for truth, reflectance in (("monte_carlo", mc), ("model_itself", own)):
            path = folder / f"cube_{truth}.exr"
            write_cube(path, Cube(reflectance, cube.mask, cube.header))
            accuracy = _fit(folder, path, f"reconstruction_noiseless_{truth}", load_fit_settings(None, model=MODELS["transport"]))
            for name, p in accuracy["parameters"].items():
                rows.append({"seed": seed, "truth": truth, "parameter": name, "median_error": round(p["median_error"], 4),
                             "fit_over_truth_median": round(p["fit_median"] / p["truth_median"], 4) if name != "beta_m" else "",
                             "fit_median": p["fit_median"], "truth_median": p["truth_median"],
                             "residual_rms": round(accuracy["residual_rms"], 5),
                             "model_over_mc_centre_per_band": " ".join(f"{float(v):.4f}" for v in centre)})
            print(seed, truth, {n: round(p["median_error"], 3) for n, p in accuracy["parameters"].items()}, round(accuracy["residual_rms"], 5))
    write_csv(_csv("transport_session_noiseless.csv"), rows, f"seeds {SEEDS}, fitted with profiles: transport")
    assert all(r["median_error"] >= 0 for r in rows)


def test_each_models_floor_at_the_sessions_noise():
    """What each model's fit gives on its *own* physics at the sessions' noise: the model's render of
    the truth maps (``profiles`` each way) plus white noise of ``SKINLAYERS_FLOOR_NOISE`` (default
    0.004: the cube's 0.0036 and the Monte Carlo's 0.0015 together), fitted with the same model
    (dermal blood on nodes of ``SKINLAYERS_FLOOR_CHD_MM``, default the fit's). A map error here is the
    data's limit for that model, not a mismatch with transport. Writes ``transport_session_floor.csv``
    (``_<cell>mm`` added with a cell)."""
    from skinlayers.formats.cube import Cube, write_cube

    noise = float(os.environ.get("SKINLAYERS_FLOOR_NOISE", 0.004))
    cell = os.environ.get("SKINLAYERS_FLOOR_CHD_MM")
    grid = {"map_cell_mm": {"C_hd": float(cell)}} if cell else {}
    rows = []
    rig = _rig()
    for seed in SEEDS:
        folder, cube, scene = _kept(seed)
        for model, overrides in MODELS.items():
            own = _own_render(rig, scene, seed, overrides)
            g = torch.Generator().manual_seed(seed)
            path = folder / f"cube_floor_{model}.exr"
            write_cube(path, Cube(own + noise * torch.randn(own.shape, generator=g), cube.mask, cube.header))
            accuracy = _fit(folder, path, f"reconstruction_floor_{model}", load_fit_settings(None, model=overrides, **grid))
            rows += _map_rows(accuracy, {"seed": seed, "model": model, "noise": noise, "C_hd_cell_mm": cell or "default"})
            print(seed, model, {n: round(p["median_error"], 3) for n, p in accuracy["parameters"].items()}, round(accuracy["residual_rms"], 5))
    name = "transport_session_floor.csv" if not cell else f"transport_session_floor_{float(cell):g}mm.csv"
    write_csv(_csv(name), rows, f"seeds {SEEDS}, white noise {noise}, each model on its own render, C_hd nodes {cell or 'default'}")
    assert all(r["median_error"] >= 0 for r in rows)


def test_dermal_blood_grid_on_transport_sessions():
    """The kept sessions refitted with dermal blood on nodes of ``SKINLAYERS_GRID_MM`` (default 0.375,
    today's, then 0.75 and 1.5 mm), each model. Under transport physics a pixel's dermal blood is hard
    to tell from its neighbours' (the Cramér–Rao bound, ``test_bench_identifiability.py``,
    ``test_bound_under_each_models_physics``): a coarser grid trades that noise for the truth's own
    variation within a node. Writes ``transport_session_grid.csv``."""
    cells = tuple(float(c) for c in os.environ.get("SKINLAYERS_GRID_MM", "0.375,0.75,1.5").split(","))
    rows = []
    for seed in SEEDS:
        folder, _, _ = _kept(seed)
        cube = folder / "calibrated" / CUBE_NAME
        for model, overrides in MODELS.items():
            for cell in cells:
                settings = load_fit_settings(None, model=overrides, map_cell_mm={"C_hd": cell})
                accuracy = _fit(folder, cube, f"reconstruction_grid_{model}_{cell:g}", settings)
                rows += _map_rows(accuracy, {"seed": seed, "model": model, "C_hd_cell_mm": cell})
                print(seed, model, cell, {n: round(p["median_error"], 3) for n, p in accuracy["parameters"].items()})
    write_csv(_csv("transport_session_grid.csv"), rows, f"seeds {SEEDS}, C_hd on nodes of {cells} mm, each model")
    assert all(r["median_error"] >= 0 for r in rows)
