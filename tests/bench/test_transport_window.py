"""Benchmark: homogeneous skin under the session's window, the model (each ``profiles``) against the
Monte Carlo (run on demand: ``pytest -m bench tests/bench/test_transport_window.py -s``).

A Table 2 row (``SKINLAYERS_WINDOW_PRESET``, default III interior) on the simulator's truth grid for a
32² cube (7.5-mm window, 0.117-mm pixels, 3 mm of skin beyond it), at the rig's nine band centres.
The Monte Carlo renders it through the homogeneous twin, so its image is the twin's point response
(200,000 photons) convolved with the window: nearly free of noise. Writes ``transport_window.csv``:
per band and profiles the model's exitance over the Monte Carlo's at the centre (16² pixels), just
inside the edge (the first three pixels) and 0.35–0.6 mm outside it, and the Monte Carlo's relative
standard error at the centre. What it isolates: the profiles' lateral shape (no heterogeneity, no
camera, no fit).
"""

from __future__ import annotations

import os

import pytest
import torch

from bench_io import write_csv

from skinlayers.model import TABLE2, ModelSettings
from skinlayers.model.render.illumination import Light
from skinlayers.model.patch.maps import SkinMaps
from skinlayers.model.render.renderer import SkinRenderer
from skinlayers.model.transport import TransportRenderer

pytestmark = pytest.mark.bench

PRESET = os.environ.get("SKINLAYERS_WINDOW_PRESET", "III interior")
BANDS_NM = (430.0, 460.0, 490.0, 520.0, 550.0, 580.0, 610.0, 640.0, 670.0)
WINDOW_MM, WINDOW_PX, MARGIN_PX = 7.5, 64, 26


def test_the_window_on_homogeneous_skin_against_the_monte_carlo():
    mm, n = WINDOW_MM / WINDOW_PX, WINDOW_PX + 2 * MARGIN_PX
    maps = SkinMaps.uniform(TABLE2[PRESET], (n, n), mm, dtype=torch.float64)
    wl = torch.tensor(BANDS_NM, dtype=torch.float64)
    settings = ModelSettings.model_validate({"transport": {"twin": True, "twin_kernel_share": 2.0}})
    mc = TransportRenderer(settings).render(maps, Light("window", size_mm=WINDOW_MM), wl, photons=100_000, seed=3)
    centre, e = slice(n // 2 - 8, n // 2 + 8), MARGIN_PX
    regions = {"centre": (centre, centre), "inside_edge": (centre, slice(e, e + 3)), "outside_0.35_0.6mm": (centre, slice(e - 5, e - 3))}
    rows = []
    for profiles, handover in (("diffusion", "lambertian"), ("transport", "lambertian"), ("transport", "angular")):
        model = SkinRenderer(ModelSettings(profiles=profiles, handover=handover)).render(
            maps.to(dtype=torch.float32), Light("window", size_mm=WINDOW_MM, border_mm=3.0), wl.float(), under_gel=True).exitance[0].double()
        ratio = model / mc.exitance[0]
        for j, band in enumerate(BANDS_NM):
            row = {"preset": PRESET, "profiles": profiles, "handover": handover, "band_nm": band}
            for name, (ys, xs) in regions.items():
                row[f"model_over_mc_{name}"] = round(float(ratio[j, ys, xs].mean()), 5)
            row["mc_relative_se_centre"] = round(float((mc.exitance_std_error[0, j] / mc.exitance[0, j])[centre, centre].mean()), 5)
            rows.append(row)
            print(row)
    write_csv("transport_window.csv", rows, f"{PRESET}, {WINDOW_MM}-mm window, {mm:.4f} mm pixels; MC 100,000 photons + twin kernel 200,000")
    assert all(0.5 < r["model_over_mc_centre"] < 1.5 for r in rows)
