"""Point fits that choose their model (``select_spectrum_models``, ``fit-spectrum --model auto``):
what they free, at what cost, and whether it helps, against truths the fit did not make.

- ``spectrum_models_nist.csv``: NIST's 100 forearms (400–700 nm, 3 nm), against the measurements:
  the fixed model, DWRR08's (free scale), and ``auto`` capped at 30 and at 100 iterations per
  extended fit, side by side in one run: time, RMS residual, what BIC chose;
- ``spectrum_models_simulated.csv``: 40 skins per scene rendered every 1 nm through a 3 nm band-pass
  with noise σ = 0.003 — by the diffusion model with one constant changed, and by the transport
  profiles (adding-doubling totals: other physics) — fitted fixed and ``auto`` (σ known, and
  estimated): how often the changed constant was freed, its value, and melanin's error.

Run: ``pytest -m bench tests/bench/test_bench_spectrum_models.py -s``.
"""

from __future__ import annotations

import time
from pathlib import Path

import pytest
import torch

from skinlayers.model import ModelSettings, SkinModel, SkinParams
from skinlayers.model.column.point_model import point_reflectance
from skinlayers.reconstruct import fit_spectra, select_spectrum_models
from skinlayers.reconstruct.spectrum.spectra_io import read_spectra_csv
from skinlayers.reconstruct.spectrum.spectrum_models import candidate_label

from bench_io import write_csv

pytestmark = pytest.mark.bench

NIST = Path(__file__).resolve().parents[1] / "data" / "nist_skin_reflectance_forearm_avg_370-830nm.csv"
NOISE = 0.003
SKINS = 40
#: Scene → the truth's constants (diffusion) or ``"transport"``.
SCENES = {
    "fixed model's constants": {},
    "dermis scattering ratio 1.5": {"dermis_scattering_ratio": 1.5},
    "dermis scattering ratio 3": {"dermis_scattering_ratio": 3.0},
    "epidermis 0.4 mm": {"epidermis_thickness_mm": 0.4},
    "dermal oxygenation 0.3": {"oxygenation_dermis": 0.3},
    "transport profiles (adding-doubling)": "transport",
}


def _chosen(selection) -> str:
    counts = {candidate_label(c): int((selection.choice == j).sum()) for j, c in enumerate(selection.candidates)}
    return "; ".join(f"{k} {v}" for k, v in counts.items() if v)


def test_spectrum_models_nist():
    data = read_spectra_csv(NIST).select(400, 700)
    y, wl = data.reflectance, data.wavelength_nm
    fit_spectra(y[:2], wl)  # warm-up
    rows, capped = [], None
    runs = {"fixed": dict(candidates=[()]), "paper (free scale)": dict(candidates=[()], free_scale=True),
            "auto, 30 iterations": dict(max_iterations=30), "auto, 100 iterations": dict(max_iterations=100)}
    for name, kw in runs.items():
        start = time.perf_counter()
        selection = select_spectrum_models(y, wl, SkinModel(), **kw)
        seconds = time.perf_counter() - start
        rms = selection.fit.rms_residual
        row = {"model": name, "spectra": y.shape[0], "seconds": round(seconds, 2),
               "median_rms": round(float(rms.median()), 5), "worst_rms": round(float(rms.max()), 5),
               "chosen": _chosen(selection)}
        if name.startswith("auto"):
            if capped is None:
                capped = selection.rms_residual
            else:  # every candidate's residual, capped against uncapped, spectrum by spectrum
                row["max_rms_ratio_30_over_100"] = round(float((capped / selection.rms_residual).max()), 6)
            for n, v in selection.fit.constants.items():
                row[f"{n}_median"] = round(float(v.median()), 4)
        rows.append(row)
    write_csv("spectrum_models_nist.csv", rows, "NIST forearms, against the measurements")
    assert rows[2]["median_rms"] < 0.5 * rows[0]["median_rms"]


def _simulate(truth: torch.Tensor, wl: torch.Tensor, scene, seed: int) -> torch.Tensor:
    fine = torch.arange(float(wl[0]) - 2, float(wl[-1]) + 3, 1.0, dtype=torch.float64)
    params = SkinParams.from_tensor(truth)
    if scene == "transport":
        r = SkinModel(ModelSettings(profiles="transport")).diffuse_reflectance(params, fine)
    else:
        r = point_reflectance(SkinModel(), params, fine,
                              {n: torch.full((truth.shape[0],), v, dtype=torch.float64) for n, v in scene.items()})
    w = torch.tensor([1.0, 2.0, 3.0, 2.0, 1.0], dtype=torch.float64) / 9.0
    idx = (wl - fine[0]).long()
    banded = sum(w[j] * r[:, idx + j - 2] for j in range(5))
    g = torch.Generator().manual_seed(seed)
    return banded + NOISE * torch.randn(banded.shape, generator=g, dtype=torch.float64)


def test_spectrum_models_simulated():
    wl = torch.arange(400.0, 701.0, 3.0, dtype=torch.float64)
    g = torch.Generator().manual_seed(7)
    lo = torch.tensor([0.002, 0.05, 0.0005, 0.0002, 0.002], dtype=torch.float64)
    hi = torch.tensor([0.2, 0.95, 0.02, 0.01, 0.04], dtype=torch.float64)
    truth = lo + (hi - lo) * torch.rand(SKINS, 5, generator=g, dtype=torch.float64)

    def melanin_error(fit) -> float:
        return round(float(((fit.params.C_m - truth[:, 0]).abs() / truth[:, 0]).median()), 4)

    rows = []
    for scene, constants in SCENES.items():
        y = _simulate(truth, wl, constants, seed=11)
        for noise in (NOISE, None):
            start = time.perf_counter()
            selection = select_spectrum_models(y, wl, SkinModel(), noise=noise)
            seconds = time.perf_counter() - start
            row = {"scene": scene, "noise_known": noise is not None, "spectra": SKINS, "seconds": round(seconds, 2),
                   "chosen": _chosen(selection),
                   "C_m_error_fixed": melanin_error(selection.fits[()]), "C_m_error_auto": melanin_error(selection.fit),
                   "median_rms_fixed": round(float(selection.fits[()].rms_residual.median()), 5),
                   "median_rms_auto": round(float(selection.fit.rms_residual.median()), 5)}
            if isinstance(constants, dict):
                for name, value in constants.items():
                    freed = torch.tensor([name in f for f in selection.fit.freed])
                    row["truth_constant_freed"] = int(freed.sum())
                    row["freed_value_median"] = round(float(selection.fit.constants[name][freed].median()), 4) if bool(freed.any()) else ""
                    row["truth_value"] = value
            else:
                reference = fit_spectra(y, wl, SkinModel(ModelSettings(profiles="transport")))
                row["C_m_error_transport_fit"] = melanin_error(reference)
            rows.append(row)
    write_csv("spectrum_models_simulated.csv", rows, f"{SKINS} skins per scene, 3 nm band-pass, noise {NOISE}")
    null = [r for r in rows if r["scene"] == "fixed model's constants" and r["noise_known"]][0]
    assert null["chosen"] == f"fixed {SKINS}" or int(null["chosen"].split("fixed ")[1].split(";")[0]) >= SKINS - 2
