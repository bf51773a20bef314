"""Benchmark: the shipped Monte Carlo sessions at 64², the size a user fits, fitted with each candidate for
the default (run on demand: ``pytest -m bench tests/bench/test_transport_session_64.py -s``).

The sessions are ``skinlayers.analyses.truths.SESSION_SEEDS_64`` (the demo's scene rendered once by the transport
reference, 250,000 photons per wavelength node; no diffusion default was tuned on them, and they chose
transport's grids: scores on them are not held out), photographed through the
simulated rig and calibrated as ``skinlayers tradeoff`` does; each configuration below is a fit setting
over the defaults. The table is the tradeoff's (``tradeoff.csv`` in ``bench_results/transport_session_64/``,
resumed on a rerun): per map the median error and the share of scored pixels whose truth lies within
±2σ of the fit, the residual over the cube's noise, the fit's time. ``transport_session_64.csv`` is its
inverse rows.
"""

from __future__ import annotations

import csv
import shutil

import pytest

from bench_io import out_dir

from skinlayers.reconstruct.settings import DEFAULT_MAP_CELL_MM
from skinlayers.analyses.tradeoff import SessionSpec, TradeoffPlan, make_session, run_tradeoff
from skinlayers.analyses.tradeoff_plan import all_configs
from skinlayers.analyses.truths import SESSION_PX, SESSION_PX_64, SESSION_SEEDS, SESSION_SEEDS_64

pytestmark = pytest.mark.bench

#: The candidates: the paper's physics (the default today); transport on diffusion's node spacings, with
#: dermal blood on coarser nodes, and with the grids it now has by default (epidermal blood on nodes too);
#: the segment coupling. Every spacing is written out: the defaults move with what this bench finds.
_D = dict(DEFAULT_MAP_CELL_MM)
_T = {"profiles": "transport"}
CONFIGS = {
    "diffusion": {"model": {"profiles": "diffusion"}},
    "transport, diffusion's grids": {"model": _T, "map_cell_mm": _D},
    "transport, C_hd 0.5 mm": {"model": _T, "map_cell_mm": {**_D, "C_hd": 0.5}},
    "transport, C_hd 0.75 mm": {"model": _T, "map_cell_mm": {**_D, "C_hd": 0.75}},
    "transport, C_he 0.25 mm, C_hd 0.5 mm": {"model": _T, "map_cell_mm": {**_D, "C_he": 0.25, "C_hd": 0.5}},
    "transport, segment": {"model": {**_T, "render": {"coupling": "segment"}}, "map_cell_mm": _D},
}


def test_the_64px_monte_carlo_sessions_fitted_with_each_candidate():
    out = out_dir() / "transport_session_64"
    plan = TradeoffPlan(forward=[], inverse=list(CONFIGS), sessions=[SessionSpec("transport", s, SESSION_PX_64) for s in SESSION_SEEDS_64],
                        scale_sizes=[], scale_configs=[], scale_seed=0, configs={**all_configs(), **CONFIGS})
    result = run_tradeoff(out, plan=plan)
    with result.table.open() as f:
        rows = [r for r in csv.DictReader(f) if r["part"] == "inverse"]
    shutil.copy(result.table, out_dir() / "transport_session_64.csv")
    assert len(rows) == len(CONFIGS) * len(SESSION_SEEDS_64)
    assert all(0.0 <= float(r["sigma_coverage_C_hd"]) <= 1.0 for r in rows)


#: Seeds that measure the transport floors; the others (and the 32² sessions) check them.
FLOOR_SEEDS = SESSION_SEEDS_64[:2]


def test_the_model_floor_of_each_physics_on_the_monte_carlos_light():
    """For each physics, each map's model floor (``uncertainty.MODEL_FLOORS``): the smallest share of the
    value (β_m: absolute) which, added in quadrature to σ's data terms, puts 90% of the scored pixels' truth
    within ±2σ, on each Monte Carlo session of the test above (its calibrated cubes, fitted again with the
    physics alone changed). ``FLOOR_SEEDS`` measure it, the other seeds and the 32² sessions (seeds 41–43,
    photographed here) check the shipped value's coverage.
    Writes ``transport_floor.csv``."""
    import torch

    from skinlayers.demo import _on_fit_grid, scored_pixels
    from skinlayers.formats.cube import read_cube
    from skinlayers.model import PARAMETER_NAMES
    from skinlayers.model.patch.maps_io import read_maps
    from skinlayers.reconstruct import fit_cube, load_fit_settings
    from skinlayers.reconstruct.diagnosis.uncertainty import MODEL_FLOOR_ABSOLUTE, MODEL_FLOORS, floor_for_coverage

    from bench_io import write_csv

    rows = []
    specs = [SessionSpec("transport", s, SESSION_PX_64) for s in SESSION_SEEDS_64]
    specs += [SessionSpec("transport", s, SESSION_PX) for s in SESSION_SEEDS]  # 32², other seeds: checks only
    for spec in specs[len(SESSION_SEEDS_64):]:
        folder = out_dir() / "transport_session_64" / "sessions" / spec.name
        if not (folder / "calibrated" / "cube.exr").exists():
            make_session(spec, folder)
    for physics in ("transport", "diffusion"):
        for spec in specs:
            seed = spec.seed
            folder = out_dir() / "transport_session_64" / "sessions" / spec.name
            if not (folder / "calibrated" / "cube.exr").exists():
                pytest.skip(f"{folder}: run test_the_64px_monte_carlo_sessions_fitted_with_each_candidate first")
            fit = fit_cube(read_cube(folder / "calibrated" / "cube.exr"), load_fit_settings(None, model={"profiles": physics}), device="cpu")
            truth = read_maps(folder / "session" / "truth" / "maps.exr")
            keep = scored_pixels(fit.flags.cpu())
            for k, name in enumerate(PARAMETER_NAMES):
                t, f = _on_fit_grid(truth, fit.maps, name)
                t, f = t[keep], f[keep]
                sigma = fit.sigma[k].double().cpu()[keep]
                shipped = MODEL_FLOORS[physics][name]
                scale = torch.ones_like(f) if name in MODEL_FLOOR_ABSOLUTE else f.abs().clamp_min(1e-12)
                err = (f - t).abs()
                data, needed = floor_for_coverage(err, sigma, shipped, scale)
                rows.append({"physics": physics, "seed": seed, "size_px": spec.size_px, "role": "measures" if seed in FLOOR_SEEDS else "checks", "map": name,
                             "pixels": int(keep.sum()),
                             "median_error": round(float((err if name in MODEL_FLOOR_ABSOLUTE else err / t.abs()).median()), 4),
                             "cover_sigma": round(float((err <= 2 * sigma).double().mean()), 3),
                             "cover_data_terms": round(float((err <= 2 * data).double().mean()), 3),
                             "floor_for_90": round(needed, 4), "model_floor": shipped})
    write_csv("transport_floor.csv", rows, "model floors on the 64² Monte Carlo sessions")
    # the shipped transport floor is what its own rule gives on the seeds that measured it (carotene aside:
    # it rests at a bound there), and covers 90% of their pixels
    measured = [r for r in rows if r["physics"] == "transport" and r["role"] == "measures" and r["map"] != "C_bc"]
    assert all(r["floor_for_90"] <= r["model_floor"] and r["cover_sigma"] >= 0.9 for r in measured), measured
