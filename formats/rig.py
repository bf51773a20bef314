"""The rig as a session records it: bands with their filters and exposures, the wheel, the camera, the
targets, the polarizers and the window's geometry.

A contract between acquisition (which captures with it and writes it, as used, into every session's
``manifest.json``) and calibration (which reads the filters' widths, the camera angle, the targets and the
geometry back from there). ``acquire.rig.load_rig`` reads it from YAML (``configs/rig.yaml`` is the
embedded default). The measurement it describes is DWRR08 §6.1: narrow-band filters in a wheel, a camera
30° off the flash axis, crossed polarizers, a Spectralon target, a gray card, a 7.5-mm window in black tape.
"""

from __future__ import annotations

from typing import Literal, Optional

from pydantic import Field, field_validator, model_validator

from .settings import PixelBox, SettingsError, Strict, validate_settings

__all__ = ["BandConfig", "CameraConfig", "GeometryConfig", "PolarizationConfig", "RigConfig", "RigError",
           "TargetsConfig", "WheelConfig", "rig_from_dict"]


#: The largest cube and rectified window a rig may ask for: 8× and 8× the paper's 256 and 512.
MAX_CUBE_PX, MAX_RECTIFY_PX = 2048, 4096


class RigError(SettingsError):
    """A rig file or value that cannot be used; the message names the file, the key and the problem."""


class BandConfig(Strict):
    """One acquisition band: its filter and the exposure it is taken with."""

    wavelength_nm: float = Field(..., ge=380, le=800, description="Centre wavelength of the band-pass filter (nm).")
    fwhm_nm: float = Field(10.0, gt=0, le=100, description="Full width at half maximum of the filter (nm).")
    filter_position: int = Field(..., ge=1, description="Wheel position holding this filter (1-based, as the FW102C counts).")
    iso: int = Field(400, gt=0, le=409600, description="ISO of the frames in this band (DWRR08: 200–800 by wavelength).")
    shutter_s: float = Field(0.01, gt=0, le=60, description="Shutter time (s); the flash is far shorter (DWRR08: 1/100 s).")
    aperture_f: float = Field(10.0, ge=0.5, le=128, description="Aperture f-number (DWRR08: f/10).")


class WheelConfig(Strict):
    """The filter wheel (Thorlabs FW102C / FW212C)."""

    port: Optional[str] = Field(None, description="Serial port of the wheel, e.g. /dev/ttyUSB0 or COM3.")
    baud: int = Field(115200, gt=0, description="Baud rate (FW102C default 115200, 8N1).")
    timeout_s: float = Field(2.0, gt=0, le=600, description="Time to wait for one answer of the wheel (s).")
    move_timeout_s: float = Field(10.0, gt=0, le=600, description="Time to wait for a move to finish (s).")
    retries: int = Field(2, ge=0, le=10, description="Retries of an exchange that failed before giving up.")
    position_count: int = Field(12, description="Positions of the wheel (6 or 12).")
    dark_position: int = Field(1, ge=1, description="Position of the opaque slot used for the black frame.")


class CameraConfig(Strict):
    """The camera and how to reach it."""

    driver: Literal["gphoto2", "simulated"] = Field("gphoto2", description="gphoto2 (a real camera) or simulated.")
    model: Optional[str] = Field(None, description="Camera model to pick when several are connected (gphoto2 --camera).")
    port: Optional[str] = Field(None, description="gphoto2 port, e.g. usb:001,004 (auto-detected when omitted).")
    angle_deg: float = Field(30.0, ge=0, lt=80, description="Camera axis off the flash axis (DWRR08 §6: 30°).")


