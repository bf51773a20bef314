"""A residual with a shape (``reconstruct/diagnosis/structure.py``): a vein's stripe above the noise is
flagged along its length and named with its bands; white noise alone flags nothing."""

from __future__ import annotations

import torch

from skinlayers.reconstruct.diagnosis.structure import STRUCTURE_SIGMA_ON, find_structure, structure_notes, structure_widening

BANDS_NM = [430.0 + 30.0 * j for j in range(9)]
MM = 0.05


def _noise(seed: int, sigma: float = 0.005, size: int = 96) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.randn(len(BANDS_NM), size, size, generator=g, dtype=torch.float64) * sigma


def test_white_noise_is_not_structure():
    mask = torch.ones(96, 96, dtype=torch.bool)
    for seed in range(3):
        found = find_structure(_noise(seed), mask, BANDS_NM, torch.ones(9, dtype=torch.bool), MM)
        assert found.count == 0 and structure_notes(found, 96 * 96) == []


def test_a_veins_stripe_is_flagged_along_its_length_with_its_bands_and_its_sigma_widened():
    residual = _noise(1)
    x = torch.arange(96)
    stripe = ((x - 40).abs() <= 3)[None].expand(96, 96)
    for j, sign in ((2, 1.0), (3, 1.0), (4, -1.0), (5, -1.0)):  # ±1.2 noise σ in 490–580 nm: a vein's blood
        residual[j] += sign * 0.006 * stripe
    mask = torch.ones(96, 96, dtype=torch.bool)
    used = torch.ones(9, dtype=torch.bool)
    found = find_structure(residual, mask, BANDS_NM, used, MM)
    assert bool((found.flagged & stripe).any(1).all())  # along its whole length
    assert float(found.flagged[stripe].float().mean()) >= 0.8  # its edges, where the smoothing halves it, may drop
    away = (x - 40).abs() > 8  # beyond the smoothing's reach
    assert float(found.flagged[:, away].float().mean()) <= 0.01
    assert found.bands_nm == [490.0, 520.0, 550.0, 580.0] and found.regions == 1
    note = structure_notes(found, 96 * 96)
    assert len(note) == 1 and "490, 520, 550, 580 nm" in note[0]
    widening = structure_widening(found.flagged, residual, used, mask, ["C_m", "C_hd"]).reshape(2, 96, 96)
    assert bool((widening[:, ~found.flagged] == 1).all()) and float(widening[0][stripe].median()) > 1.2
    assert torch.allclose(widening[1], widening[0] * torch.where(found.flagged, STRUCTURE_SIGMA_ON["C_hd"], 1.0).double())


def test_a_band_left_out_of_the_fit_is_not_searched_and_an_offset_is_no_shape():
    residual = _noise(2)
    residual[0, :, :48] += 0.01  # a dead band's step: not in the loss, not searched
    residual[5] += 0.01  # an offset of a whole band: the band-bias check's, not a shape
    used = torch.ones(9, dtype=torch.bool)
    used[0] = False
    mask = torch.ones(96, 96, dtype=torch.bool)
    assert find_structure(residual, mask, BANDS_NM, used, MM).count == 0
    used[0] = True
    assert find_structure(residual, mask, BANDS_NM, used, MM).count > 0  # the step, searched, is one
