"""Synthetic reflectance cubes whose truth is known, made at higher fidelity than the fit (no inverse crime).

A scene (``acquire.scene.SkinScene``: smooth variation of every chromophore, freckles, a scar, a vein
in the interface absorbance, optionally hairs) is rendered

- on a grid ``fine``× finer than the cube's, then box-averaged down (the camera's pixels average);
- over real occluded skin around the window (its own parameters, not a copy of the edge's), with a
  wider dark border beyond;
- through each band's filter (a Gaussian of 10 nm FWHM, as the rig's and the simulated bench's) by
  5-point Gauss–Hermite quadrature (the fit models the band with 3 points);
- with the exact FFT blur instead of the fit's pyramid and a fixed, generous count of series terms;

then given camera-like noise (shot noise growing with the signal, read noise, a different gain per
band, as ISO 200–800 would) and a radiometric scale error, and written as a calibration ``Cube``
whose mask leaves out the window's edge ring (calibration's ``edge_margin_px = 1``).

Loaded by path (``importlib``) from the reconstruction tests and the benchmarks.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from skinlayers.acquire.simulator.scene import SkinScene, VariationConfig, scene_from_dict
from skinlayers.formats.cube import Cube, CubeHeader
from skinlayers.model import ModelSettings
from skinlayers.model.render.illumination import Light
from skinlayers.model.patch.maps import SkinMaps
from skinlayers.model.render.renderer import SkinRenderer

RIG_BANDS_NM = (430.0, 460.0, 490.0, 520.0, 550.0, 580.0, 610.0, 640.0, 670.0)
WINDOW_MM = 7.5
OCCLUDED_MM = 2.0  # real skin rendered around the window before the dark border
BAND_FWHM_NM = 10.0
_NODES, _WEIGHTS = np.polynomial.hermite.hermgauss(5)
BAND_OFFSETS_NM = tuple(float(v) for v in math.sqrt(2.0) * BAND_FWHM_NM / (2.0 * math.sqrt(2.0 * math.log(2.0))) * _NODES)
BAND_WEIGHTS = tuple(float(v) for v in _WEIGHTS / _WEIGHTS.sum())
SHOT_GAIN = 1e-5  # shot-noise variance per unit reflectance: σ = 0.22% at R = 0.5, gain 1
READ_NOISE = 1e-3
BAND_GAIN = (2.0, 2.0, 1.4, 1.4, 1.0, 1.0, 1.0, 1.4, 1.4)  # relative noise variance per band (ISO)


@dataclass
class SyntheticCube:
    """The cube, the truth box-averaged to its grid ``(1, H, W)``, the noise actually added
    ``(L, H, W)``, where the vein and the hairs lie ``(H, W)`` (bool, the vein dilated by a pixel) and
    the noise-free cube ``(L, H, W)``."""

    cube: Cube
    truth: SkinMaps
    noise: torch.Tensor
    vein: torch.Tensor
    hair: torch.Tensor
    clean: torch.Tensor


def scene_config(preset: str = "III interior", hairs: int = 0, seed_features: bool = True, variation: float = 1.0) -> dict:
    """A small scene: smooth variation (the scene's default amplitudes times ``variation``), two
    freckles, a scar, a vein (unless ``seed_features`` is off); ``hairs`` dark hairs."""
    config = {
        "base": {"preset": preset},
        "freckles": {"count": 2 if seed_features else 0, "radius_mm": [0.3, 0.5]},
        "scar": {"count": 1 if seed_features else 0},
        "veins": {"count": 1 if seed_features else 0},
        "hairs": {"count": hairs},
    }
    if variation != 1.0:
        defaults = VariationConfig()
        config["variation"] = {k: getattr(defaults, k) * variation for k in ("C_m", "beta_m", "C_he", "C_bc", "C_hd")}
    return config


def make_cube(
    size_px: int = 32,
    *,
    seed: int = 0,
    preset: str = "III interior",
    hairs: int = 0,
    fine: int = 2,
    noise: float = 1.0,
    radiometric_scale: float = 1.0,
    bands_nm: tuple[float, ...] = RIG_BANDS_NM,
    settings: ModelSettings | None = None,
    view_angle_deg: float = 30.0,
    blur: str = "fft",
    features: bool = True,
    variation: float = 1.0,
) -> SyntheticCube:
    """``blur="pyramid"`` for large cubes, where the FFT reference costs hours here (the fit's blur,
    still at twice its resolution and with the band integration). ``features=False, variation=0``:
    flat skin, a homogeneous patch."""
    settings = settings or ModelSettings()
    renderer = SkinRenderer(settings.model_copy(update={"render": settings.render.model_copy(update={"blur": blur})}))
    scene = SkinScene(scene_from_dict(scene_config(preset, hairs, features, variation)), seed=seed)
    n_fine = size_px * fine
    mm_fine = WINDOW_MM / n_fine
    margin = int(round(OCCLUDED_MM / mm_fine))
    total = n_fine + 2 * margin
    wl = torch.tensor([b + o for b in bands_nm for o in BAND_OFFSETS_NM], dtype=torch.float64)
    maps = scene.maps(mm_fine, total, wl, optics=settings.optics)
    light = Light("window", size_mm=WINDOW_MM, border_mm=5.0)
    with torch.no_grad():
        out = renderer.render(maps, light, wl, view_angle_deg=view_angle_deg, series_terms=10)
    image = out.image[0, :, margin:margin + n_fine, margin:margin + n_fine]
    weights = torch.tensor(BAND_WEIGHTS, dtype=image.dtype)
    banded = (image.reshape(len(bands_nm), len(BAND_OFFSETS_NM), n_fine, n_fine) * weights[None, :, None, None]).sum(1)
    clean = F.avg_pool2d(banded[None], fine)[0] * radiometric_scale
    g = torch.Generator().manual_seed(1000 + seed)
    gain = torch.tensor(BAND_GAIN[: len(bands_nm)] if len(bands_nm) == len(BAND_GAIN) else [1.0] * len(bands_nm))
    sigma = torch.sqrt(gain[:, None, None] * (SHOT_GAIN * clean.clamp_min(0) + READ_NOISE**2))
    added = noise * sigma * torch.randn(clean.shape, generator=g, dtype=clean.dtype)
    measured = (clean + added).to(torch.float32)
    mask = torch.zeros(size_px, size_px, dtype=torch.bool)
    mask[1:-1, 1:-1] = True
    mm = WINDOW_MM / size_px
    header = CubeHeader(wavelengths_nm=[float(b) for b in bands_nm], band_fwhm_nm=[BAND_FWHM_NM] * len(bands_nm),
                        camera_angle_deg=view_angle_deg, mm_per_pixel=mm, provenance={"made_by": f"synthetic cube, seed {seed}"})
    cube = Cube(measured, mask, header)
    crop = lambda v: F.avg_pool2d(v[:, None, margin:margin + n_fine, margin:margin + n_fine], fine)[:, 0]  # noqa: E731
    truth = SkinMaps(*(crop(getattr(maps, n)) for n in ("C_m", "beta_m", "C_he", "C_bc", "C_hd")), mm_per_pixel=mm)
    axis = (torch.arange(total, dtype=torch.float64) - (total - 1) / 2.0) * mm_fine
    y, x = torch.meshgrid(axis, axis, indexing="ij")
    vessel = crop(scene.vessel_path_at(x, y)[None].float())[0]
    vein = F.max_pool2d((vessel > 1e-5)[None, None].float(), 3, stride=1, padding=1)[0, 0] > 0
    hair = crop(scene.hair_absorbance_at(x, y)[None].float())[0] > 0.05
    return SyntheticCube(cube, truth, added.to(torch.float32), vein, hair, clean.to(torch.float32))
