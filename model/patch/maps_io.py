"""Parameter maps on disk as the renderer's ``SkinMaps``: the file format is ``formats/maps.py``; this
module adds the tensors' dtype and device and the physical checks (``SkinMaps.validate``)."""

from __future__ import annotations

from pathlib import Path

import torch

from ...formats.maps import read_map_file, write_map_file
from .maps import SkinMaps
from ..optics.params import PARAMETER_NAMES

__all__ = ["read_maps", "write_maps"]


def read_maps(path: str | Path, dtype: torch.dtype = torch.float32, device=None) -> SkinMaps:
    """Read and validate a maps file (B = 1)."""
    f = read_map_file(path)
    tensor = lambda a: a.to(dtype=dtype, device=device)[None]  # noqa: E731
    absorbance = None if f.absorbance is None else f.absorbance.to(dtype=dtype, device=device)[None]
    return SkinMaps(
        **{n: tensor(f.params[n]) for n in PARAMETER_NAMES}, mm_per_pixel=f.mm_per_pixel,
        rho_s=None if f.rho_s is None else tensor(f.rho_s), absorbance=absorbance, absorbance_wavelength_nm=f.absorbance_wavelength_nm,
    ).validate(str(path))


def write_maps(path: str | Path, maps: SkinMaps, extra: dict[str, torch.Tensor] | None = None, attributes: dict | None = None,
               index: int = 0) -> Path:
    """Write item ``index`` of a batch of maps (and extra channels such as residuals)."""
    return write_map_file(
        path, {n: getattr(maps, n)[index] for n in PARAMETER_NAMES}, maps.mm_per_pixel,
        rho_s=None if maps.rho_s is None else maps.rho_s[index],
        absorbance=None if maps.absorbance is None else maps.absorbance[index],
        absorbance_wavelength_nm=maps.absorbance_wavelength_nm, extra=extra, attributes=attributes,
    )
