"""Chromophore spectra and the layers' optical coefficients (DWRR08 §5.1, Eq. 11–13).

The constants, their units and their primary sources (Jacques for the melanins and the baseline,
Prahl for hemoglobin, PhotochemCAD for β-carotene) are tabulated in docs/model.md, "Constants and
units".

Tabulated spectra (hemoglobin, β-carotene) are package data files naming their sources, read once;
closed forms (melanins, baseline, scattering) are functions of the settings' constants. Any
wavelength in 380–800 nm is served, tables by linear interpolation.

Shapes: wavelengths ``(L,)``; chromophore spectra ``(L,)``; layer coefficients for parameters of
batch shape ``(...)`` are ``(..., L)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from importlib import resources

import numpy as np
import torch

from ...formats.errors import InputError
from .optics import SkinOptics

__all__ = [
    "MIN_WAVELENGTH_NM",
    "MAX_WAVELENGTH_NM",
    "ChromophoreSpectra",
    "chromophore_spectra",
    "check_wavelengths",
    "epidermis_scattering",
]

MIN_WAVELENGTH_NM = 380.0
MAX_WAVELENGTH_NM = 800.0
LN10 = math.log(10.0)
PER_CM_TO_PER_MM = 0.1


@lru_cache(maxsize=None)
def _table(name: str) -> np.ndarray:
    text = resources.files("skinlayers.model").joinpath("data", name).read_text()
    rows = [line for line in text.splitlines() if line and not line.startswith("#")]
    return np.array([[float(v) for v in row.split(",")] for row in rows[1:]])


def check_wavelengths(wavelength_nm: torch.Tensor) -> torch.Tensor:
    """Validate a 1-D tensor of wavelengths in 380–800 nm; return it as float64."""
    w = torch.as_tensor(wavelength_nm, dtype=torch.float64)
    if w.ndim != 1 or w.numel() == 0:
        raise InputError(f"wavelengths must be a non-empty 1-D list, got shape {tuple(w.shape)}")
    if not bool(torch.isfinite(w).all()):
        raise InputError("wavelengths must be finite numbers")
    if bool((w < MIN_WAVELENGTH_NM).any()) or bool((w > MAX_WAVELENGTH_NM).any()):
        raise InputError(
            f"wavelengths must lie within {MIN_WAVELENGTH_NM:g}–{MAX_WAVELENGTH_NM:g} nm, "
            f"got {float(w.min()):g}–{float(w.max()):g} nm"
        )
    return w


def _interp(x: torch.Tensor, xp: np.ndarray, fp: np.ndarray, right: float | None = None) -> torch.Tensor:
    values = np.interp(x.cpu().numpy(), xp, fp, right=right)
    return torch.from_numpy(values)


def epidermis_scattering(wavelength_nm: torch.Tensor, optics: SkinOptics) -> torch.Tensor:
    """Reduced scattering of the epidermis, Eq. 13 (Jacques 1998), mm⁻¹, ``(L,)``."""
    w = torch.as_tensor(wavelength_nm, dtype=torch.float64)
    return optics.scattering_mie_coeff * w**optics.scattering_mie_exponent + (
        optics.scattering_rayleigh_coeff * w**optics.scattering_rayleigh_exponent
    )


@dataclass(frozen=True)
class ChromophoreSpectra:
    """Absorption of each pure chromophore medium and the layers' scattering at L wavelengths, mm⁻¹.

    ``blood_epidermis`` and ``blood_dermis`` are whole blood at the layers' oxygenations.
    """

    wavelength_nm: torch.Tensor
    eumelanin: torch.Tensor
    pheomelanin: torch.Tensor
    oxy_blood: torch.Tensor
    deoxy_blood: torch.Tensor
    blood_epidermis: torch.Tensor
    blood_dermis: torch.Tensor
    carotene: torch.Tensor
    baseline: torch.Tensor
    scattering_epidermis: torch.Tensor
    scattering_dermis: torch.Tensor

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> "ChromophoreSpectra":
        fields = {k: v.to(device=device, dtype=dtype) for k, v in self.__dict__.items()}
        return ChromophoreSpectra(**fields)


def chromophore_spectra(wavelength_nm: torch.Tensor, optics: SkinOptics | None = None) -> ChromophoreSpectra:
    """All chromophore absorption spectra and scattering at the given wavelengths (float64, CPU).

    - melanins: σa_em = 6.6e10 λ^-3.33, σa_pm = 2.9e14 λ^-4.75 mm⁻¹ (Jacques' forms in mm⁻¹);
    - whole blood: σa = 0.1 · ln10 · ε(λ) · 150 / 64500 mm⁻¹ with ε from Prahl's compilation;
    - β-carotene: σa = 0.1 · ln10 · ε(λ) · c_ref mm⁻¹ with ε from PhotochemCAD (0 beyond 700 nm);
    - baseline: 0.0244 + 8.53 exp(-(λ-154)/66.2) mm⁻¹;
    - scattering: Eq. 13 in the epidermis, half of it in the dermis.
    """
    optics = optics or SkinOptics()
    w = check_wavelengths(wavelength_nm).cpu()  # tables live on the CPU; callers move the result
    hb = _table("hemoglobin_molar_extinction.csv")
    car = _table("beta_carotene_molar_extinction.csv")
    molar_hb = optics.hemoglobin_g_per_l / optics.hemoglobin_g_per_mol
    to_sigma = PER_CM_TO_PER_MM * LN10
    oxy = to_sigma * molar_hb * _interp(w, hb[:, 0], hb[:, 1])
    deoxy = to_sigma * molar_hb * _interp(w, hb[:, 0], hb[:, 2])
    carotene = to_sigma * optics.carotene_reference_mol_per_l * _interp(w, car[:, 0], car[:, 1], right=0.0)
    eu = optics.eumelanin_coeff * w**optics.eumelanin_exponent
    pheo = optics.pheomelanin_coeff * w**optics.pheomelanin_exponent
    base = optics.baseline_offset + optics.baseline_amplitude * torch.exp(
        -(w - optics.baseline_center_nm) / optics.baseline_width_nm
    )
    scat = epidermis_scattering(w, optics)
    ge, gd = optics.oxygenation_epidermis, optics.oxygenation_dermis
    return ChromophoreSpectra(
        wavelength_nm=w,
        eumelanin=eu,
        pheomelanin=pheo,
        oxy_blood=oxy,
        deoxy_blood=deoxy,
        blood_epidermis=ge * oxy + (1.0 - ge) * deoxy,
        blood_dermis=gd * oxy + (1.0 - gd) * deoxy,
        carotene=carotene,
        baseline=base,
        scattering_epidermis=scat,
        scattering_dermis=optics.dermis_scattering_ratio * scat,
    )
