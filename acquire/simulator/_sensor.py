"""The simulated sensor: electrons to raw DN with shot and read noise, quantisation, black level and
saturation, on an RGGB Bayer mosaic.

Per raw pixel, with g = e_per_dn_iso100 · 100 / ISO electrons per DN (EMVA 1288's linear camera model):

    e ~ Poisson(mean electrons), clipped at the full well
    DN = round(black + (e + N(0, σ_e²)) / g + N(0, σ_dn²)), clipped to 0 … white level

so that, below saturation, E[DN] = black + μ_e / g and Var[DN] = (μ_e + σ_e²) / g² + σ_dn² + 1/12.
"""

from __future__ import annotations

import numpy as np
import torch

from ._optics import RGGB
from .simulation_settings import SimSensor

__all__: list[str] = []


def per_position(values: tuple, height: int, width: int, dtype=torch.float64, device=None) -> torch.Tensor:
    """A ``(H, W)`` map holding ``values[k]`` at the Bayer position k = 2·(row % 2) + (col % 2)."""
    cell = torch.tensor(values, dtype=dtype, device=device).reshape(2, 2)
    return cell.repeat((height + 1) // 2, (width + 1) // 2)[:height, :width]


def mosaic(channels: torch.Tensor) -> torch.Tensor:
    """``(3, H, W)`` red, green, blue → the RGGB mosaic ``(H, W)``."""
    out = torch.empty(channels.shape[1:], dtype=channels.dtype, device=channels.device)
    for k, c in enumerate(RGGB):
        r, q = divmod(k, 2)
        out[r::2, q::2] = channels[c, r::2, q::2]
    return out


def e_per_dn(sensor: SimSensor, iso: int) -> float:
    return sensor.e_per_dn_iso100 * 100.0 / iso


def expose(mean_electrons: torch.Tensor, sensor: SimSensor, iso: int, generator: torch.Generator) -> np.ndarray:
    """Raw DN ``(H, W)`` uint16 of a mosaic of mean electrons ``(H, W)`` (see the module docstring)."""
    mean = mean_electrons.to(torch.float64).clamp(min=0.0)
    electrons = torch.poisson(mean, generator=generator).clamp(max=sensor.full_well_e)
    noise_e = torch.randn(mean.shape, dtype=torch.float64, device=mean.device, generator=generator)
    noise_dn = torch.randn(mean.shape, dtype=torch.float64, device=mean.device, generator=generator)
    black = per_position(sensor.black_level, *mean.shape, device=mean.device)
    dn = black + (electrons + sensor.read_noise_e * noise_e) / e_per_dn(sensor, iso) + sensor.read_noise_dn * noise_dn
    dn = torch.round(dn).clamp(0, sensor.white_level)
    return dn.to(torch.int32).cpu().numpy().astype(np.uint16)

