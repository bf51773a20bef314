"""Typed settings of the calibration: which corrections run, and the thresholds of its checks.

``configs/calibration.yaml`` holds the defaults as a file to copy and edit; a YAML file given by the
user overrides any subset; unknown keys are refused. The resolved settings are written into
``calibration.json`` and the cube's header, so any cube can be re-made.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal, Optional

from pydantic import Field

from ..formats.errors import SettingsError
from ..formats.settings import PixelBox, Strict, load_settings
from .errors import CalibrationError

__all__ = ["CalibrationSettings", "SettingsFileError", "load_calibration_settings"]


class SettingsFileError(CalibrationError, SettingsError):
    """A calibration settings file or value that cannot be used; names the file, key and problem."""


class CalibrationSettings(Strict):
    """Switches of every correction and the thresholds of the quality checks."""

    # Corrections (corrections.py: R = (S − D)/(F − D) · g_F/g_S · ρ_spectralon · f_spectralon/f_skin).
    dark_frame: bool = Field(
        True, description="Subtract the black frame (opaque slot) from every frame; off: only the black level of the raw tags."
    )
    flat_field: bool = Field(
        True,
        description=(
            "Divide by the band's Spectralon frame at the same camera pixels (vignetting, flash non-uniformity, "
            "spectral sensitivity); off: divide by the reference's median over the window only (spectral sensitivity)."
        ),
    )
    spectralon_reflectance: bool = Field(
        True, description="Multiply by the Spectralon's certified reflectance of the band (rig targets)."
    )
    gray_card: bool = Field(
        True, description="Correct flash-to-flash intensity by the gray card (reference over skin frame); off: exposure ratio only."
    )
    polarization: bool = Field(True, description="Apply the rig's polarization factors (spectralon_factor / skin_factor).")
    align_bands: bool = Field(True, description="Align the rectified bands to the reference band (ECC on gradient images).")
    gray_card_roi_px: Optional[PixelBox] = Field(
        None,
        description="[x0, y0, x1, y1] raw pixels of the gray card, replacing the rig's geometry.gray_card_roi_px.",
    )
    gray_card_inset: float = Field(
        0.15,
        ge=0,
        lt=0.5,
        description="Fraction of the card region's width and height left out on each side (the lens blurs its border).",
    )

    # Raw decoding and exposure checks.
    saturation_margin: float = Field(
        0.01, ge=0, lt=0.5, description="A photosite at or above white − margin × white is saturated (fraction of the white level)."
    )
    underexposure_level: float = Field(
        0.01,
        ge=0,
        lt=1,
        description=(
            "A superpixel whose mean photosite signal above black is below this fraction of (white − black) is under-exposed."
        ),
    )

    # Window detection and resampling.
    interpolation: Literal["linear", "cubic", "lanczos"] = Field(
        "cubic", description="Kernel of the perspective rectification (OpenCV INTER_LINEAR, INTER_CUBIC, INTER_LANCZOS4)."
    )
    window_edge_model: bool = Field(
        True,
        description=(
            "Refit each window side with the physical edge model (tape, then skin at half its plateau rising inward); "
            "off: derivative peaks only, biased inward by the skin's darkening near the tape."
        ),
    )
    window_min_area_fraction: float = Field(
        0.002, gt=0, lt=1, description="Smallest window candidate, as a fraction of the superpixel image's area."
    )
    window_max_ring_ratio: float = Field(
        0.7,
        gt=0,
        lt=1,
        description="A window candidate's surround (tape) must be darker than this fraction of its inside (skin).",
    )
    edge_margin_px: int = Field(
        1, ge=0, description="Cube pixels along the window edge left out of the mask (lens blur mixes in the tape)."
    )

    # Band alignment.
    align_reference_nm: Optional[float] = Field(None, description="Band the others are aligned to (default: the middle band).")
    align_motion: Literal["translation", "euclidean"] = Field("translation", description="ECC motion model.")
    align_border: float = Field(
        0.06, ge=0, lt=0.4, description="Fraction of the side along the window edge that the alignment ignores."
    )

    align_min_shift_px: float = Field(
        0.5,
        ge=0,
        le=100,
        description=(
            "A measured shift below this (cube pixels) is reported, not applied: each window is cut from its own frame, "
            "which registers the bands better than ECC across bands of different contrast (0.1–0.2 px); 0: apply every shift."
        ),
    )
    max_alignment_px: float = Field(
        4.0, gt=0, le=100, description="A shift beyond this (cube pixels) is not applied: the band stays as rectified, flagged."
    )

    # Quality-check thresholds (flags).
    gray_card_drift: float = Field(
        0.15, gt=0, description="Flag a band whose flash factor differs from 1 by more than this (fraction)."
    )
    max_misalignment_px: float = Field(1.0, gt=0, le=100, description="Flag a band whose alignment shift exceeds this (cube pixels).")
    card_spectrum_limit: float = Field(
        0.02, gt=0, description="Flag a band where the gray card, read against the Spectralon in the reference frame, departs "
        "from its other bands by more than this (fraction): that band's certified Spectralon value or its reference frame is off."
    )
    max_flagged_fraction: float = Field(
        0.05, ge=0, le=1, description="Flag a band whose saturated or under-exposed share of the window exceeds this."
    )


def load_calibration_settings(path: str | Path | None = None, **overrides) -> CalibrationSettings:
    """Embedded defaults, overridden by a YAML file if given, then by keyword ``overrides``.

    Raises ``SettingsFileError`` naming the file, the key and the problem.
    """
    return load_settings(CalibrationSettings, path, SettingsFileError, "calibration settings", overrides)
