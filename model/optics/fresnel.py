"""Fresnel terms of smooth dielectric boundaries.

Relative index ``eta`` is always the index of the medium the light is in over the index of the
medium beyond the boundary (Donner & Jensen 2005; indices 1.40 and 1.38 from DWRR08 §5.1): the
epidermis under air has ``eta = 1.40``, the dermis under the epidermis ``eta = 1.38 / 1.40``.
"""

from __future__ import annotations

import torch

__all__ = [
    "diffuse_fresnel_reflectance",
    "extrapolation_factor",
    "fresnel_reflectance",
    "fresnel_transmittance",
]


def diffuse_fresnel_reflectance(eta: torch.Tensor | float) -> torch.Tensor:
    """Hemispherical (diffuse) Fresnel reflectance F_dr(eta) of the boundary, seen from inside.

    Egan & Hilgeman's rational fits (as used by Jensen et al. 2001 and Donner & Jensen 2005):
    ``-1.440/eta^2 + 0.710/eta + 0.668 + 0.0636 eta`` for ``eta >= 1`` and
    ``-0.4399 + 0.7099/eta - 0.3319/eta^2 + 0.0636/eta^3`` for ``eta < 1``.
    """
    # Python numbers are taken in float64 (torch's default dtype would round A to float32)
    eta = torch.as_tensor(eta, dtype=eta.dtype if torch.is_tensor(eta) else torch.float64)
    above = -1.440 / eta**2 + 0.710 / eta + 0.668 + 0.0636 * eta
    below = -0.4399 + 0.7099 / eta - 0.3319 / eta**2 + 0.0636 / eta**3
    return torch.where(eta >= 1.0, above, below)


def extrapolation_factor(eta: torch.Tensor | float) -> torch.Tensor:
    """A = (1 + F_dr) / (1 - F_dr): the boundary's internal-reflection factor; z_b = 2 A D."""
    fdr = diffuse_fresnel_reflectance(eta)
    return (1.0 + fdr) / (1.0 - fdr)


def fresnel_reflectance(cos_theta: torch.Tensor | float, eta: torch.Tensor | float) -> torch.Tensor:
    """Unpolarised Fresnel reflectance for light arriving from outside a medium of relative index eta.

    ``cos_theta`` is the cosine of the angle of incidence in the outer medium; ``eta`` is the index of
    the medium being entered over the index of the one the light comes from (1.40 for air to skin).
    Total internal reflection (possible for ``eta < 1``) returns 1.
    """
    cos_i = torch.as_tensor(cos_theta, dtype=torch.float64)
    eta = torch.as_tensor(eta, dtype=cos_i.dtype)
    sin2_t = (1.0 - cos_i**2) / eta**2
    tir = sin2_t >= 1.0
    cos_t = torch.sqrt(torch.clamp(1.0 - sin2_t, min=0.0))
    r_s = (cos_i - eta * cos_t) / (cos_i + eta * cos_t)
    r_p = (eta * cos_i - cos_t) / (eta * cos_i + cos_t)
    r = 0.5 * (r_s**2 + r_p**2)
    return torch.where(tir, torch.ones_like(r), r)


def fresnel_transmittance(cos_theta: torch.Tensor | float, eta: torch.Tensor | float) -> torch.Tensor:
    """1 - fresnel_reflectance: the fraction of collimated light that crosses a smooth boundary."""
    return 1.0 - fresnel_reflectance(cos_theta, eta)
