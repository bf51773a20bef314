"""The reflectance cube: calibration's output and reconstruction's input, defined here and nowhere else.

Who writes it: ``calibration.calibrate_session`` (from a session; every header field from the rig in
the session's manifest). Who reads it: ``reconstruct.fit_cube`` (the fit takes the bands, their filters'
widths, the camera angle and the pixel size from the header, never from guesses).

**File** (``cube.exr``): float32 OpenEXR with one channel ``R_<nm>`` per band (reflectance factor, 0–1
for skin: the ratio to an ideal white diffuser seen the same way) and a channel ``mask`` (1 where a
pixel is valid in every band, 0 where it is saturated, under-exposed, outside the window or otherwise
flagged). Header attributes: ``skinlayers_cube`` (the ``CubeHeader`` below as JSON: the one the reader
trusts), and for other EXR readers ``wavelengths_nm`` (float list) and ``mm_per_pixel`` (float).

**Header** (``CubeHeader``):

| field | unit | meaning |
|---|---|---|
| ``wavelengths_nm`` | nm | each band's filter centre, increasing, one per ``R_<nm>`` channel |
| ``band_fwhm_nm`` | nm | each band's filter width (Gaussian FWHM); None: not recorded by the cube's maker |
| ``camera_angle_deg`` | degree | the camera's axis off the flash axis (the skin's normal); None: not recorded |
| ``mm_per_pixel`` | mm | side of a cube pixel on the skin |
| ``software_version`` | | the skinlayers version that wrote it |
| ``provenance`` | | where it came from: ``session`` (folder), ``made_by``, ``created`` (ISO 8601, UTC), ``rig`` (name) |
| ``calibration`` | | free-form record of the calibration (window corners, alignment, settings); read by people |

Cubes written before the typed header (a JSON ``meta`` attribute) are read too: their camera angle comes
from ``meta``, and their filters' width is None, which the fit reports.
"""

from __future__ import annotations

import math

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import torch
from pydantic import Field, ValidationError, model_validator

from .errors import InputError
from .exr import band_channels, float_attribute, read_exr, write_exr
from .maps import MAX_MM_PER_PIXEL, MIN_MM_PER_PIXEL
from .settings import Strict, format_validation_error
from .version import software_version

__all__ = [
    "CALIBRATED_SUFFIX", "CUBE_NAME", "RECONSTRUCTION_SUFFIX", "Cube", "CubeError", "CubeHeader", "Provenance", "calibrated_dir",
    "read_cube", "reconstruction_dir", "write_cube",
]

#: File name of the cube in a calibrated folder.
CUBE_NAME = "cube.exr"
#: Calibration writes beside a session, never into it: ``<SESSION>_calibrated``.
CALIBRATED_SUFFIX = "_calibrated"
#: And the fit of its cube: ``<SESSION>_reconstruction``.
RECONSTRUCTION_SUFFIX = "_reconstruction"
_HEADER_ATTRIBUTE = "skinlayers_cube"
#: Two bands' centres (or a channel's name and the header) agree within this.
_SAME_NM = 1e-3


class CubeError(InputError):
    """A cube file or header that cannot be used; the message names the file and the problem."""


def calibrated_dir(session: str | Path) -> Path:
    """Where a session's calibration goes by default: ``<session>_calibrated`` beside it."""
    session = Path(session).resolve()
    return session.parent / f"{session.name}{CALIBRATED_SUFFIX}"


def reconstruction_dir(session: str | Path) -> Path:
    """Where a session's fit goes by default: ``<session>_reconstruction`` beside it."""
    session = Path(session).resolve()
    return session.parent / f"{session.name}{RECONSTRUCTION_SUFFIX}"


class Provenance(Strict):
    """Where a cube came from."""

    session: Optional[str] = Field(None, description="The session folder it was calibrated from.")
    made_by: str = Field("unknown", description="What made it (\"skinlayers calibrate\", a test's synthetic cube, …).")
    created: Optional[str] = Field(None, description="When, ISO 8601 UTC.")
    rig: Optional[str] = Field(None, description="The rig's name, as the session recorded it.")


class CubeHeader(Strict):
    """Everything a reader of a cube needs besides the pixels (see the module docstring)."""

    wavelengths_nm: list[float] = Field(..., min_length=1, max_length=512, description="Band centres (nm), increasing.")
    band_fwhm_nm: Optional[list[float]] = Field(None, description="Each band's filter FWHM (nm); None: not recorded.")
    camera_angle_deg: Optional[float] = Field(None, ge=0, lt=90, description="Camera axis off the flash axis (°); None: not recorded.")
    mm_per_pixel: float = Field(..., ge=MIN_MM_PER_PIXEL, lt=MAX_MM_PER_PIXEL, description="Pixel side on the skin (mm).")
    software_version: str = Field(default_factory=software_version, description="The skinlayers version that wrote it.")
    provenance: Provenance = Provenance()
    calibration: dict = Field(default_factory=dict, description="The calibration's own record (free-form, for people).")

    @model_validator(mode="after")
    def _bands(self) -> "CubeHeader":
        wl = self.wavelengths_nm
        if any(b <= a for a, b in zip(wl, wl[1:])):
            raise ValueError(f"wavelengths_nm must increase, got {wl}")
        if self.band_fwhm_nm is not None:
            if len(self.band_fwhm_nm) != len(wl):
                raise ValueError(f"band_fwhm_nm has {len(self.band_fwhm_nm)} values for {len(wl)} bands")
            if any(not w >= 0 for w in self.band_fwhm_nm):
                raise ValueError(f"band_fwhm_nm must be >= 0 nm, got {self.band_fwhm_nm}")
        return self


