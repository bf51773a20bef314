"""Benchmark: the dermis's point response, the Monte Carlo against the dipole whose shape the renderer
uses (run on demand: ``pytest -m bench tests/bench/test_transport_dermis_shape.py -s``).

III interior's dermis (a half-space of index 1.38 under the epidermis's 1.40) lit at one point by
Lambertian light from above the boundary (cosine-weighted in the epidermis, refracted, Fresnel
transmittance; what the epidermis hands the dermis), 200,000 photons tallied on 0.05-mm pixels over
±12 mm; the dipole (DWRR08 Eq. 3–5, ``profiles.dipole_profile``) integrated on a fine radial grid.
Writes ``transport_dermis_shape.csv``: per band and radius the share of the light that leaves beyond
it, each way (shapes only: the totals are compared elsewhere, and ``profiles: transport`` rescales
the dipole's to adding-doubling's). The Monte Carlo's radius is the pixel centre's (0.05-mm bins).
"""

from __future__ import annotations

import math

import pytest
import torch

from bench_io import write_csv

from skinlayers.model import TABLE2, ModelSettings
from skinlayers.model.optics.fresnel import fresnel_reflectance
from skinlayers.model.patch.maps import SkinMaps
from skinlayers.model.column.profiles import dipole_profile
from skinlayers.model.transport import Medium, TransportRenderer, walk

pytestmark = pytest.mark.bench

BANDS_NM = (460.0, 560.0, 640.0)
RADII_MM = (0.1, 0.25, 0.5, 1.0, 2.0, 3.75)
PHOTONS, PIXEL_MM, HALF_PX = 200_000, 0.05, 240


def test_the_dermis_point_response_against_the_dipole():
    o = ModelSettings().optics
    rows = []
    for band in BANDS_NM:
        skin = SkinMaps.uniform(TABLE2["III interior"], (1, 1), 1.0, dtype=torch.float64)
        med = TransportRenderer(ModelSettings())._medium(skin, 0, torch.tensor([band], dtype=torch.float64))
        sigma_a, sigma_s = float(med.sigma_a_per_mm[1, 0, 0]), med.sigma_s_per_mm[1]
        n = 2 * HALF_PX + 1
        dermis = Medium((math.inf,), (o.n_dermis,), o.n_epidermis, 1.0, (sigma_s,), 0.0,
                        torch.full((1, n, n), sigma_a, dtype=torch.float64), torch.ones(0, n, n, dtype=torch.float64), PIXEL_MM)
        g = torch.Generator().manual_seed(1)
        u = torch.rand(3, PHOTONS, dtype=torch.float64, generator=g)
        cos_above, eta = torch.sqrt(u[0]), o.n_dermis / o.n_epidermis
        sin2 = (1 - cos_above**2) / eta**2
        weight = torch.where(sin2 < 1, 1 - fresnel_reflectance(cos_above, eta).to(torch.float64), torch.zeros_like(cos_above))
        cos_in = torch.sqrt((1 - sin2).clamp_min(0)).clamp_min(1e-6)
        tally = walk(dermis, (u[1] - 0.5) * PIXEL_MM, (u[2] - 0.5) * PIXEL_MM, cos_in, weight, g,
                     azimuth=2 * math.pi * torch.rand(PHOTONS, dtype=torch.float64, generator=g))
        surface = tally.surface[0]
        centre = (torch.arange(n, dtype=torch.float64) - HALF_PX) * PIXEL_MM
        radius = torch.sqrt(centre[:, None] ** 2 + centre[None, :] ** 2)
        r = torch.linspace(5e-4, 12.0, 24_000, dtype=torch.float64)
        d = dipole_profile(r, torch.tensor([sigma_a], dtype=torch.float64), torch.tensor(sigma_s, dtype=torch.float64), eta).reshape(-1)
        cdf = torch.cumsum(2 * math.pi * r * d * (r[1] - r[0]), 0)
        for radius_mm in RADII_MM:
            rows.append({"band_nm": band, "sigma_a_per_mm": round(sigma_a, 4), "sigma_s_prime_per_mm": round(sigma_s, 3),
                         "radius_mm": radius_mm,
                         "share_beyond_mc": round(float(surface[radius > radius_mm].sum() / surface.sum()), 4),
                         "share_beyond_dipole": round(1 - float(cdf[int((r <= radius_mm).sum()) - 1] / cdf[-1]), 4)})
            print(rows[-1])
    write_csv("transport_dermis_shape.csv", rows, f"III interior dermis, {PHOTONS:,} photons, {PIXEL_MM} mm pixels")
    assert all(0.0 <= r["share_beyond_mc"] <= 1.0 for r in rows)
