"""What the capture session knows of its instruments: a filter wheel and a camera (with its flash).

The session code talks to the base classes ``FilterWheel`` and ``Camera`` only. They hold the rules
every driver keeps: the wheel's 6 or 12 positions, the check of a requested position and the read-back
after a move; the camera's read-back of each exposure setting; an idempotent ``close()`` and use as a
context manager. Real drivers (the Thorlabs FW102C over a serial port, a camera through gphoto2) and
their simulated twins derive from them and add only what is particular to a device, so every session
that runs at the bench also runs, unchanged, against simulated hardware.

Positions are numbered as the FW102C numbers them: 1 … ``position_count``.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence, TypeVar

from ...formats.errors import SkinlayersError

__all__ = ["Camera", "CameraError", "DeviceError", "ExposureSettings", "FilterWheel", "WheelError"]


class DeviceError(SkinlayersError, RuntimeError):
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


_Self = TypeVar("_Self", bound="_Instrument")


class _Instrument(ABC):
    """Closing, once, and use as a context manager (closed on leaving the block, also on an error)."""

    name = "instrument"
    """How error messages name the device."""

    _closed = False

    @property
    def closed(self) -> bool:
        """Whether ``close()`` has been called."""
        return self._closed

    def close(self) -> None:
        """Release the device; a second call does nothing."""
        if not self._closed:
            self._closed = True
            self._close()

    def _close(self) -> None:
        """Release what the device holds (a port, a handle); nothing by default."""

    def __enter__(self: _Self) -> _Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class FilterWheel(_Instrument):
    """A motorised filter wheel with positions 1 … ``position_count``.

    A driver implements ``identify()``, ``position()``, ``_position_count()`` and ``_move(position)``,
    and ``_close()`` where it holds something; it may extend ``_error`` to say more about a failure.
    """

    POSITION_COUNTS = (6, 12)
    """The position counts of an FW102C (6) and an FW212C (12)."""

    name = "filter wheel"

    @property
    def position_count(self) -> int:
        """Number of filter positions, 6 or 12; ``WheelError`` if the wheel reports another."""
        count = self._position_count()
        if count not in self.POSITION_COUNTS:
            raise self._error(f"it reports {count} positions, expected {' or '.join(map(str, self.POSITION_COUNTS))}")
        return count

    @abstractmethod
    def identify(self) -> str:
        """A line naming the device (model, firmware, serial where known)."""

    @abstractmethod
    def position(self) -> int:
        """The position the wheel reports now, 1 … ``position_count``."""

    def move_to(self, position: int) -> None:
        """Move to ``position`` and return once the wheel reports it there; ``WheelError`` otherwise.

        A position that is not an int in 1 … ``position_count`` raises ``ValueError`` before the wheel
        is asked to move.
        """
        count = self.position_count
        if isinstance(position, bool) or not isinstance(position, int) or not 1 <= position <= count:
            raise ValueError(f"{self.name}: position {position!r} outside 1–{count}")
        found = self._move(position)
        if found != position:
            raise self._error(f"asked for position {position}, it reports {found}")

    @abstractmethod
    def _position_count(self) -> int:
        """The number of positions the wheel reports."""

    @abstractmethod
    def _move(self, position: int) -> int:
        """Move to a valid ``position``; the position the wheel reports once it has stopped."""

    def _error(self, what: str) -> WheelError:
        return WheelError(f"{self.name}: {what}")


EXPOSURE_FIELDS = {"iso": "iso", "shutter": "shutter_s", "aperture": "aperture_f"}
"""Camera setting → the ``ExposureSettings`` field it sets, in the order a camera is configured."""
# An exposure stop is log2 of ISO or shutter time and 2·log2 of the f-number (light ∝ 1/f²).
_STOPS_PER_LOG2 = {"iso": 1.0, "shutter": 1.0, "aperture": 2.0}


def stops_apart(setting: str, a: float, b: float) -> float:
    """How many stops of exposure two values of ``setting`` (a key of ``EXPOSURE_FIELDS``) differ."""
    return abs(math.log2(a / b)) * _STOPS_PER_LOG2[setting]


def format_shutter_s(seconds: float) -> str:
    """The camera's way of writing a shutter time: 0.01 → ``1/100``, 0.3 → ``0.3``, 2 → ``2``."""
    if not seconds > 0:
        raise ValueError(f"shutter time must be > 0 s, got {seconds}")
    if seconds < 1:
        inverse = 1 / seconds
        if abs(inverse - round(inverse)) < 1e-6 * inverse:
            return f"1/{round(inverse)}"
    return f"{seconds:g}"


