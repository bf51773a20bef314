"""The loss's band weights (``fit.band_weights``, ``FitSettings.band_weights``): each band by the inverse
of the cube's own noise, measured on the cube; and what that buys where the noise differs between bands.

Truth: a flat patch rendered at twice the fit's resolution with the band integration (the synthetic cubes),
given noise whose σ per band is known (the red bands 2–8× the rest, as the rig's 610–670 nm)."""

from __future__ import annotations

import pytest
import torch

from skinlayers.formats.cube import Cube
from skinlayers.reconstruct.choice.grid_choice import band_noise
from skinlayers.reconstruct.mapfit.fit import NOISE_WEIGHT_MAX, band_weights, fit_cube
from skinlayers.reconstruct.settings import BAND_WEIGHTS_BY_PROFILES, FitSettings

#: σ per band (reflectance units) of the test's noise: the rig's pattern, exaggerated
SIGMA = torch.tensor([0.002, 0.002, 0.002, 0.002, 0.002, 0.002, 0.004, 0.008, 0.016], dtype=torch.float64)


def _noisy(clean: torch.Tensor, sigma: torch.Tensor, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return clean.double() + sigma[:, None, None] * torch.randn(clean.shape, generator=g, dtype=torch.float64)


def test_weights_follow_the_measured_noise():
    clean = torch.full((9, 128, 128), 0.4, dtype=torch.float64)
    cube = _noisy(clean, SIGMA, 1)
    mask = torch.ones(128, 128, dtype=torch.bool)
    used = torch.ones(9, dtype=torch.bool)
    w = band_weights(band_noise(cube, mask), used, "noise")
    typical = SIGMA.pow(2).mean().sqrt()
    torch.testing.assert_close(w, (typical / SIGMA).clamp(max=NOISE_WEIGHT_MAX), rtol=0.05, atol=0)
    used[4] = False
    w = band_weights(band_noise(cube, mask), used, "noise")
    assert w[4] == 0 and bool((w[used] > 0).all())
    assert torch.equal(band_weights(band_noise(cube, mask), used, "equal"), used.double())
    assert torch.equal(band_weights(None, used, "noise"), used.double())  # a cube too small to tell its noise


def test_a_band_without_noise_does_not_carry_the_fit():
    cube = _noisy(torch.full((3, 32, 32), 0.4, dtype=torch.float64), torch.tensor([0.01, 0.01, 1e-9], dtype=torch.float64), 2)
    w = band_weights(band_noise(cube, torch.ones(32, 32, dtype=torch.bool)), torch.ones(3, dtype=torch.bool), "noise")
    assert float(w[2]) == NOISE_WEIGHT_MAX


def test_weights_by_the_model_profiles():
    assert FitSettings().band_weighting == BAND_WEIGHTS_BY_PROFILES["diffusion"] == "equal"
    assert FitSettings(model={"profiles": "transport"}).band_weighting == "noise"
    assert FitSettings(model={"profiles": "transport"}, band_weights="equal").band_weighting == "equal"
    with pytest.raises(ValueError):
        FitSettings(band_weights="inverse")


@pytest.fixture(scope="module")
def flat_fits(synthetic):
    """One flat patch (16², higher fidelity than the fit) with the test's noise, fitted per pixel both ways."""
    made = synthetic.make_cube(16, seed=3, noise=0.0, features=False, variation=0.0, blur="pyramid")
    measured = _noisy(made.clean, SIGMA, 3).to(torch.float32)
    cube = Cube(measured, made.cube.mask, made.cube.header)
    per_pixel = {"C_m": 0.0, "beta_m": 1.5, "C_he": 0.0, "C_bc": 100.0, "C_hd": 0.0}
    fits = {w: fit_cube(cube, FitSettings(band_weights=w, map_cell_mm=per_pixel, forward="homogeneous")) for w in ("noise", "equal")}
    return made.truth, made.cube.mask, fits


def test_noise_weights_fit_unequal_noise_closer(flat_fits):
    """Least squares weighted by the noise is the better estimate where the bands' noise differs (the
    Gauss–Markov theorem, for the linearised fit): the per-pixel maps scatter less about the truth."""
    truth, mask, fits = flat_fits
    error = {}
    for w, fit in fits.items():
        error[w] = {n: float(((getattr(fit.maps, n)[0] - getattr(truth, n)[0]) / getattr(truth, n)[0])[mask].pow(2).mean().sqrt())
                    for n in ("C_m", "C_he", "C_hd")}
    for n in ("C_m", "C_he", "C_hd"):
        assert error["noise"][n] < 0.9 * error["equal"][n], error
    assert fits["noise"].band_weight[-1] < fits["noise"].band_weight[0] and torch.equal(fits["equal"].band_weight, torch.ones(9, dtype=torch.float64))
