"""The session folder's ``manifest.json``: what was captured, how, and where it lies.

A session folder holds ``manifest.json`` and the raw files as the camera wrote them (and, for
simulated sessions, ``truth/``). The manifest records the schema version, the rig configuration as
used, subject, site and operator, and for every frame its role (``dark``, ``reference``, ``skin``),
band, filter position, exposure, file name, SHA-256 and time. It is rewritten atomically after every
frame (a temporary file, then a rename), so a session broken off at any moment is consistent and can
be resumed.

A manifest is data, not instructions: a file name that would leave the session folder (an absolute
path, ``..``, a drive or a separator) is refused wherever a manifest is read.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Literal, Optional

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from .errors import InputError
from .files import atomic_write, now_iso, safe_member
from .rig import RigConfig, rig_from_dict
from .settings import format_validation_error

__all__ = ["MANIFEST_NAME", "SCHEMA_VERSION", "Exposure", "FrameRecord", "Manifest", "ManifestError", "read_manifest",
           "write_manifest"]

MANIFEST_NAME = "manifest.json"
#: The largest manifest read (a session of ten thousand frames writes about 5 MB).
MAX_MANIFEST_BYTES = 64 << 20
SCHEMA_VERSION = 1
Role = Literal["dark", "reference", "skin"]


class ManifestError(InputError):
    """A manifest that cannot be used; the message names the file and the problem."""


class Exposure(BaseModel):
    """A frame's exposure as the camera reported it."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    iso: int = Field(..., gt=0)
    shutter_s: float = Field(..., gt=0)
    aperture_f: float = Field(..., gt=0)


class FrameRecord(BaseModel):
    """One captured frame."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    role: Role
    band_nm: Optional[float] = Field(None, description="Band of the filter (None for the dark frame).")
    filter_position: int = Field(..., ge=1)
    exposure: Exposure
    file: str = Field(..., description="Raw file, relative to the session folder.")
    sha256: str = Field(..., min_length=64, max_length=64)
    time: str = Field(..., description="ISO 8601 time the frame was taken (UTC).")

    @field_validator("file")
    @classmethod
    def _inside(cls, value: str) -> str:
        return safe_member(value)

    @property
    def key(self) -> tuple[str, Optional[float]]:
        """What the frame is: (role, band); a session has at most one frame per key."""
        return self.role, self.band_nm


class Manifest(BaseModel):
    """The session's record. ``status`` is ``in_progress`` until every planned frame is taken."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    schema_version: int = SCHEMA_VERSION
    software_version: str = "unknown"
    created: str = Field(default_factory=lambda: now_iso())
    status: Literal["in_progress", "complete"] = "in_progress"
    subject: str = ""
    site: str = ""
    operator: str = ""
    simulated: bool = False
    rig: dict = Field(..., description="The rig configuration as used (RigConfig, dumped).")
    frames: list[FrameRecord] = Field(default_factory=list)
    notes: dict = Field(default_factory=dict, description="Free-form extras (simulation seed and scene, …).")

    @field_validator("schema_version")
    @classmethod
    def _version(cls, value: int) -> int:
        if value != SCHEMA_VERSION:
            raise ValueError(f"schema version {value} is not supported (this software reads {SCHEMA_VERSION})")
        return value

    def frame(self, role: str, band_nm: Optional[float] = None) -> Optional[FrameRecord]:
        for f in self.frames:
            if f.role == role and (band_nm is None if f.band_nm is None else band_nm is not None and abs(f.band_nm - band_nm) < 1e-6):
                return f
        return None

    def rig_config(self) -> RigConfig:
        """The rig as a validated ``RigConfig``."""
        return rig_from_dict(self.rig, "manifest rig")


def write_manifest(session: str | Path, manifest: Manifest) -> Path:
    """Write ``manifest.json`` atomically (a temporary file in the folder, flushed, then renamed)."""
    session = Path(session)
    path = session / MANIFEST_NAME
    text = json.dumps(manifest.model_dump(mode="json"), indent=2) + "\n"
    return atomic_write(path, text.encode(), prefix=".manifest-")


def read_manifest(session: str | Path) -> Manifest:
    """Read and validate a session's manifest; ``ManifestError`` names the file and the problem."""
    path = Path(session) / MANIFEST_NAME
    if not path.exists():
        raise ManifestError(f"{Path(session)}: not a session folder (no {MANIFEST_NAME})")
    if path.stat().st_size > MAX_MANIFEST_BYTES:
        raise ManifestError(f"{path}: larger than {MAX_MANIFEST_BYTES >> 20} MB; a session's manifest is a few kB per frame")
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError) as exc:
        raise ManifestError(f"{path}: cannot read ({exc})") from None
    except json.JSONDecodeError as exc:
        raise ManifestError(f"{path}: not valid JSON ({exc})") from None
    except RecursionError:  # the decoder recurses once per level of nesting
        raise ManifestError(f"{path}: nested too deeply to be a manifest; refused") from None
    if not isinstance(data, dict):
        raise ManifestError(f"{path}: expected a JSON object")
    try:
        return Manifest.model_validate(data)
    except ValidationError as exc:
        raise ManifestError(f"{path}: {format_validation_error(exc)}") from None