def show_setting(setting: str, value: float) -> str:
    """A value of ``setting`` as a photographer writes it: ``1/100 s``, ``f/10``, ``ISO 200``."""
    if setting == "shutter":
        return f"{format_shutter_s(value)} s"
    if setting == "aperture":
        return f"f/{value:g}"
    return f"ISO {value:g}"


class Camera(_Instrument):
    """A camera that fires the flash with each exposure and delivers raw files.

    A driver implements ``identify()``, ``capture(destination)`` and ``_set(setting, value)``, and
    ``_close()`` where it holds something.
    """

    name = "camera"

    # One rule for every camera: a value counts as the one asked for within this many stops of exposure
    # (see stops_apart), so the same number serves ISO, shutter and aperture. Cameras show nominal
    # values (1/3 s as 0.3: 0.15 stop off; f/5.657 as 5.6) and their settings lie 1/3 stop apart:
    # 1/6 stop takes the nominal value and still tells the neighbours apart. A camera that reports
    # exactly the values of its own list sets a tighter tolerance, so that an ignored setting shows.
    readback_tolerance_stops = 1 / 6

    @abstractmethod
    def identify(self) -> str:
        """A line naming the camera (model, serial where known)."""

    def configure(self, exposure: ExposureSettings) -> ExposureSettings:
        """Set ISO, shutter and aperture, read each back, and return what the camera reports.

        Cameras ignore values they do not support silently; a read-back that differs from the request
        by more than ``readback_tolerance_stops`` raises ``CameraError`` naming the setting, the value
        asked for and the value found (the settings after it are then left as they were).
        """
        found = {}
        for setting, field in EXPOSURE_FIELDS.items():
            asked = float(getattr(exposure, field))
            value, report = self._set(setting, asked)
            if value is None or stops_apart(setting, value, asked) > self.readback_tolerance_stops:
                raise CameraError(
                    f"{self.name}: {setting} asked {show_setting(setting, asked)}, the camera reports {report}"
                )
            found[field] = value
        return ExposureSettings(iso=round(found["iso"]), shutter_s=found["shutter_s"], aperture_f=found["aperture_f"])

    @abstractmethod
    def capture(self, destination: Path) -> Path:
        """Expose one frame and write its raw file to ``destination`` (the suffix may be changed to
        the camera's raw format); return the path written. ``CameraError`` if no frame arrives."""

    @abstractmethod
    def _set(self, setting: str, value: float) -> tuple[Optional[float], str]:
        """Set ``setting`` (a key of ``EXPOSURE_FIELDS``: ISO, seconds or f-number) to ``value`` and
        read it back: the value the camera reports (None if it reports no number, e.g. ``bulb``) and
        how it reported it, for the error message."""

    def _nearest(self, setting: str, value: float, offered: Sequence[float]) -> Optional[int]:
        """Index of the offered value that counts as ``value`` (the nearest, within
        ``readback_tolerance_stops``), or None: the value a camera with these choices can set."""
        if not offered:
            return None
        best = min(range(len(offered)), key=lambda i: stops_apart(setting, offered[i], value))
        return best if stops_apart(setting, offered[best], value) <= self.readback_tolerance_stops else None
