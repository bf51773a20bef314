"""The radiometric convention of skinlayers, written once and used by renderer, simulator and fit.

* Light in: the irradiance that enters the skin is Φ = F_t(θ_i) E, with F_t the smooth-surface
  Fresnel transmittance from the medium above into the epidermis (DWRR08 §6.2, after Jensen et al.
  2001: under gel the surface is smooth, F_t = 1 - F_r; the project's convention: docs/model.md,
  "Radiometric convention").
* Inside: layer profiles give radiant exitance M per unit entering power; M already includes the
  internal reflections at the boundaries.
* Light out: M is the flux that leaves the surface. Its radiance is taken to follow the smooth
  boundary's transmittance, L(θ_o) ∝ F_t(θ_o), normalised so that L integrates over the hemisphere to
  exactly M: L(θ_o) = M F_t(θ_o) / (π (1 - F_dr,ext)), with F_dr,ext the hemispherical average of the
  external Fresnel reflectance. (Jensen et al. 2001 use M F_t(θ_o) / π, which loses 1 - F_dr,ext ≈ 8%
  of the light; we keep energy.)
* What is reported: the *diffuse reflectance* R_d = M / E (hemispherical, specular excluded), and a
  camera's *reflectance factor* ρ(θ_o) = π L(θ_o) / E = R_d F_t(θ_o) / (1 - F_dr,ext), the ratio to an
  ideal white Lambertian target seen the same way (what Spectralon calibration measures).
"""

from __future__ import annotations

import math

import torch

from .fresnel import fresnel_reflectance, fresnel_transmittance

__all__ = ["entry_transmittance", "external_diffuse_reflectance", "exit_factor", "specular_reflectance"]


def entry_transmittance(n_skin: float, n_above: float = 1.0, cos_theta_i: float = 1.0) -> float:
    """F_t of collimated light entering the skin at incidence θ_i (unpolarised)."""
    return float(fresnel_transmittance(cos_theta_i, n_skin / n_above))


def specular_reflectance(n_skin: float, n_above: float = 1.0, cos_theta_i: float = 1.0) -> float:
    """F_r of the smooth surface: the first-surface reflection a sphere with specular included adds."""
    return float(fresnel_reflectance(cos_theta_i, n_skin / n_above))


def external_diffuse_reflectance(n_skin: float, n_above: float = 1.0, samples: int = 20001) -> float:
    """Hemispherical average of the external Fresnel reflectance, ∫ F_r(θ) 2 cos θ sin θ dθ."""
    mu = torch.linspace(0.0, 1.0, samples, dtype=torch.float64)
    return float(torch.trapezoid(fresnel_reflectance(mu, n_skin / n_above) * 2.0 * mu, mu))


def exit_factor(n_skin: float, n_above: float = 1.0, cos_theta_o: float = 1.0) -> float:
    """ρ(θ_o) / R_d = F_t(θ_o) / (1 - F_dr,ext): the reflectance factor a camera at θ_o sees per unit R_d."""
    return float(fresnel_transmittance(cos_theta_o, n_skin / n_above)) / (
        1.0 - external_diffuse_reflectance(n_skin, n_above)
    )


def degrees_to_cos(angle_deg: float) -> float:
    return math.cos(math.radians(angle_deg))
