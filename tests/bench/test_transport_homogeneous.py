"""Benchmark: the Monte Carlo reference's diffuse reflectance of Table 2's nine rows with the paper's
indices (1.40 over 1.38) and the interface absorber, the truth for the forward model's homogeneous
accuracy (run on demand: ``pytest -m bench tests/bench/test_transport_homogeneous.py -s``).

Adding-doubling cannot express the index step between the layers; this can. Writes
``transport_table2_mc.csv`` (``bench_io``): row, wavelength, the Monte Carlo value, its standard error,
photons, seconds, and the model's value with each profile choice. Copy it to
``tests/data/transport_table2_mc.csv`` (with its header comment) to move the stored truth that
``tests/model/test_transport_profiles.py`` checks the model against.
"""

from __future__ import annotations

import os
import time

import pytest
import torch

from bench_io import write_csv

from skinlayers.model import TABLE2, ModelSettings, SkinParams
from skinlayers.model.transport import TransportRenderer

pytestmark = pytest.mark.bench

PHOTONS = int(os.environ.get("SKINLAYERS_TABLE2_PHOTONS", 400_000))
WAVELENGTHS_NM = [float(w) for w in os.environ.get("SKINLAYERS_TABLE2_NM", "400,450,500,550,600,650,700").split(",")]
SEED = 15


def test_table2_monte_carlo():
    renderer = TransportRenderer(ModelSettings())
    wl = torch.tensor(WAVELENGTHS_NM, dtype=torch.float64)
    rows = []
    for name, mapping in TABLE2.items():
        start = time.perf_counter()
        result = renderer.totals(SkinParams.from_mapping(mapping), wl, photons=PHOTONS, seed=SEED)
        seconds = (time.perf_counter() - start) / wl.numel()
        for j, w in enumerate(WAVELENGTHS_NM):
            rows.append({
                "row": name, "wavelength_nm": w, "monte_carlo": float(result.reflectance[j]),
                "std_error": float(result.std_error[j]), "photons": PHOTONS, "seed": SEED,
                "seconds": round(seconds, 2),
            })
        print(f"{name}: {seconds:.1f} s per band", flush=True)
    write_csv("transport_table2_mc.csv", rows, f"Table 2 by Monte Carlo, {PHOTONS} photons a band")
