"""Benchmark: the Monte Carlo transport reference against adding-doubling, every case with its z-score
(run on demand: ``pytest -m bench tests/bench/test_transport_validation.py -s``).

The cases of ``tests/model/test_transport_reference.py``'s slow checks, written out: Table 2's nine rows
at 470, 560 and 650 nm (epidermis over a semi-infinite dermis, one index, no interface absorber: what
adding-doubling can express) and the 0.25-mm slab over skin's σa range. Writes
``transport_validation.csv`` (``bench_io``) with the Monte Carlo value, its standard error, the
adding-doubling value (64 quadrature points), z = (MC − AD)/SE, the photons and the seconds. The first
row is one band of III interior with ``SKINLAYERS_PEAK_PHOTONS`` photons (default 10⁷), run first so
that its ``peak_mb`` — the process's peak resident memory over what it held just before the walk — is the
walk's own: the photons go in batches (``transport.batch_photons``), so the peak is set by the batch,
not by the count.
"""

from __future__ import annotations

import math
import os
import resource
import time

import pytest
import torch

pytest.importorskip("iadpython")

import transport_reference as ref
from bench_io import write_csv

from skinlayers.model import TABLE2, ModelSettings, SkinModel, SkinParams
from skinlayers.model.optics.radiometry import entry_transmittance
from skinlayers.model.transport import Medium, TransportRenderer, walk

pytestmark = pytest.mark.bench

PHOTONS = int(os.environ.get("SKINLAYERS_VALIDATION_PHOTONS", 1_000_000))
PEAK_PHOTONS = int(os.environ.get("SKINLAYERS_PEAK_PHOTONS", 10_000_000))
WL = torch.tensor([470.0, 560.0, 650.0], dtype=torch.float64)


def _peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _resident_mb() -> float:
    """The process's resident memory now (Linux; the peak where /proc is missing)."""
    try:
        return float(open("/proc/self/statm").read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except OSError:
        return _peak_mb()


def test_transport_reference_against_adding_doubling():
    rows = []
    settings = ModelSettings.model_validate({"optics": {"n_dermis": 1.40, "interface_melanin_fraction": 0.0}})
    model, renderer = SkinModel(settings), TransportRenderer(settings)
    spectra = model.spectra(WL)
    before = _resident_mb()
    start = time.perf_counter()
    big = renderer.totals(SkinParams.from_mapping(TABLE2["III interior"]), WL[1:2], photons=PEAK_PHOTONS, seed=8)
    seconds = time.perf_counter() - start
    ab = model.absorption(SkinParams.from_mapping(TABLE2["III interior"]), spectra)
    layers = [ref.Layer(float(ab.epidermis[1]), float(spectra.scattering_epidermis[1]), 0.25),
              ref.Layer(float(ab.dermis[1]), float(spectra.scattering_dermis[1]), ref.DERMIS_MM)]
    ad = ref.adding_doubling_stack(layers, quad_points=64).R_diffuse
    mc, se = float(big.reflectance[0]), float(big.std_error[0])
    rows.append({"case": "III interior, skin", "wavelength_nm": float(WL[1]), "quantity": "R", "monte_carlo": round(mc, 6),
                 "std_error": round(se, 6), "adding_doubling": round(ad, 6), "z": round((mc - ad) / se, 2), "photons": PEAK_PHOTONS,
                 "seconds": round(seconds, 1), "peak_mb": round(_peak_mb() - before)})
    for k, row in enumerate(TABLE2):  # each row its own seed: one for all would make their errors alike
        params = SkinParams.from_mapping(TABLE2[row])
        start = time.perf_counter()
        totals = renderer.totals(params, WL, photons=PHOTONS, seed=10 + k)
        seconds = time.perf_counter() - start
        ab = model.absorption(params, spectra)
        for j, w in enumerate(WL.tolist()):
            layers = [ref.Layer(float(ab.epidermis[j]), float(spectra.scattering_epidermis[j]), 0.25),
                      ref.Layer(float(ab.dermis[j]), float(spectra.scattering_dermis[j]), ref.DERMIS_MM)]
            ad = ref.adding_doubling_stack(layers, quad_points=64).R_diffuse
            mc, se = float(totals.reflectance[j]), float(totals.std_error[j])
            rows.append({"case": f"{row}, skin", "wavelength_nm": w, "quantity": "R", "monte_carlo": round(mc, 6), "std_error": round(se, 6),
                         "adding_doubling": round(ad, 6), "z": round((mc - ad) / se, 2), "photons": PHOTONS,
                         "seconds": round(seconds / WL.numel(), 1)})
    for case, (sigma_s, sigma_a) in enumerate((s, a) for s in (4.40, 6.08, 12.54) for a in (0.02, 0.2, 2.0, 20.0, 80.0)):
        # each case its own photons: one seed for all would make their errors alike
        medium = Medium((0.25,), (ref.N_SKIN,), 1.0, 1.0, (sigma_s,), 0.0, torch.full((1, 1, 1), sigma_a, dtype=torch.float64),
                        torch.ones(0, 1, 1, dtype=torch.float64), 1.0)
        batches, per = 16, PHOTONS // 16
        zero = torch.zeros(per * batches, dtype=torch.float64)
        start = time.perf_counter()
        t = walk(medium, zero, zero, torch.ones_like(zero), torch.full_like(zero, entry_transmittance(ref.N_SKIN)),
                 torch.Generator().manual_seed(100 + case), label=torch.arange(batches).repeat_interleave(per), labels=batches)
        seconds = time.perf_counter() - start
        ad = ref.adding_doubling_slab(ref.Layer(sigma_a, sigma_s, 0.25), quad_points=64)
        for quantity, values, exact in (("R", t.reflected / per, ad.R_diffuse), ("T", t.transmitted / per, ad.T_diffuse)):
            mc, se = float(values.mean()), float(values.std(unbiased=True) / math.sqrt(batches))
            rows.append({"case": f"slab σa {sigma_a:g}, σs′ {sigma_s:g}", "wavelength_nm": "", "quantity": quantity,
                         "monte_carlo": round(mc, 8), "std_error": round(se, 8), "adding_doubling": round(exact, 8),
                         "z": round((mc - exact) / se, 2) if se > 0 else "", "photons": PHOTONS, "seconds": round(seconds, 1)})
    write_csv("transport_validation.csv", rows)
    assert all(abs(r["z"]) < 3.5 for r in rows if r["z"] != "" and r["adding_doubling"] > 1e-5)
