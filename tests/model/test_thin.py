"""Thin geometry: transmission through epidermis – thin dermis – epidermis (DWRR08 §4.4)."""

from __future__ import annotations

import pytest
import torch

from skinlayers.model import TABLE2, SkinModel, SkinParams, multipole_totals
from skinlayers.model.render.illumination import Light
from skinlayers.model.patch.maps import SkinMaps
from skinlayers.model.optics.radiometry import entry_transmittance
from skinlayers.model.render.renderer import SkinRenderer
from skinlayers.model.render.thin import blend_thin, render_transmission

F64 = torch.float64
WL = torch.tensor([450.0, 600.0, 700.0], dtype=F64)


@pytest.fixture(scope="module")
def renderer(tmp_path_factory) -> SkinRenderer:
    return SkinRenderer(cache_dir=str(tmp_path_factory.mktemp("tables")))


def closed_form_transmission(row: dict, dermis_mm: float, round_trips: int = 2) -> torch.Tensor:
    """The paper's truncated series with each layer's plane integrals (the Fourier domain at k = 0)."""
    model = SkinModel()
    o = model.settings.optics
    s = model.spectra(WL)
    ab = model.absorption(SkinParams.from_mapping(row), s)
    epi = multipole_totals(ab.epidermis, s.scattering_epidermis, o.epidermis_thickness_mm,
                           o.n_epidermis / o.n_above, o.n_epidermis / o.n_dermis)
    eta = o.n_dermis / o.n_epidermis
    derm = multipole_totals(ab.dermis, s.scattering_dermis, dermis_mm, eta, eta, source_depth="capped")
    a = torch.exp(-ab.interface_absorbance)
    back = sum((derm.R_plus * a * epi.R_minus * a) ** m for m in range(round_trips + 1))
    front = sum((epi.R_minus * a * derm.R_minus * a) ** m for m in range(round_trips + 1))
    return entry_transmittance(o.n_epidermis) * epi.T_plus * a * back * derm.T_plus * a * front * epi.T_minus


@pytest.mark.parametrize("row, dermis_mm", [("I interior", 1.0), ("IV exterior", 2.0)])
def test_homogeneous_slab_matches_the_closed_form(renderer, row, dermis_mm):
    maps = SkinMaps.uniform(TABLE2[row], (16, 16), 0.05)
    result = render_transmission(renderer, maps, Light("uniform"), WL, dermis_mm)
    expected = closed_form_transmission(TABLE2[row], dermis_mm)
    assert float((result.exitance[0].double() / expected[:, None, None] - 1).abs().max()) < 0.005
    assert bool((expected[2] > expected[0]))  # red light crosses an ear, blue does not


def test_back_lit_spot_glows_through_and_spreads(renderer):
    maps = SkinMaps.uniform(TABLE2["II interior"], (64, 64), 0.05)
    spot = render_transmission(renderer, maps, Light("window", size_mm=0.6, border_mm=3.0), WL, 1.0).exitance[0]
    centre = spot[:, 32, 32]
    assert bool((centre > 0).all())
    assert bool((spot[:, 32, 45] < centre).all()) and bool((spot[:, 32, 45] > 0.01 * centre).all())
    energy_in = 0.6 * 0.6 * entry_transmittance(1.4)
    assert float(spot.sum((-1, -2)).max() * 0.05**2) < energy_in


def test_blend_thin_eq10():
    r, t = torch.tensor([0.4]), torch.tensor([0.1])
    torch.testing.assert_close(blend_thin(r, t, 1.0), r)
    torch.testing.assert_close(blend_thin(r, t, -1.0), t)
    torch.testing.assert_close(blend_thin(r, t, 0.0), 0.5 * (r + t))


def test_mismatched_sides_are_refused(renderer):
    front = SkinMaps.uniform(TABLE2["I interior"], (8, 8), 0.05)
    back = SkinMaps.uniform(TABLE2["I interior"], (8, 9), 0.05)
    with pytest.raises(ValueError, match="same grid"):
        render_transmission(renderer, front, Light("uniform"), WL, 1.0, back)
