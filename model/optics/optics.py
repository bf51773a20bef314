"""The fixed optical properties of the two-layer skin model (``SkinOptics``), on their own so that the
spectra can take them without the rest of the settings (``ModelSettings.optics`` holds them)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from ...formats.settings import Strict

__all__ = ["SkinOptics"]


class SkinOptics(Strict):
    """Fixed optical properties of the two-layer skin model (DWRR08 §5, §5.1, Eq. 11–13; chromophore sources: docs/model.md, "Constants and units")."""

    epidermis_thickness_mm: float = Field(0.25, gt=0, description="Epidermis thickness (DWRR08 §5.1).")
    n_epidermis: float = Field(1.40, gt=1, description="Refractive index of the epidermis.")
    n_dermis: float = Field(1.38, gt=1, description="Refractive index of the dermis.")
    n_above: float = Field(1.0, ge=1, description="Index of the medium above the skin (air = 1).")
    scattering_mie_coeff: float = Field(14.74, description="σs' epidermis = a λ^b + c λ^d (Eq. 13): a, mm⁻¹.")
    scattering_mie_exponent: float = Field(-0.22, description="Eq. 13: b.")
    scattering_rayleigh_coeff: float = Field(2.2e11, description="Eq. 13: c, mm⁻¹.")
    scattering_rayleigh_exponent: float = Field(-4.0, description="Eq. 13: d.")
    dermis_scattering_ratio: float = Field(0.5, gt=0, description="σs' dermis over σs' epidermis (DWRR08 §5.1).")
    oxygenation_epidermis: float = Field(0.7, ge=0, le=1, description="γ_e, oxygenated fraction of epidermal blood.")
    oxygenation_dermis: float = Field(0.7, ge=0, le=1, description="γ_d, oxygenated fraction of dermal blood.")
    hemoglobin_g_per_l: float = Field(150.0, gt=0, description="Hemoglobin in whole blood (Prahl).")
    hemoglobin_g_per_mol: float = Field(64500.0, gt=0, description="Molar mass of hemoglobin (Prahl).")
    carotene_reference_mol_per_l: float = Field(
        150.0 / 64500.0,
        gt=0,
        description=(
            "Molar concentration of β-carotene in the medium whose volume fraction C_bc is. DWRR08 does "
            "not state it; this default gives the carotene medium the molar density of hemoglobin in "
            "whole blood (2.33 mM), so C_bc and C_he are fractions of equally concentrated pigment media "
            "on the same 0–0.05 range (see docs/model.md for the check against Table 2)."
        ),
    )
    eumelanin_coeff: float = Field(6.6e10, description="σa_em = a λ^b mm⁻¹ (Jacques; 6.6e11 in cm⁻¹).")
    eumelanin_exponent: float = Field(-3.33, description="σa_em exponent b.")
    pheomelanin_coeff: float = Field(2.9e14, description="σa_pm = a λ^b mm⁻¹ (Jacques; 2.9e15 in cm⁻¹).")
    pheomelanin_exponent: float = Field(-4.75, description="σa_pm exponent b.")
    baseline_offset: float = Field(0.0244, description="σa_base = a + b exp(-(λ - c)/w) mm⁻¹: a.")
    baseline_amplitude: float = Field(8.53, description="σa_base: b, mm⁻¹.")
    baseline_center_nm: float = Field(154.0, description="σa_base: c, nm.")
    baseline_width_nm: float = Field(66.2, gt=0, description="σa_base: w, nm.")
    interface_melanin_fraction: float = Field(
        0.175, ge=0, description="Interface absorbance as a fraction of epidermal melanin absorption (DWRR08 §5.1)."
    )
    source_depth: Literal["mean_free_path", "capped"] = Field(
        "mean_free_path",
        description=(
            "Depth of the multipole's point source: one transport mean free path (the paper), or capped "
            "at half the layer thickness (a renderer-port hack; see docs/model.md for both against transport)."
        ),
    )
