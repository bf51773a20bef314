"""Calibration: raw frames of a session to a reflectance cube (dark, flat, gray card, polarization,
window detection and band alignment).

``calibrate_session(session_dir, out_dir=None, settings=None, progress=None, *, overwrite=False)`` runs
the whole chain; the modules hold one step each: ``raw`` (decoding, superpixels), ``window`` (detection,
rectification), ``align`` (bands to each other), ``corrections`` (the radiometric factors), ``checks``
(what refuses and what is flagged), ``report`` (contact sheet). The cube it writes is defined in
``formats/cube.py``.
"""

from .checks import Flag
from .errors import (
    BandMissingError,
    CalibrationError,
    ChecksumMismatchError,
    FrameMissingError,
    RawDecodeError,
    WindowNotFoundError,
)
from .pipeline import CalibrationResult, calibrate_session, default_out_dir
from .settings import CalibrationSettings, SettingsFileError, load_calibration_settings

__all__ = [
    "BandMissingError",
    "CalibrationError",
    "CalibrationResult",
    "CalibrationSettings",
    "ChecksumMismatchError",
    "Flag",
    "FrameMissingError",
    "RawDecodeError",
    "SettingsFileError",
    "WindowNotFoundError",
    "calibrate_session",
    "default_out_dir",
    "load_calibration_settings",
]
