"""The homogeneous model with some of its fixed constants free per spectrum, for point fits that ask
whether a spectrum supports more than the five chromophores.

DWRR08 fixes the epidermis's thickness (0.25 mm, §5.1), the dermal blood's oxygenation (0.7) and the
dermis's scattering (half the epidermis's, §5.1) for every skin. Real skin varies in all three, and a
spectrum may carry the evidence: ``point_reflectance`` is ``SkinModel.diffuse_reflectance`` (the
exact diffusion totals, DWRR08 §3 Eq. 3) with any of them given per spectrum instead, differentiable
in each, so a fit can free them one at a time and a criterion can judge whether the residual paid for
them (``reconstruct/spectrum/spectrum_models.py``).

Shapes: parameters and constants ``(B,)``, wavelengths ``(L,)`` → spectra ``(B, L)``.
"""

from __future__ import annotations

import dataclasses

import torch

from .layered import SkinModel, combine_layers
from ..optics.params import SkinParams, layer_absorption
from ..optics.radiometry import entry_transmittance

__all__ = ["CONSTANT_BOUNDS", "CONSTANT_NAMES", "constant_bounds", "constant_defaults", "point_reflectance"]

#: The constants a point fit may free, and the range each may take. Thickness: 0.1–0.5 mm spans the
#: epidermis from thin facial skin to the thick forearm and dorsal hand (DWRR08 §5.1 fixes 0.25 mm);
#: oxygenation: the whole fraction range; the dermis's scattering relative to the epidermis's: from a
#: sixteenth to four times (DWRR08 fixes one half; docs/model.md shows that a ratio of 1–2 removes the
#: diffusion model's deficit against transport, so the upper end is there for a reason).
CONSTANT_BOUNDS = {
    "epidermis_thickness_mm": (0.1, 0.5),
    "oxygenation_dermis": (0.0, 1.0),
    "dermis_scattering_ratio": (0.0625, 4.0),
}
CONSTANT_NAMES = tuple(CONSTANT_BOUNDS)
#: The multipole's source lies one transport mean free path ℓ = 1/σt′ below the surface and must lie
#: inside the layer (``SlabOptics.build``): the thinnest epidermis a fit may reach is this factor above
#: the longest ℓ at its bands (1/min σs′, since σt′ ≥ σs′).
_THICKNESS_MARGIN = 1.02


def constant_defaults(model: SkinModel) -> dict[str, float]:
    """The settings' values of the freeable constants (what the fixed model uses)."""
    o = model.settings.optics
    return {name: float(getattr(o, name)) for name in CONSTANT_NAMES}


def constant_bounds(model: SkinModel, wavelength_nm: torch.Tensor, names) -> tuple[torch.Tensor, torch.Tensor]:
    """``(lo, hi)`` ``(len(names),)`` float64 of the named constants at these bands: ``CONSTANT_BOUNDS``,
    the thickness's lower bound raised where the multipole's source would leave the layer."""
    lo, hi = [], []
    for name in names:
        a, b = CONSTANT_BOUNDS[name]
        if name == "epidermis_thickness_mm" and model.settings.optics.source_depth == "mean_free_path":
            longest_ell = 1.0 / float(model.spectra(wavelength_nm).scattering_epidermis.min())
            a = max(a, _THICKNESS_MARGIN * longest_ell)
        if a >= b:
            raise ValueError(f"{name}: no room between its bounds at these bands ({a:.4g} ≥ {b:.4g})")
        lo.append(a)
        hi.append(b)
    return torch.tensor(lo, dtype=torch.float64), torch.tensor(hi, dtype=torch.float64)


def point_reflectance(
    model: SkinModel, params: SkinParams, wavelength_nm: torch.Tensor, constants: dict[str, torch.Tensor] | None = None
) -> torch.Tensor:
    """R_d ``(B, L)`` of the homogeneous two-layer model (exact diffusion totals), with each named
    constant ``(B,)`` in place of the settings' value; equal to ``model.diffuse_reflectance`` when none
    is given. Differentiable in the parameters and the constants."""
    constants = constants or {}
    unknown = set(constants) - set(CONSTANT_NAMES)
    if unknown:
        raise ValueError(f"unknown constants {sorted(unknown)}; choose from {CONSTANT_NAMES}")
    if model.settings.profiles != "diffusion":
        raise ValueError("freeing the model's constants needs profiles: diffusion (the multipole's closed form)")
    o = model.settings.optics
    ref = params.C_m
    spectra = model.spectra(wavelength_nm).to(ref.device, ref.dtype)
    column = {name: value.to(ref)[..., None] for name, value in constants.items()}  # (B, 1)
    if "oxygenation_dermis" in column:
        g = column["oxygenation_dermis"]
        spectra = dataclasses.replace(spectra, blood_dermis=g * spectra.oxy_blood + (1.0 - g) * spectra.deoxy_blood)
    if "dermis_scattering_ratio" in column:
        spectra = dataclasses.replace(
            spectra, scattering_dermis=column["dermis_scattering_ratio"] * spectra.scattering_epidermis)
    thickness = column.get("epidermis_thickness_mm")
    ab = layer_absorption(params, spectra, o.interface_melanin_fraction,
                          o.epidermis_thickness_mm if thickness is None else thickness)
    totals = model.transforms_at(ab.epidermis, ab.dermis, ab.interface_absorbance, wavelength_nm, None, "exact", spectra,
                                 thickness_mm=thickness)
    return entry_transmittance(o.n_epidermis, o.n_above) * combine_layers(totals)
