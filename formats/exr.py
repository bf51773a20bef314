"""OpenEXR images with named float32 channels and typed header attributes, and the spectral image format.

**Spectral images** (render output, the truth of a simulated session): one channel ``<prefix>_<nm>``
per wavelength (``R_550``), header ``wavelengths_nm`` (float list) and ``mm_per_pixel`` (float).

Every reader names the file, channel and problem in its error; nothing here guesses. The writer is
atomic (a temporary file in the folder, then a rename), as every output of the toolkit is.
"""

from __future__ import annotations

import json
import os
import re
import tempfile
from pathlib import Path

import numpy as np
import torch

from .errors import InputError

__all__ = ["ExrError", "band_channels", "float_attribute", "json_attribute", "read_exr", "read_exr_header", "read_spectral", "write_exr", "write_spectral"]

_BAND = re.compile(r"^([A-Za-z]+)_(\d+(?:\.\d+)?)$")


class ExrError(InputError):
    """An image file that cannot be used; the message names the file, channel and problem."""


def _openexr():
    import OpenEXR  # noqa: PLC0415 (its native library loads only when an image is read or written)

    return OpenEXR


def write_exr(path: str | Path, channels: dict[str, np.ndarray | torch.Tensor], attributes: dict | None = None) -> Path:
    """Write float32 channels ``(H, W)`` and header attributes atomically (temp file, then rename)."""
    OpenEXR = _openexr()
    path = Path(path)
    data = {}
    shape = None
    for name, value in channels.items():
        arr = value.detach().cpu().numpy() if isinstance(value, torch.Tensor) else np.asarray(value)
        arr = np.ascontiguousarray(arr, dtype=np.float32)
        if arr.ndim != 2:
            raise ValueError(f"{path}: channel {name} must be 2-D (H, W), got shape {arr.shape}")
        if shape is not None and arr.shape != shape:
            raise ValueError(f"{path}: channel {name} has shape {arr.shape}, others {shape}")
        shape = arr.shape
        data[name] = arr
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    for key, value in (attributes or {}).items():
        if isinstance(value, (list, tuple, np.ndarray, torch.Tensor)):
            value = np.asarray(value.cpu() if isinstance(value, torch.Tensor) else value, dtype=np.float32)
        header[key] = value
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".tmp-", suffix=".exr")
    os.fchmod(fd, 0o644)  # mkstemp makes it private; outputs are shared data, as every other file written
    os.close(fd)
    try:
        with OpenEXR.File(header, data) as f:
            f.write(tmp)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path


def read_exr(path: str | Path, error: type[Exception] = ExrError) -> tuple[dict[str, np.ndarray], dict]:
    """All channels as float32 ``(H, W)`` arrays and the header; ``error`` names the file."""
    OpenEXR = _openexr()
    path = Path(path)
    if not path.exists():
        raise error(f"{path}: no such file")
    try:
        with OpenEXR.File(str(path)) as f:
            header = dict(f.header())
            channels = {name: np.asarray(c.pixels, dtype=np.float32) for name, c in f.channels().items()}
    except (RuntimeError, OSError, ValueError) as exc:
        raise error(f"{path}: not a readable OpenEXR file ({exc})") from None
    return channels, header


def read_exr_header(path: str | Path, error: type[Exception] = ExrError) -> tuple[int, int, dict]:
    """(height, width, header) of an OpenEXR file, read without its pixels: work can be sized, and
    refused, before the image is loaded."""
    OpenEXR = _openexr()
    path = Path(path)
    if not path.exists():
        raise error(f"{path}: no such file")
    try:
        with OpenEXR.File(str(path), header_only=True) as f:
            header = dict(f.header())
        (x0, y0), (x1, y1) = (tuple(int(v) for v in corner) for corner in header["dataWindow"])
    except (RuntimeError, OSError, ValueError, KeyError, TypeError) as exc:
        raise error(f"{path}: not a readable OpenEXR file ({exc})") from None
    return y1 - y0 + 1, x1 - x0 + 1, header


def json_attribute(header: dict, key: str, default):
    """A header attribute written as JSON text (a dict, as ``flag_bits``) or as the value itself (a float
    list, as ``wavelengths_nm``); ``default`` where the header lacks it."""
    value = header.get(key, default)
    return json.loads(value) if isinstance(value, (str, bytes)) else value


def float_attribute(header: dict, key: str, path: Path, error: type[Exception] = ExrError) -> float:
    """A float header attribute, to float32's 7 significant digits (it is stored as float32)."""
    if key not in header:
        raise error(f"{path}: header attribute {key} is missing")
    try:
        value = float(header[key])
    except (TypeError, ValueError):
        raise error(f"{path}: header attribute {key} must be a number, got {shown(header[key])}") from None
    return float(f"{value:.7g}")


def shown(value) -> str:
    """A header value for an error message, shortened; a damaged file's attribute may not even print."""
    try:
        text = repr(value)
    except (UnicodeDecodeError, ValueError, TypeError, RuntimeError):
        return f"an unreadable {type(value).__name__}"
    return text if len(text) <= 80 else text[:77] + "..."


def band_channels(channels: dict[str, np.ndarray], prefix: str) -> list[tuple[float, str]]:
    """(wavelength nm, channel name) of every ``<prefix>_<nm>`` channel, by wavelength."""
    found = []
    for name in channels:
        m = _BAND.match(name)
        if m and m.group(1) == prefix:
            found.append((float(m.group(2)), name))
    return sorted(found)


def write_spectral(path: str | Path, image: torch.Tensor, wavelength_nm: torch.Tensor, mm_per_pixel: float,
                   prefix: str = "R", attributes: dict | None = None, extra: dict[str, torch.Tensor] | None = None) -> Path:
    """Write ``(L, H, W)`` as channels ``<prefix>_<nm>`` with the wavelengths in the header; ``extra``:
    more spectral images ``(L, H, W)`` by prefix (a Monte Carlo render's standard error, ``SE``)."""
    wl = [float(w) for w in torch.as_tensor(wavelength_nm).reshape(-1)]
    if image.ndim != 3 or image.shape[0] != len(wl):
        raise ValueError(f"spectral image must be (L, H, W) with L = {len(wl)}, got {tuple(image.shape)}")
    channels = {f"{prefix}_{w:g}": image[j] for j, w in enumerate(wl)}
    for name, values in (extra or {}).items():
        channels.update({f"{name}_{w:g}": values[j] for j, w in enumerate(wl)})
    return write_exr(path, channels, {"wavelengths_nm": wl, "mm_per_pixel": float(mm_per_pixel), **(attributes or {})})


def read_spectral(path: str | Path, prefix: str = "R", error: type[Exception] = ExrError) -> tuple[torch.Tensor, torch.Tensor, dict]:
    """``(L, H, W)`` image, ``(L,)`` wavelengths and the header of a spectral EXR."""
    path = Path(path)
    channels, header = read_exr(path, error)
    bands = band_channels(channels, prefix)
    if not bands:
        raise error(f"{path}: no channels {prefix}_<nm> (has: {', '.join(sorted(channels)) or 'none'})")
    image = torch.stack([torch.from_numpy(channels[n].copy()) for _, n in bands])
    return image, torch.tensor([w for w, _ in bands], dtype=torch.float64), header
