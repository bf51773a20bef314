"""The hair finder on constructed cubes: a thin dark line in red light is found and flagged with its halo;
freckles, a vein and the camera's noise are not hairs."""

from __future__ import annotations

import torch

from skinlayers.reconstruct.diagnosis.hairs import HALO_MM, find_hairs, hair_notes

WAVELENGTHS_NM = [430.0, 460.0, 490.0, 520.0, 550.0, 580.0, 610.0, 640.0, 670.0]
MM_PER_PIXEL = 0.03  # a 256² cube over 7.5 mm
SIDE = 128
NOISE = 0.004  # reflectance units, each band


def _skin(seed: int, noise: float = NOISE) -> tuple[torch.Tensor, torch.Tensor]:
    """Skin ``(L, H, W)`` with two freckles (0.2 and 0.35 mm radius) and a vein (0.3 mm radius), ``noise`` added."""
    gen = torch.Generator().manual_seed(seed)
    y, x = torch.meshgrid(torch.arange(SIDE) * MM_PER_PIXEL, torch.arange(SIDE) * MM_PER_PIXEL, indexing="ij")
    base = torch.linspace(0.25, 0.55, len(WAVELENGTHS_NM))[:, None, None].expand(-1, SIDE, SIDE).clone()
    blue_weight = torch.linspace(1.0, 0.2, len(WAVELENGTHS_NM))[:, None, None]
    for cx, cy, radius in ((1.0, 1.0, 0.2), (3.0, 1.2, 0.35)):
        freckle = (((x - cx) ** 2 + (y - cy) ** 2).sqrt() < radius).float()
        base = base * (1.0 - 0.35 * blue_weight * freckle)
    vein = ((y - 3.0).abs() < 0.3).float()
    base = base * (1.0 - 0.12 * torch.linspace(0.2, 1.0, len(WAVELENGTHS_NM))[:, None, None] * vein)
    noisy = base + noise * torch.randn(base.shape, generator=gen)
    return noisy, torch.full((len(WAVELENGTHS_NM),), noise)


def test_a_thin_dark_line_is_found_and_flagged_with_its_halo():
    cube, noise = _skin(0)
    line = torch.zeros(SIDE, SIDE, dtype=torch.bool)
    line[20:100, 64] = True  # a hair 2.4 mm long, one pixel (30 µm) wide, grey: 40% of the light taken
    cube[:, line] *= 0.6
    mask = torch.ones(SIDE, SIDE, dtype=torch.bool)
    found = find_hairs(cube, WAVELENGTHS_NM, mask, MM_PER_PIXEL, noise)
    assert found.count == 1
    assert bool(found.pixels[25:95, 64].all()) and int(found.pixels.sum()) < 1.2 * int(line.sum())
    ring = round(HALO_MM / MM_PER_PIXEL)
    assert bool(found.flagged[60, 64 - ring]) and bool(found.flagged[60, 64 + ring]) and not bool(found.flagged[60, 64 + ring + 2])
    assert "1 hair(s) found" in hair_notes(found, SIDE * SIDE)[0]


def test_freckles_a_vein_and_noise_are_not_hairs():
    for seed in range(3):
        cube, noise = _skin(seed)
        found = find_hairs(cube, WAVELENGTHS_NM, torch.ones(SIDE, SIDE, dtype=torch.bool), MM_PER_PIXEL, noise)
        assert found.count == 0 and not bool(found.flagged.any()), seed
        assert hair_notes(found, SIDE * SIDE) == []


def test_outside_the_mask_nothing_is_found():
    cube, noise = _skin(1)
    cube[:, 40:80, 30] *= 0.5
    mask = torch.ones(SIDE, SIDE, dtype=torch.bool)
    mask[:, :40] = False  # the line lies outside the window
    found = find_hairs(cube, WAVELENGTHS_NM, mask, MM_PER_PIXEL, noise)
    assert found.count == 0


def test_sigma_is_widened_by_the_measured_factors_on_and_away_from_hairs():
    from skinlayers.model import PARAMETER_NAMES
    from skinlayers.reconstruct.diagnosis.hairs import HAIR_SIGMA_AWAY, HAIR_SIGMA_ON, hair_widening

    flagged = torch.tensor([True, False, True])
    factors = hair_widening(flagged, PARAMETER_NAMES)
    assert factors.shape == (len(PARAMETER_NAMES), 3)
    for k, name in enumerate(PARAMETER_NAMES):
        assert factors[k].tolist() == [HAIR_SIGMA_ON[name], HAIR_SIGMA_AWAY[name], HAIR_SIGMA_ON[name]]
        assert HAIR_SIGMA_ON[name] >= 1.0 and HAIR_SIGMA_AWAY[name] >= 1.0  # widened, never narrowed


def test_a_cube_without_noise_has_no_hairs_and_a_dead_red_band_is_not_looked_at():
    cube, _ = _skin(0)
    clean, _ = _skin(0, noise=0.0)
    clean[:, 30:90, 40] *= 0.995  # a fine crease, 0.5% darker
    mask = torch.ones(SIDE, SIDE, dtype=torch.bool)
    # band_noise's floor (1e-9) as the noise: a faint line of the skin must not pass for a hair
    assert find_hairs(clean, WAVELENGTHS_NM, mask, MM_PER_PIXEL, torch.full((9,), 1e-9)).count == 0
    lined = cube.clone()
    lined[:, 20:100, 64] *= 0.6
    lined[8] = 1e-4 + 0.05 * torch.rand(SIDE, SIDE, generator=torch.Generator().manual_seed(1))  # 670 nm dead and noisy
    noise = torch.full((9,), NOISE)
    noise[8] = 0.05
    used = torch.ones(9, dtype=torch.bool)
    used[8] = False
    assert find_hairs(lined, WAVELENGTHS_NM, mask, MM_PER_PIXEL, noise, used).count == 1
