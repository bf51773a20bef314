"""The skin parameters (DWRR08 Table 1) and the layers' absorption they imply (Eq. 11, 12, 8).

``SkinParams`` holds the five chromophore fractions as tensors of any common (broadcastable) batch
shape ``(...)``: a single spectrum (``()``), a batch of spectra (``(B,)``) or maps (``(B, H, W)``).
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Mapping

import torch

from ...formats.errors import InputError
from ...formats.maps import PARAMETER_NAMES
from .spectra import ChromophoreSpectra

__all__ = [
    "N_PARAMS",
    "PARAMETER_BOUNDS",
    "PARAMETER_NAMES",
    "TABLE2",
    "LayerAbsorption",
    "SkinParams",
    "layer_absorption",
    "layer_absorption_jacobian",
    "parameter_bounds",
]

#: Chromophore parameters per pixel: the width of every per-pixel tensor ``(N, N_PARAMS)``.
N_PARAMS = len(PARAMETER_NAMES)

#: Typical ranges of DWRR08 Table 1, used as the bounds of every fit.
PARAMETER_BOUNDS: dict[str, tuple[float, float]] = {
    "C_m": (0.0, 0.5),
    "beta_m": (0.0, 1.0),
    "C_he": (0.0, 0.05),
    "C_bc": (0.0, 0.05),
    "C_hd": (0.0, 0.1),
}


def parameter_bounds(dtype: torch.dtype = torch.float64, device=None) -> tuple[torch.Tensor, torch.Tensor]:
    """``PARAMETER_BOUNDS`` as lower and upper bound tensors ``(N_PARAMS,)``, in the order of ``PARAMETER_NAMES``."""
    lo = torch.tensor([PARAMETER_BOUNDS[n][0] for n in PARAMETER_NAMES], dtype=dtype, device=device)
    hi = torch.tensor([PARAMETER_BOUNDS[n][1] for n in PARAMETER_NAMES], dtype=dtype, device=device)
    return lo, hi


#: DWRR08 Table 2: mean parameters per Fitzpatrick type, lower arm (β_m to the paper's digits).
TABLE2: dict[str, dict[str, float]] = {
    "I interior": dict(C_he=0.000184, C_hd=0.004133, C_m=0.000126, beta_m=0.0238095, C_bc=0.000240),
    "II interior": dict(C_he=0.002971, C_hd=0.007399, C_m=0.00571, beta_m=0.833975, C_bc=0.000010),
    "III interior": dict(C_he=0.001441, C_hd=0.004674, C_m=0.005364, beta_m=0.151566, C_bc=0.000081),
    "IV interior": dict(C_he=0.002359, C_hd=0.004503, C_m=0.013851, beta_m=0.11501, C_bc=0.001105),
    "I exterior": dict(C_he=0.001933, C_hd=0.005001, C_m=0.002346, beta_m=0.0767263, C_bc=0.001543),
    "II exterior": dict(C_he=0.000342, C_hd=0.004226, C_m=0.002718, beta_m=0.894776, C_bc=0.000000),
    "III exterior": dict(C_he=0.001766, C_hd=0.004072, C_m=0.009446, beta_m=0.143447, C_bc=0.000113),
    "IV exterior": dict(C_he=0.003252, C_hd=0.006598, C_m=0.019121, beta_m=0.137964, C_bc=0.002384),
    "V exterior": dict(C_he=0.006558, C_hd=0.012924, C_m=0.038484, beta_m=0.0603627, C_bc=0.006445),
}


@dataclass(frozen=True)
class SkinParams:
    """Melanin fraction, melanin blend, epidermal blood, carotene, dermal blood; each ``(...)``."""

    C_m: torch.Tensor
    beta_m: torch.Tensor
    C_he: torch.Tensor
    C_bc: torch.Tensor
    C_hd: torch.Tensor

    @classmethod
    def from_mapping(
        cls, values: Mapping[str, object], *, dtype: torch.dtype = torch.float64, device: torch.device | str | None = None
    ) -> "SkinParams":
        """Build from a mapping with exactly the five keys; refuses unknown or missing keys."""
        unknown = sorted(set(values) - set(PARAMETER_NAMES))
        if unknown:
            raise InputError(f"unknown parameter(s): {', '.join(unknown)} (expected {', '.join(PARAMETER_NAMES)})")
        missing = [n for n in PARAMETER_NAMES if n not in values]
        if missing:
            raise InputError(f"missing parameter(s): {', '.join(missing)}")
        return cls(**{n: torch.as_tensor(values[n], dtype=dtype, device=device) for n in PARAMETER_NAMES})

    @classmethod
    def from_tensor(cls, x: torch.Tensor) -> "SkinParams":
        """From ``(..., N_PARAMS)`` in the order of ``PARAMETER_NAMES``."""
        return cls(*x.unbind(-1))

    def as_tensor(self) -> torch.Tensor:
        """``(..., N_PARAMS)`` in the order of ``PARAMETER_NAMES``."""
        return torch.stack(torch.broadcast_tensors(*self.values()), dim=-1)

    def values(self) -> tuple[torch.Tensor, ...]:
        return tuple(getattr(self, f.name) for f in fields(self))

    def to_dict(self) -> dict[str, object]:
        return {n: getattr(self, n).tolist() for n in PARAMETER_NAMES}

    def validate(self) -> "SkinParams":
        """Refuse NaN, negative fractions, β_m outside 0–1 and fractions that over-fill a layer."""
        for name in PARAMETER_NAMES:
            v = getattr(self, name)
            if not bool(torch.isfinite(v).all()):
                raise InputError(f"{name} must be a finite number")
            if bool((v < 0).any()):
                raise InputError(f"{name} must be >= 0 (a volume fraction), got {float(v.min()):g}")
        if bool((self.beta_m > 1).any()):
            raise InputError(f"beta_m must be <= 1 (the eumelanin share), got {float(self.beta_m.max()):g}")
        epi = self.C_m + self.C_he + self.C_bc
        if bool((epi > 1).any()):
            raise InputError(f"C_m + C_he + C_bc must be <= 1 (epidermal volume fractions), got {float(epi.max()):g}")
        if bool((self.C_hd > 1).any()):
            raise InputError(f"C_hd must be <= 1 (a volume fraction), got {float(self.C_hd.max()):g}")
        return self


@dataclass(frozen=True)
class LayerAbsorption:
    """σa of epidermis and dermis (mm⁻¹) and the interface absorbance from melanin; each ``(..., L)``."""

    epidermis: torch.Tensor
    dermis: torch.Tensor
    interface_absorbance: torch.Tensor


def layer_absorption(
    params: SkinParams, spectra: ChromophoreSpectra, interface_melanin_fraction: float, epidermis_thickness_mm: float
) -> LayerAbsorption:
    """Eq. 11 (epidermis), Eq. 12 (dermis) and the melanin part of the interface absorbance (§5.1).

    P_mel = f · C_m (β_m σa_em + (1-β_m) σa_pm) · d_epi with f = 0.175.
    """
    s = spectra

    def col(x: torch.Tensor) -> torch.Tensor:
        return x[..., None]

    melanin = col(params.beta_m) * s.eumelanin + (1.0 - col(params.beta_m)) * s.pheomelanin
    c_m, c_he, c_bc, c_hd = col(params.C_m), col(params.C_he), col(params.C_bc), col(params.C_hd)
    epi = (
        c_m * melanin
        + c_he * s.blood_epidermis
        + c_bc * s.carotene
        + (1.0 - c_m - c_he - c_bc) * s.baseline
    )
    derm = c_hd * s.blood_dermis + (1.0 - c_hd) * s.baseline
    interface = interface_melanin_fraction * c_m * melanin * epidermis_thickness_mm
    return LayerAbsorption(epi, derm, interface)


def layer_absorption_jacobian(
    params: SkinParams, spectra: ChromophoreSpectra, interface_melanin_fraction: float, epidermis_thickness_mm: float
) -> torch.Tensor:
    """∂(σa_epi, σa_derm, P_mel)/∂(parameters) of ``layer_absorption``, ``(3, ..., L, N_PARAMS)`` in the
    order of ``PARAMETER_NAMES``: Eq. 11–12 are linear in each parameter, so each column is a difference
    of chromophore spectra weighted by the others."""
    s = spectra
    beta, c_m = params.beta_m[..., None], params.C_m[..., None]
    melanin = beta * s.eumelanin + (1.0 - beta) * s.pheomelanin
    shape = melanin.shape
    zero = torch.zeros(shape, dtype=melanin.dtype, device=melanin.device)
    d_melanin = (s.eumelanin - s.pheomelanin).expand(shape)
    f_d = interface_melanin_fraction * epidermis_thickness_mm
    columns = {
        "C_m": (melanin - s.baseline, zero, f_d * melanin),
        "beta_m": (c_m * d_melanin, zero, f_d * c_m * d_melanin),
        "C_he": ((s.blood_epidermis - s.baseline).expand(shape), zero, zero),
        "C_bc": ((s.carotene - s.baseline).expand(shape), zero, zero),
        "C_hd": (zero, (s.blood_dermis - s.baseline).expand(shape), zero),
    }
    return torch.stack([torch.stack([columns[n][k] for n in PARAMETER_NAMES], -1) for k in range(3)])
