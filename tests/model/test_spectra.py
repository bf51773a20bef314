"""Chromophore spectra and layer absorption against the published figures they come from."""

from __future__ import annotations

import math

import pytest
import torch

from skinlayers.model import SkinOptics, SkinParams, chromophore_spectra, layer_absorption

W = torch.tensor([380.0, 400.0, 451.0, 500.0, 542.0, 576.0, 650.0, 700.0, 800.0], dtype=torch.float64)


def test_melanin_in_mm_not_cm():
    """Jacques: μa,em = 6.6e11 λ^-3.33 cm⁻¹ → 142.8 cm⁻¹ ... at 400 nm is 1428 cm⁻¹ = 142.8 mm⁻¹."""
    s = chromophore_spectra(W)
    assert float(s.eumelanin[1]) == pytest.approx(6.6e11 * 400.0**-3.33 / 10.0, rel=1e-12)
    assert float(s.eumelanin[1]) == pytest.approx(142.8, rel=2e-3)
    assert float(s.pheomelanin[1]) == pytest.approx(2.9e15 * 400.0**-4.75 / 10.0, rel=1e-12)


def test_blood_from_prahl_table():
    """Whole blood: μa = 2.303 ε 150/64500 cm⁻¹ with Prahl's ε: HbO2 53292 cm⁻¹/M at 542 nm, Hb 40092 at 576 nm."""
    s = chromophore_spectra(W)
    to_mm = 0.1 * math.log(10) * 150 / 64500
    assert float(s.oxy_blood[4]) == pytest.approx(53292 * to_mm, rel=1e-9)
    assert float(s.deoxy_blood[5]) == pytest.approx(40092 * to_mm, rel=1e-9)
    # oxy peak at 576 nm above the 560 nm trough: the Q bands are where they belong
    s2 = chromophore_spectra(torch.tensor([560.0, 576.0], dtype=torch.float64))
    assert float(s2.oxy_blood[1]) > 1.5 * float(s2.oxy_blood[0])
    torch.testing.assert_close(s.blood_dermis, 0.7 * s.oxy_blood + 0.3 * s.deoxy_blood)


def test_carotene_reference_concentration():
    """σa_bc = 0.1 ln10 ε c_ref; ε(451) ≈ 139,500 cm⁻¹/M (PhotochemCAD); nothing beyond 700 nm."""
    opt = SkinOptics()
    s = chromophore_spectra(W, opt)
    expected = 0.1 * math.log(10) * 139500 * opt.carotene_reference_mol_per_l
    assert float(s.carotene[2]) == pytest.approx(expected, rel=2e-3)
    assert float(s.carotene[-1]) == 0.0
    # at 650 nm only the measurement's noise floor remains (about 0.4% of the peak)
    assert float(s.carotene[6]) < 1e-2 * float(s.carotene[2])


def test_baseline_and_scattering():
    s = chromophore_spectra(W)
    assert float(s.baseline[3]) == pytest.approx(0.0244 + 8.53 * math.exp(-(500 - 154) / 66.2), rel=1e-12)
    sigma_400 = 14.74 * 400**-0.22 + 2.2e11 * 400**-4
    assert float(s.scattering_epidermis[1]) == pytest.approx(sigma_400, rel=1e-12)
    assert float(s.scattering_epidermis[1]) == pytest.approx(12.5, rel=0.01)  # Eq. 13 (DWRR08 §5.1) at 400 nm
    assert float(s.scattering_epidermis[7]) == pytest.approx(4.4, rel=0.01)
    torch.testing.assert_close(s.scattering_dermis, 0.5 * s.scattering_epidermis)


def test_interpolation_between_table_rows():
    s = chromophore_spectra(torch.tensor([500.0, 501.0, 502.0], dtype=torch.float64))
    assert float(s.oxy_blood[1]) == pytest.approx(0.5 * float(s.oxy_blood[0] + s.oxy_blood[2]), rel=1e-12)


@pytest.mark.parametrize("bad", [[379.0], [500.0, 801.0], [float("nan")], []])
def test_wavelengths_out_of_range(bad):
    with pytest.raises(ValueError, match="wavelength"):
        chromophore_spectra(torch.tensor(bad, dtype=torch.float64))


def test_layer_absorption_eq11_eq12():
    s = chromophore_spectra(W)
    p = SkinParams.from_mapping(dict(C_m=0.1, beta_m=0.25, C_he=0.02, C_bc=0.01, C_hd=0.05))
    ab = layer_absorption(p, s, 0.175, 0.25)
    mel = 0.25 * s.eumelanin + 0.75 * s.pheomelanin
    epi = 0.1 * mel + 0.02 * s.blood_epidermis + 0.01 * s.carotene + (1 - 0.13) * s.baseline
    derm = 0.05 * s.blood_dermis + 0.95 * s.baseline
    torch.testing.assert_close(ab.epidermis, epi)
    torch.testing.assert_close(ab.dermis, derm)
    torch.testing.assert_close(ab.interface_absorbance, 0.175 * 0.1 * mel * 0.25)


@pytest.mark.parametrize(
    "values, message",
    [
        (dict(C_m=-0.01), "C_m must be >= 0"),
        (dict(beta_m=1.2), "beta_m must be <= 1"),
        (dict(C_m=0.6, C_he=0.3, C_bc=0.2), "C_m \\+ C_he \\+ C_bc must be <= 1"),
        (dict(C_hd=float("nan")), "C_hd must be a finite number"),
    ],
)
def test_bad_parameters_are_refused(values, message):
    base = dict(C_m=0.01, beta_m=0.5, C_he=0.002, C_bc=0.001, C_hd=0.005)
    with pytest.raises(ValueError, match=message):
        SkinParams.from_mapping({**base, **values}).validate()


def test_unknown_or_missing_parameter():
    with pytest.raises(ValueError, match="unknown parameter"):
        SkinParams.from_mapping(dict(C_m=0.1, beta_m=0.5, C_he=0, C_bc=0, C_hd=0, melanin=2))
    with pytest.raises(ValueError, match="missing parameter"):
        SkinParams.from_mapping(dict(C_m=0.1))
