"""The errors calibration raises: each names the file, band or value at fault in one line.

Refusals (the cube would be wrong everywhere, or the input is not what the manifest says) are these
exceptions; problems that leave part of the cube usable are *flags* (``checks.Flag``), recorded in
``calibration.json`` and, where they are local, in the cube's mask. ``checks.py`` documents which is which.
"""

from __future__ import annotations

from ..formats.errors import InputError, SkinlayersError

__all__ = [
    "BandMissingError",
    "CalibrationError",
    "ChecksumMismatchError",
    "FrameMissingError",
    "RawDecodeError",
    "WindowNotFoundError",
]


class CalibrationError(InputError):
    """A session, frame or setting calibration cannot use; the message names it and the problem."""


class RawDecodeError(CalibrationError):
    """A raw file that cannot be decoded (corrupt, truncated, not a Bayer raw); names the file."""


class ChecksumMismatchError(CalibrationError):
    """A frame whose SHA-256 differs from the manifest's record."""


class BandMissingError(CalibrationError):
    """The manifest lacks a frame the calibration needs (a band's reference or skin frame, the dark frame)."""


class WindowNotFoundError(CalibrationError):
    """No window, or more than one candidate, in a skin frame."""


class FrameMissingError(SkinlayersError, FileNotFoundError):
    """A file the manifest names is not in the session folder."""
