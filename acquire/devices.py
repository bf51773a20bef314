"""What the capture session knows of its instruments: a filter wheel and a camera (with its flash).

The session code talks to these protocols only. Real drivers (the Thorlabs FW102C over a serial
port, a camera through gphoto2) and their simulated twins implement them alike, so every session
that runs at the bench also runs, unchanged, against simulated hardware.

Positions are numbered as the FW102C numbers them: 1 … ``position_count``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Protocol, runtime_checkable

__all__ = ["Camera", "CameraError", "DeviceError", "ExposureSettings", "FilterWheel", "WheelError"]


class DeviceError(RuntimeError):
    """An instrument did not do what it was asked; the message names the device and what happened."""


class WheelError(DeviceError):
    """The filter wheel did not answer, answered wrongly, or stopped at the wrong position."""


class CameraError(DeviceError):
    """The camera was not found, refused a setting, or did not deliver a frame."""


@dataclass(frozen=True)
class ExposureSettings:
    """Exposure of one frame: ISO, shutter time in seconds and aperture as an f-number."""

    iso: int
    shutter_s: float
    aperture_f: float

    def __post_init__(self) -> None:
        if self.iso <= 0 or not self.shutter_s > 0 or not self.aperture_f > 0:
            raise ValueError(f"exposure must have iso > 0, shutter_s > 0 and aperture_f > 0, got {self}")

    def as_dict(self) -> dict[str, float]:
        return {"iso": self.iso, "shutter_s": self.shutter_s, "aperture_f": self.aperture_f}


@runtime_checkable
class FilterWheel(Protocol):
    """A motorised filter wheel."""

    @property
    def position_count(self) -> int:
        """Number of filter positions (6 or 12 on an FW102C)."""
        ...

    def identify(self) -> str:
        """A line naming the device (model, firmware, serial where known)."""
        ...

    def position(self) -> int:
        """The position the wheel reports now, 1 … ``position_count``."""
        ...

    def move_to(self, position: int) -> None:
        """Move to ``position`` and return once the wheel reports it there; ``WheelError`` otherwise."""
        ...

    def close(self) -> None:
        ...


@runtime_checkable
class Camera(Protocol):
    """A camera that fires the flash with each exposure and delivers raw files."""

    def identify(self) -> str:
        """A line naming the camera (model, serial where known)."""
        ...

    def configure(self, exposure: ExposureSettings) -> ExposureSettings:
        """Set ISO, shutter and aperture, read each back, and return what the camera reports.

        Cameras ignore values they do not support silently; a read-back that differs from the request
        raises ``CameraError`` naming the setting, the value asked for and the value found.
        """
        ...

    def capture(self, destination: Path) -> Path:
        """Expose one frame and write its raw file to ``destination`` (the suffix may be changed to
        the camera's raw format); return the path written. ``CameraError`` if no frame arrives."""
        ...

    def close(self) -> None:
        ...
