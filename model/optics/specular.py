"""The surface's specular term: Torrance–Sparrow with a Beckmann distribution (DWRR08 §5.1, after
Donner & Jensen 2006), scaled per pixel by the oiliness ρ_s.

Returned as a *reflectance factor* π f_r cos θ_i (the ratio to an ideal white Lambertian surface
seen the same way), so it adds directly to the subsurface reflectance factor. Under gel with crossed
polarizers (the measurement) the renderer leaves it out.
"""

from __future__ import annotations

import math

import torch

from .fresnel import fresnel_reflectance

__all__ = ["torrance_sparrow_factor"]


def torrance_sparrow_factor(cos_light: float, cos_view: float, azimuth_deg: float, eta: float, roughness: float) -> float:
    """π f_r(ω_i, ω_o) cos θ_i for a smooth-facet dielectric of relative index ``eta``.

    f_r = F(ω_i·h) D(h) G / (4 cos θ_i cos θ_o), Beckmann D = exp(-tan²θ_h/m²) / (π m² cos⁴θ_h),
    Cook–Torrance shadowing G = min(1, 2 cosθ_h cosθ_o / (ω_o·h), 2 cosθ_h cosθ_i / (ω_o·h)).
    Light and view directions: polar angles from the normal, ``azimuth_deg`` between their planes.
    """
    if not (0 < cos_light <= 1 and 0 < cos_view <= 1):
        return 0.0
    sin_l, sin_v = math.sqrt(1 - cos_light**2), math.sqrt(1 - cos_view**2)
    phi = math.radians(azimuth_deg)
    wi = (sin_l, 0.0, cos_light)
    wo = (sin_v * math.cos(phi), sin_v * math.sin(phi), cos_view)
    hx, hy, hz = wi[0] + wo[0], wi[1] + wo[1], wi[2] + wo[2]
    norm = math.sqrt(hx * hx + hy * hy + hz * hz)
    hx, hy, hz = hx / norm, hy / norm, hz / norm
    cos_h = hz
    vh = wo[0] * hx + wo[1] * hy + wo[2] * hz
    tan2 = (1 - cos_h**2) / cos_h**2
    d = math.exp(-tan2 / roughness**2) / (math.pi * roughness**2 * cos_h**4)
    g = min(1.0, 2 * cos_h * cos_view / vh, 2 * cos_h * cos_light / vh)
    f = float(fresnel_reflectance(torch.tensor(vh, dtype=torch.float64), eta))
    brdf = f * d * g / (4 * cos_light * cos_view)
    return math.pi * brdf * cos_light
