"""The parameter-map file format (``maps.exr``) and the interface-absorbance format (``ink.exr``).

**Maps**: one float32 channel per parameter named exactly ``C_m``, ``beta_m``, ``C_he``, ``C_bc``,
``C_hd`` (DWRR08 Table 1: melanin fraction, eumelanin share of it, epidermal blood, β-carotene, dermal
blood; all fractions 0–1), optionally ``rho_s`` (surface oiliness); optionally interface absorbance
channels ``P_<nm>`` (one per wavelength, dimensionless, transmittance e^-P); the header attribute
``mm_per_pixel`` (float). Other channels (a fit's ``residual_rms``, ``res_<nm>``, ``flags``,
``sigma_<param>``) are carried along and kept in ``MapFile.extra``.

**Absorbance** (veins, tattoos): channels ``P_<nm>`` and ``mm_per_pixel``.

This module reads and writes the file; ``model.maps_io`` turns it into the renderer's ``SkinMaps`` and
checks the physical ranges.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import torch

from .exr import ExrError, band_channels, float_attribute, read_exr, write_exr

__all__ = ["MAP_CHANNELS", "MAX_MM_PER_PIXEL", "MIN_MM_PER_PIXEL", "PARAMETER_NAMES", "MapFile", "MapsError", "read_absorbance", "read_map_file", "write_map_file"]

#: The five chromophore parameters, in the order every per-pixel tensor ``(N, N_PARAMS)`` holds them.
PARAMETER_NAMES = ("C_m", "beta_m", "C_he", "C_bc", "C_hd")
#: Channel names of the map format, in order; ``rho_s`` is optional.
MAP_CHANNELS = (*PARAMETER_NAMES, "rho_s")
#: A pixel's side on the skin (mm): above a tenth of a micrometre (below that no optics resolves it, and
#: a millimetre of border would take ten thousand pixels), below a centimetre.
MIN_MM_PER_PIXEL, MAX_MM_PER_PIXEL = 1e-4, 10.0


class MapsError(ExrError):
    """Maps that cannot be read or rendered; the message names the file or channel and the problem."""


@dataclass
class MapFile:
    """A maps file's content: ``params`` name → ``(H, W)`` float32, ``absorbance`` ``(L, H, W)`` at
    ``absorbance_wavelength_nm`` ``(L,)``, every other channel in ``extra``, the header."""

    params: dict[str, torch.Tensor]
    mm_per_pixel: float
    rho_s: torch.Tensor | None = None
    absorbance: torch.Tensor | None = None
    absorbance_wavelength_nm: torch.Tensor | None = None
    extra: dict[str, torch.Tensor] = field(default_factory=dict)
    header: dict = field(default_factory=dict)


def read_map_file(path: str | Path) -> MapFile:
    """Read a maps file; ``MapsError`` names the file and what is missing."""
    path = Path(path)
    channels, header = read_exr(path, MapsError)
    missing = [n for n in PARAMETER_NAMES if n not in channels]
    if missing:
        raise MapsError(f"{path}: missing channel(s) {', '.join(missing)} (has: {', '.join(sorted(channels)) or 'none'})")
    mm = float_attribute(header, "mm_per_pixel", path, MapsError)
    tensor = lambda a: torch.from_numpy(a.copy())  # noqa: E731
    bands = band_channels(channels, "P")
    absorbance = wl = None
    if bands:
        absorbance = torch.stack([tensor(channels[n]) for _, n in bands])
        wl = torch.tensor([w for w, _ in bands], dtype=torch.float64)
    taken = {*MAP_CHANNELS, *(n for _, n in bands)}
    return MapFile(
        {n: tensor(channels[n]) for n in PARAMETER_NAMES}, mm, tensor(channels["rho_s"]) if "rho_s" in channels else None,
        absorbance, wl, {n: tensor(a) for n, a in channels.items() if n not in taken}, header,
    )


def write_map_file(
    path: str | Path, params: dict[str, torch.Tensor], mm_per_pixel: float, *, rho_s: torch.Tensor | None = None,
    absorbance: torch.Tensor | None = None, absorbance_wavelength_nm: torch.Tensor | None = None,
    extra: dict[str, torch.Tensor] | None = None, attributes: dict | None = None,
) -> Path:
    """Write maps ``(H, W)`` each (and extra channels such as residuals) atomically."""
    channels: dict[str, torch.Tensor] = {n: params[n] for n in PARAMETER_NAMES}
    if rho_s is not None:
        channels["rho_s"] = rho_s
    if absorbance is not None and absorbance_wavelength_nm is not None:
        for j, w in enumerate(absorbance_wavelength_nm.tolist()):
            channels[f"P_{w:g}"] = absorbance[j]
    for name, value in (extra or {}).items():
        if name in MAP_CHANNELS:
            raise ValueError(f"extra channel {name} would overwrite a parameter")
        channels[name] = value
    return write_exr(path, channels, {"mm_per_pixel": float(mm_per_pixel), **(attributes or {})})


def read_absorbance(path: str | Path) -> tuple[torch.Tensor, torch.Tensor, float]:
    """An interface absorbance file: ``(L, H, W)`` absorbance, ``(L,)`` wavelengths, mm per pixel."""
    path = Path(path)
    channels, header = read_exr(path, MapsError)
    bands = band_channels(channels, "P")
    if not bands:
        raise MapsError(f"{path}: no absorbance channels P_<nm> (has: {', '.join(sorted(channels)) or 'none'})")
    stack = torch.stack([torch.from_numpy(channels[n].copy()) for _, n in bands])
    for (w, n), layer in zip(bands, stack):
        if not bool(torch.isfinite(layer).all()) or bool((layer < 0).any()):
            raise MapsError(f"{path}: channel {n} must be finite and >= 0")
    return stack, torch.tensor([w for w, _ in bands], dtype=torch.float64), float_attribute(header, "mm_per_pixel", path, MapsError)
