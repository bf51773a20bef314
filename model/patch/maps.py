"""Parameter maps: the five chromophore maps, oiliness and optional interface absorbance, on a grid.

``SkinMaps`` is what the heterogeneous renderer draws: per pixel the DWRR08 Table 1 parameters,
batched ``(B, H, W)``, plus an optional user absorbance of the thin interface layer per wavelength
``(B, L, H, W)`` (veins, tattoos; DWRR08 §4.2, Fig. 1 and 15) and the pixel size in mm.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import torch

from ...formats.maps import MAP_CHANNELS, MAX_MM_PER_PIXEL, MIN_MM_PER_PIXEL, MapsError
from ..optics.params import PARAMETER_BOUNDS, PARAMETER_NAMES, SkinParams

__all__ = ["MAP_CHANNELS", "MapsError", "SkinMaps"]


@dataclass(frozen=True)
class SkinMaps:
    """Per-pixel skin parameters ``(B, H, W)`` and the grid's pixel size.

    ``absorbance`` ``(B, L, H, W)`` is extra absorbance P of the interface layer (dimensionless,
    A = e^-P) at ``absorbance_wavelength_nm`` ``(L,)``; it adds to the 17.5% melanin share.
    """

    C_m: torch.Tensor
    beta_m: torch.Tensor
    C_he: torch.Tensor
    C_bc: torch.Tensor
    C_hd: torch.Tensor
    mm_per_pixel: float
    rho_s: torch.Tensor | None = None
    absorbance: torch.Tensor | None = None
    absorbance_wavelength_nm: torch.Tensor | None = None

    @classmethod
    def uniform(
        cls, params: dict[str, float], shape: tuple[int, int], mm_per_pixel: float, batch: int = 1,
        dtype: torch.dtype = torch.float32, device: torch.device | str | None = None,
    ) -> "SkinMaps":
        """Homogeneous maps of one parameter set (``rho_s`` optional in ``params``)."""
        full = lambda v: torch.full((batch, *shape), float(v), dtype=dtype, device=device)  # noqa: E731
        rho = params.get("rho_s")
        base = {n: full(params[n]) for n in PARAMETER_NAMES}
        return cls(**base, mm_per_pixel=float(mm_per_pixel), rho_s=None if rho is None else full(rho))

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self.C_m.shape)  # type: ignore[return-value]

    @property
    def device(self) -> torch.device:
        return self.C_m.device

    @property
    def dtype(self) -> torch.dtype:
        return self.C_m.dtype

    def params(self) -> SkinParams:
        return SkinParams(self.C_m, self.beta_m, self.C_he, self.C_bc, self.C_hd)

    def channel(self, name: str) -> torch.Tensor:
        if name == "rho_s":
            return self.rho_s if self.rho_s is not None else torch.zeros_like(self.C_m)
        return getattr(self, name)

    def replace(self, **changes) -> "SkinMaps":
        return replace(self, **changes)

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> "SkinMaps":
        out = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, torch.Tensor):
                keep_dtype = f.name == "absorbance_wavelength_nm"
                v = v.to(device=device, dtype=None if keep_dtype else dtype)
            out[f.name] = v
        return SkinMaps(**out)

    def validate(self, source: str = "maps") -> "SkinMaps":
        """Refuse wrong shapes, NaN and values outside the physical ranges, naming the channel."""
        if not (MIN_MM_PER_PIXEL <= self.mm_per_pixel < MAX_MM_PER_PIXEL):
            raise MapsError(f"{source}: mm_per_pixel must be a pixel size of {MIN_MM_PER_PIXEL:g}–{MAX_MM_PER_PIXEL:g} mm, "
                            f"got {self.mm_per_pixel!r}")
        shape = self.C_m.shape
        if len(shape) != 3 or min(shape) < 1:
            raise MapsError(f"{source}: C_m must have shape (B, H, W), got {tuple(shape)}")
        for name in MAP_CHANNELS:
            v = self.rho_s if name == "rho_s" else getattr(self, name)
            if v is None:
                continue
            if v.shape != shape:
                raise MapsError(f"{source}: channel {name} has shape {tuple(v.shape)}, C_m has {tuple(shape)}")
            if not bool(torch.isfinite(v).all()):
                bad = int((~torch.isfinite(v)).sum())
                raise MapsError(f"{source}: channel {name} has {bad} NaN or infinite pixel(s)")
            lo, hi = PARAMETER_BOUNDS.get(name, (0.0, 1.0))
            if name in ("C_m", "C_he", "C_bc", "C_hd"):
                hi = 1.0  # physical limit: a volume fraction; Table 1's ranges are typical, not hard
            vmin, vmax = float(v.min()), float(v.max())
            if vmin < lo or vmax > hi:
                raise MapsError(f"{source}: channel {name} spans {vmin:g}–{vmax:g}, outside its physical range {lo:g}–{hi:g}")
        epi = self.C_m + self.C_he + self.C_bc
        if bool((epi > 1).any()):
            raise MapsError(f"{source}: C_m + C_he + C_bc exceeds 1 at {int((epi > 1).sum())} pixel(s)")
        if self.absorbance is not None:
            a = self.absorbance
            if a.ndim != 4 or a.shape[0] != shape[0] or a.shape[2:] != shape[1:]:
                raise MapsError(f"{source}: absorbance must be (B, L, H, W) matching the maps, got {tuple(a.shape)}")
            if self.absorbance_wavelength_nm is None or self.absorbance_wavelength_nm.numel() != a.shape[1]:
                raise MapsError(f"{source}: absorbance needs one wavelength per layer of its L axis")
            if not bool(torch.isfinite(a).all()) or bool((a < 0).any()):
                raise MapsError(f"{source}: absorbance must be finite and >= 0")
        return self
