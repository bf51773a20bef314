"""Edits of parameter maps: more or less of a chromophore, a chromophore taken from another patch, an
absorbing pattern in the interface layer (DWRR08 Fig. 1, 14, 15: blood flow, tan, tattoos, veins)."""

from __future__ import annotations

import re

import torch

from ...formats.errors import InputError
from .maps import MapsError, SkinMaps
from ..optics.params import PARAMETER_NAMES

__all__ = ["CHROMOPHORES", "add_absorbance", "apply_edit", "scale_chromophore", "swap_chromophore"]

#: Names an edit may use, and the maps each changes.
CHROMOPHORES: dict[str, tuple[str, ...]] = {
    **{n: (n,) for n in PARAMETER_NAMES},
    "melanin": ("C_m",),
    "tan": ("C_m",),
    "hemoglobin": ("C_he", "C_hd"),
    "blood": ("C_he", "C_hd"),
    "carotene": ("C_bc",),
}
_EDIT = re.compile(r"^\s*([A-Za-z_]+)\s*\*\s*([0-9.eE+-]+)\s*$")


def _maps_of(name: str) -> tuple[str, ...]:
    if name not in CHROMOPHORES:
        raise InputError(f"unknown chromophore {name!r}; use one of {', '.join(CHROMOPHORES)}")
    return CHROMOPHORES[name]


def scale_chromophore(maps: SkinMaps, name: str, factor: float) -> SkinMaps:
    """Multiply a chromophore's map(s) by ``factor`` (β_m is clipped to 0–1)."""
    if not factor >= 0:
        raise InputError(f"scale factor must be >= 0, got {factor}")
    changes = {}
    for channel in _maps_of(name):
        value = getattr(maps, channel) * factor
        changes[channel] = value.clamp(0.0, 1.0) if channel == "beta_m" else value
    return maps.replace(**changes).validate("edited maps")


def swap_chromophore(maps: SkinMaps, donor: SkinMaps, name: str) -> SkinMaps:
    """Take a chromophore's map(s) from another patch of the same size (DWRR08 Fig. 14, left)."""
    if donor.shape != maps.shape:
        raise MapsError(f"cannot take {name} from maps of shape {donor.shape} into maps of shape {maps.shape}")
    changes = {c: getattr(donor, c).to(maps.C_m) for c in _maps_of(name)}
    return maps.replace(**changes).validate("edited maps")


def add_absorbance(maps: SkinMaps, absorbance: torch.Tensor, wavelength_nm: torch.Tensor) -> SkinMaps:
    """Add an interface absorbance pattern ``(L, H, W)`` or ``(B, L, H, W)`` (tattoo ink, veins)."""
    a = absorbance.to(maps.C_m)
    if a.ndim == 3:
        a = a[None].expand(maps.shape[0], -1, -1, -1)
    if a.shape[-2:] != maps.shape[-2:]:
        raise MapsError(f"absorbance of size {tuple(a.shape[-2:])} does not fit maps of size {maps.shape[-2:]}")
    wl = torch.as_tensor(wavelength_nm, dtype=torch.float64).reshape(-1)
    if maps.absorbance is not None:
        if maps.absorbance_wavelength_nm is None or not torch.equal(maps.absorbance_wavelength_nm.cpu(), wl.cpu()):
            raise MapsError("both absorbance patterns must be given at the same wavelengths to be added")
        a = a + maps.absorbance
    return maps.replace(absorbance=a, absorbance_wavelength_nm=wl).validate("edited maps")


def apply_edit(maps: SkinMaps, text: str) -> SkinMaps:
    """``NAME*FACTOR``, e.g. ``hemoglobin*1.5`` or ``melanin*0.5``."""
    m = _EDIT.match(text)
    if not m:
        raise InputError(f"--edit {text!r}: expected NAME*FACTOR, e.g. hemoglobin*1.5")
    try:
        factor = float(m.group(2))
    except ValueError:
        raise InputError(f"--edit {text!r}: {m.group(2)!r} is not a number") from None
    return scale_chromophore(maps, m.group(1), factor)
