"""The radiometric corrections, one pure function each (DWRR08 §6.1, §6.2, §6.4).

For a band, with superpixel frames above black (``raw.py``):

    R = (S − D) / (F − D) · (g_F / g_S) · ρ_spectralon(band) · f_spectralon / f_skin

- S, F, D: the skin frame, the band's Spectralon reference frame and the black frame (opaque slot),
  at the same camera pixels: the ratio cancels vignetting, flash non-uniformity, per-pixel gain and
  the spectral sensitivity of camera and filter together (flat field).
- g_F / g_S: the 30% gray card, fixed to the rig and in view in every frame, tracks the flash's
  intensity (and any exposure difference) from the reference frame to the skin frame.
- ρ_spectralon: the target's certified reflectance at the band (rig ``targets``).
- f_spectralon / f_skin: the polarization biases of the crossed polarizers (rig ``polarization``):
  each target's signal relative to an ideal depolarizing reflector of the same reflectance.

Each factor can be switched off (``CalibrationSettings``) to see what it does. The global radiometric
scale that remains (DWRR08 found 1.02) is left to the fit.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Optional, Sequence

import numpy as np

from ..formats.manifest import Exposure
from ..formats.rig import RigConfig
from .errors import CalibrationError
from .settings import CalibrationSettings

__all__ = [
    "BandFactors",
    "band_factors",
    "exposure_value",
    "gray_card_level",
    "reflectance_ratio",
    "roi_to_superpixels",
    "subtract_dark",
]


@dataclass(frozen=True)
class BandFactors:
    """The scalar factors of one band and their product ``scale`` (applied to (S − D)/(F − D))."""

    flash_factor: float
    exposure_ratio: float
    spectralon_reflectance: float
    polarization_factor: float

    @property
    def scale(self) -> float:
        return self.flash_factor * self.exposure_ratio * self.spectralon_reflectance * self.polarization_factor

    def as_dict(self) -> dict:
        return {**asdict(self), "scale": self.scale}


def subtract_dark(frame: np.ndarray, dark: Optional[np.ndarray]) -> np.ndarray:
    """``frame − dark`` ``(H, W)`` (both superpixels above black); ``dark`` None: the frame unchanged."""
    if dark is None:
        return np.asarray(frame, np.float32)
    if frame.shape != dark.shape:
        raise CalibrationError(f"frame {frame.shape} and black frame {dark.shape} differ in size")
    return np.asarray(frame, np.float32) - np.asarray(dark, np.float32)


def roi_to_superpixels(
    roi_px: Sequence[int], shape: tuple[int, int], inset: float = 0.0, name: str = "gray card"
) -> tuple[int, int, int, int]:
    """Raw-pixel box ``[x0, y0, x1, y1]`` (half-open) → the superpixels wholly inside it, after trimming
    ``inset`` × its width and height from each side (the lens blurs the card's border with whatever
    surrounds it, which differs between a reference and a skin frame), in a superpixel image of
    ``shape`` ``(H, W)``. Raises ``CalibrationError`` if it leaves the image or keeps no whole cell."""
    x0, y0, x1, y1 = (int(v) for v in roi_px)
    h, w = shape
    if x1 > 2 * w or y1 > 2 * h:
        raise CalibrationError(f"{name} region {list(roi_px)} (raw px) extends beyond the {2 * w}×{2 * h} image")
    dx, dy = inset * (x1 - x0), inset * (y1 - y0)
    sx0, sy0 = math.ceil((x0 + dx) / 2), math.ceil((y0 + dy) / 2)
    sx1, sy1 = math.floor((x1 - dx) / 2), math.floor((y1 - dy) / 2)
    if sx1 <= sx0 or sy1 <= sy0:
        raise CalibrationError(f"{name} region {list(roi_px)} (raw px) holds no whole 2×2 cell inside its border")
    return sx0, sy0, sx1, sy1


def gray_card_level(image: np.ndarray, box: tuple[int, int, int, int], saturated: np.ndarray, name: str) -> float:
    """Mean of ``image`` ``(H, W)`` (superpixels above black, dark subtracted) over ``box`` (superpixels).

    Raises ``CalibrationError`` naming ``name`` if the card has saturated pixels or no signal: its
    level would then say nothing about the flash.
    """
    x0, y0, x1, y1 = box
    sat = float(np.mean(saturated[y0:y1, x0:x1]))
    if sat > 0:
        raise CalibrationError(
            f"{name}: {sat:.1%} of the gray card is saturated; switch the gray card off (--no-gray-card) or expose less"
        )
    level = float(np.mean(image[y0:y1, x0:x1], dtype=np.float64))
    if not level > 0:
        raise CalibrationError(f"{name}: the gray card shows no signal above the black frame ({level:.3g} DN)")
    return level


def exposure_value(exposure: Exposure) -> float:
    """Relative light a frame collects: ISO × shutter / f-number²."""
    return exposure.iso * exposure.shutter_s / exposure.aperture_f**2


def band_factors(
    settings: CalibrationSettings,
    rig: RigConfig,
    band_nm: float,
    *,
    gray_reference: Optional[float],
    gray_skin: Optional[float],
    exposure_reference: Exposure,
    exposure_skin: Exposure,
) -> BandFactors:
    """The scalar factors of a band as the settings switch them.

    With the gray card, ``g_F / g_S`` holds the flash's and the exposure's changes alike; without it, the
    exposure ratio (reference over skin) stands in and the flash's jitter stays in the band.
    """
    if settings.gray_card:
        if gray_reference is None or gray_skin is None:
            raise CalibrationError(f"band {band_nm:g} nm: gray card levels missing")
        flash, exposure = gray_reference / gray_skin, 1.0
    else:
        flash, exposure = 1.0, exposure_value(exposure_reference) / exposure_value(exposure_skin)
    rho = rig.targets.spectralon_at(band_nm) if settings.spectralon_reflectance else 1.0
    pol = rig.polarization.spectralon_factor / rig.polarization.skin_factor if settings.polarization else 1.0
    return BandFactors(flash_factor=flash, exposure_ratio=exposure, spectralon_reflectance=rho, polarization_factor=pol)


def reflectance_ratio(
    skin: np.ndarray, reference: np.ndarray, scale: float, flat: Optional[float] = None
) -> tuple[np.ndarray, np.ndarray]:
    """Camera-space reflectance ``(H, W)`` and where it is defined.

    ``skin`` and ``reference`` are dark-subtracted superpixels. With ``flat`` None the reference divides
    pixel by pixel (the flat field); otherwise the scalar ``flat`` (the reference's level over the
    window) does, and vignetting and the flash's non-uniformity stay in the result. Returns the
    reflectance (0 where undefined) and a bool map of pixels where the reference has signal.
    """
    skin = np.asarray(skin, np.float32)
    denom = np.asarray(reference, np.float32) if flat is None else np.full(skin.shape, flat, np.float32)
    ok = denom > 0
    out = np.zeros(skin.shape, np.float32)
    np.divide(skin, denom, out=out, where=ok)
    return out * np.float32(scale), ok