@dataclass
class Cube:
    """Reflectance ``(L, H, W)``, a validity ``mask`` ``(H, W)`` (bool) and the ``header``."""

    reflectance: torch.Tensor
    mask: torch.Tensor
    header: CubeHeader

    def __post_init__(self) -> None:
        r = self.reflectance
        if r.ndim != 3:
            raise CubeError(f"reflectance must be (L, H, W), got {tuple(r.shape)}")
        if len(self.header.wavelengths_nm) != r.shape[0]:
            raise CubeError(f"{len(self.header.wavelengths_nm)} wavelengths for {r.shape[0]} bands")
        if tuple(self.mask.shape) != tuple(r.shape[1:]):
            raise CubeError(f"mask has shape {tuple(self.mask.shape)}, the bands {tuple(r.shape[1:])}")

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self.reflectance.shape)  # type: ignore[return-value]

    @property
    def wavelength_nm(self) -> torch.Tensor:
        """Band centres ``(L,)`` float64."""
        return torch.tensor(self.header.wavelengths_nm, dtype=torch.float64)

    @property
    def mm_per_pixel(self) -> float:
        return self.header.mm_per_pixel


def write_cube(path: str | Path, cube: Cube) -> Path:
    """Write a cube atomically."""
    header = cube.header
    channels = {f"R_{w:g}": cube.reflectance[j] for j, w in enumerate(header.wavelengths_nm)}
    channels["mask"] = cube.mask.to(torch.float32)
    attributes = {
        _HEADER_ATTRIBUTE: json.dumps(header.model_dump(mode="json"), sort_keys=True, allow_nan=False),
        "wavelengths_nm": list(header.wavelengths_nm),
        "mm_per_pixel": float(header.mm_per_pixel),
    }
    return write_exr(path, channels, attributes)


def read_cube(path: str | Path) -> Cube:
    """Read a cube; ``CubeError`` names the file and what is wrong (no bands, no mask, NaN, a header
    that disagrees with the channels, …)."""
    path = Path(path)
    channels, attributes = read_exr(path, CubeError)
    bands = []
    for name in channels:
        if name.startswith("R_"):
            try:
                nm = float(name[2:])
            except ValueError:
                nm = math.nan
            if not 0 < nm < math.inf:  # NaN included
                raise CubeError(f"{path}: channel {name} is not R_<nm> (a wavelength in nm)")
            bands.append((nm, name))
    if not bands:
        raise CubeError(f"{path}: no reflectance channels R_<nm> (has: {', '.join(sorted(channels)) or 'none'})")
    if "mask" not in channels:
        raise CubeError(f"{path}: channel mask is missing")
    bands = band_channels({n: channels[n] for _, n in bands}, "R")
    refl = torch.stack([torch.from_numpy(channels[n].copy()) for _, n in bands])
    for (w, n), layer in zip(bands, refl):
        if not bool(torch.isfinite(layer).all()):
            raise CubeError(f"{path}: channel {n} has {int((~torch.isfinite(layer)).sum())} NaN or infinite pixel(s)")
    header = _header(attributes, [w for w, _ in bands], path)
    if any(abs(a - b) > _SAME_NM for a, b in zip(header.wavelengths_nm, (w for w, _ in bands))):
        raise CubeError(f"{path}: header wavelengths {header.wavelengths_nm} differ from the channels {[n for _, n in bands]}")
    mask = torch.from_numpy(channels["mask"].copy()) > 0.5
    return Cube(refl, mask, header)


def _header(attributes: dict, channel_nm: list[float], path: Path) -> CubeHeader:
    if _HEADER_ATTRIBUTE in attributes:
        try:
            data = json.loads(_text(attributes[_HEADER_ATTRIBUTE]))
        except json.JSONDecodeError:
            raise CubeError(f"{path}: header attribute {_HEADER_ATTRIBUTE} is not valid JSON") from None
        if not isinstance(data, dict):
            raise CubeError(f"{path}: header attribute {_HEADER_ATTRIBUTE} is not a JSON object")
        if not isinstance(data.get("wavelengths_nm") or [], list):
            raise CubeError(f"{path}: header attribute {_HEADER_ATTRIBUTE}: wavelengths_nm is not a list")
        if len(data.get("wavelengths_nm") or []) != len(channel_nm):
            raise CubeError(f"{path}: the header lists {len(data.get('wavelengths_nm') or [])} bands, the file has {len(channel_nm)}")
    else:  # a cube from before the typed header: pixel size and camera angle from its attributes
        meta: dict = {}
        if "meta" in attributes:
            try:
                meta = json.loads(_text(attributes["meta"]))
            except json.JSONDecodeError:
                raise CubeError(f"{path}: header attribute meta is not valid JSON") from None
        angle = meta.get("camera_angle_deg") if isinstance(meta, dict) else None
        data = {
            "wavelengths_nm": channel_nm,
            "mm_per_pixel": float_attribute(attributes, "mm_per_pixel", path, CubeError),
            "camera_angle_deg": angle if isinstance(angle, (int, float)) else None,
            "software_version": _text(attributes.get("software_version", b"unknown")),
            "provenance": {"session": meta.get("session") if isinstance(meta, dict) else None, "made_by": "unknown (cube without a typed header)"},
        }
    try:
        return CubeHeader.model_validate(data)
    except ValidationError as exc:
        raise CubeError(f"{path}: header: {format_validation_error(exc)}") from None


def _text(value) -> str:
    """A header attribute as text; a damaged one (undecodable bytes, an attribute of unknown type)
    becomes text that the JSON reader then refuses."""
    try:
        return value.decode() if isinstance(value, bytes) else str(value)
    except (UnicodeDecodeError, ValueError, TypeError, RuntimeError):
        return "\ufffd"