class TargetsConfig(Strict):
    """Reference targets in the scene."""

    spectralon_reflectance: float | dict[float, float] = Field(
        0.99, description="Certified reflectance of the Spectralon target: one value, or per band {nm: value}."
    )

    @field_validator("spectralon_reflectance")
    @classmethod
    def _certified(cls, value):
        values = list(value.values()) if isinstance(value, dict) else [value]
        if not values or any(not (0 < v <= 1) for v in values):
            raise ValueError(f"a certified reflectance lies in (0, 1], got {value}")
        if isinstance(value, dict) and any(not 380 <= k <= 800 for k in value):
            raise ValueError(f"the certificate's wavelengths must lie within 380–800 nm, got {sorted(value)}")
        return value
    gray_card_reflectance: float = Field(0.30, gt=0, lt=1, description="Reflectance of the gray card in every frame.")

    def spectralon_at(self, wavelength_nm: float) -> float:
        """The certified reflectance at a band (linear between tabulated bands, ends held)."""
        r = self.spectralon_reflectance
        if isinstance(r, (int, float)):
            return float(r)
        pts = sorted((float(k), float(v)) for k, v in r.items())
        if wavelength_nm <= pts[0][0]:
            return pts[0][1]
        for (w0, v0), (w1, v1) in zip(pts, pts[1:]):
            if wavelength_nm <= w1:
                return v0 + (v1 - v0) * (wavelength_nm - w0) / (w1 - w0)
        return pts[-1][1]


class PolarizationConfig(Strict):
    """Biases of the crossed polarizers (DWRR08 §6.1), as factors on the signal each target gives
    relative to an ideal depolarizing reflector of the same reflectance."""

    spectralon_factor: float = Field(
        1.0527, gt=0, le=10, description="Spectralon's signal under the crossed polarizers over its certified reflectance (±5.27% s/p)."
    )
    skin_factor: float = Field(1.0, gt=0, le=10, description="Skin's (imperfect) depolarization factor; its spread is left to the fit's scale.")


class GeometryConfig(Strict):
    """The patch: the black tape's window."""

    window_mm: float = Field(7.5, gt=0, le=100, description="Side of the square window in the black tape (DWRR08: 7.5 mm).")
    cube_px: int = Field(256, ge=16, le=MAX_CUBE_PX, description="Side of the calibrated reflectance cube (DWRR08: 512 → 256).")
    rectify_px: int = Field(512, ge=16, le=MAX_RECTIFY_PX, description="Side the window is resampled to before the box filter.")
    gray_card_roi_px: Optional[PixelBox] = Field(
        None,
        description=(
            "Region of the 30% gray card in raw sensor pixels, [x0, y0, x1, y1] half-open. The card is fixed "
            "to the rig, not to the subject, so it stays at one image place; the simulator writes it."
        ),
    )


class RigConfig(Strict):
    """Everything about the rig a session and its calibration need."""

    name: str = Field("DWRR08-style rig", description="A name for this rig.")
    bands: list[BandConfig] = Field(..., min_length=1, max_length=64, description="The acquisition bands, in capture order.")
    wheel: WheelConfig = WheelConfig()
    camera: CameraConfig = CameraConfig()
    targets: TargetsConfig = TargetsConfig()
    polarization: PolarizationConfig = PolarizationConfig()
    geometry: GeometryConfig = GeometryConfig()

    @model_validator(mode="after")
    def _consistent(self) -> "RigConfig":
        positions = [b.filter_position for b in self.bands]
        if len(set(positions)) != len(positions):
            raise ValueError("bands: two bands share a filter position")
        if self.wheel.dark_position in positions:
            raise ValueError(f"wheel.dark_position {self.wheel.dark_position} also holds a band filter")
        top = max(positions + [self.wheel.dark_position])
        if top > self.wheel.position_count:
            raise ValueError(f"filter position {top} exceeds wheel.position_count {self.wheel.position_count}")
        waves = [b.wavelength_nm for b in self.bands]
        if len(set(waves)) != len(waves):
            raise ValueError("bands: two bands share a wavelength")
        return self

    @property
    def wavelengths_nm(self) -> list[float]:
        return [b.wavelength_nm for b in self.bands]

    def band(self, wavelength_nm: float) -> BandConfig:
        for b in self.bands:
            if abs(b.wavelength_nm - wavelength_nm) < 1e-6:
                return b
        raise RigError(f"no band at {wavelength_nm:g} nm in rig {self.name!r}")


def rig_from_dict(data: dict, source: str = "rig") -> RigConfig:
    """A validated rig from a mapping (a manifest's record, a YAML file's content)."""
    return validate_settings(RigConfig, data, RigError, source)
