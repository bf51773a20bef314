"""The parameter-map and spectral-image file formats (OpenEXR), read and written in one place.

**Maps** (``maps.exr``): one float32 channel per parameter named exactly ``C_m``, ``beta_m``, ``C_he``,
``C_bc``, ``C_hd``, optionally ``rho_s``; optionally interface absorbance channels ``P_<nm>`` (one per
wavelength, e.g. ``P_450``); the header attribute ``mm_per_pixel`` (float). Other channels (a fit's
``residual_rms``, flags) are carried along and ignored by the renderer.

**Absorbance** (``ink.exr``, veins): channels ``P_<nm>`` and ``mm_per_pixel``.

**Spectral images** (render output, reflectance cubes): channels ``R_<nm>``, header ``wavelengths_nm``
and ``mm_per_pixel``.

Every reader names the file, channel and problem in its error; nothing here guesses.
"""

from __future__ import annotations

import os
import re
import tempfile
from pathlib import Path

import numpy as np
import torch

from .maps import MAP_CHANNELS, MapsError, SkinMaps
from .params import PARAMETER_NAMES

__all__ = ["read_absorbance", "read_exr", "read_maps", "read_spectral", "write_exr", "write_maps", "write_spectral"]

_BAND = re.compile(r"^([A-Za-z]+)_(\d+(?:\.\d+)?)$")


def _openexr():
    import OpenEXR  # noqa: PLC0415 (optional-looking heavy import kept local)

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
    os.close(fd)
    try:
        with OpenEXR.File(header, data) as f:
            f.write(tmp)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path


def read_exr(path: str | Path) -> tuple[dict[str, np.ndarray], dict]:
    """All channels as float32 ``(H, W)`` arrays and the header; errors name the file."""
    OpenEXR = _openexr()
    path = Path(path)
    if not path.exists():
        raise MapsError(f"{path}: no such file")
    try:
        with OpenEXR.File(str(path)) as f:
            header = dict(f.header())
            channels = {name: np.asarray(c.pixels, dtype=np.float32) for name, c in f.channels().items()}
    except (RuntimeError, OSError, ValueError) as exc:
        raise MapsError(f"{path}: not a readable OpenEXR file ({exc})") from None
    return channels, header


def _float_attr(header: dict, key: str, path: Path) -> float:
    if key not in header:
        raise MapsError(f"{path}: header attribute {key} is missing")
    try:
        value = float(header[key])
    except (TypeError, ValueError):
        raise MapsError(f"{path}: header attribute {key} must be a number, got {header[key]!r}") from None
    return float(f"{value:.7g}")  # stored as float32: drop the representation noise


def _bands(channels: dict[str, np.ndarray], prefix: str) -> list[tuple[float, str]]:
    found = []
    for name in channels:
        m = _BAND.match(name)
        if m and m.group(1) == prefix:
            found.append((float(m.group(2)), name))
    return sorted(found)


def read_maps(path: str | Path, dtype: torch.dtype = torch.float32, device=None) -> SkinMaps:
    """Read and validate a maps file (B = 1)."""
    path = Path(path)
    channels, header = read_exr(path)
    missing = [n for n in PARAMETER_NAMES if n not in channels]
    if missing:
        raise MapsError(f"{path}: missing channel(s) {', '.join(missing)} (has: {', '.join(sorted(channels)) or 'none'})")
    mm = _float_attr(header, "mm_per_pixel", path)
    tensor = lambda a: torch.from_numpy(a.copy()).to(dtype=dtype, device=device)[None]  # noqa: E731
    maps = {n: tensor(channels[n]) for n in PARAMETER_NAMES}
    rho = tensor(channels["rho_s"]) if "rho_s" in channels else None
    bands = _bands(channels, "P")
    absorbance = wl = None
    if bands:
        absorbance = torch.stack([tensor(channels[n])[0] for _, n in bands])[None]
        wl = torch.tensor([w for w, _ in bands], dtype=torch.float64)
    return SkinMaps(**maps, mm_per_pixel=mm, rho_s=rho, absorbance=absorbance, absorbance_wavelength_nm=wl).validate(str(path))


def write_maps(path: str | Path, maps: SkinMaps, extra: dict[str, torch.Tensor] | None = None, attributes: dict | None = None,
               index: int = 0) -> Path:
    """Write item ``index`` of a batch of maps (and extra channels such as residuals)."""
    channels: dict[str, torch.Tensor] = {n: getattr(maps, n)[index] for n in PARAMETER_NAMES}
    if maps.rho_s is not None:
        channels["rho_s"] = maps.rho_s[index]
    if maps.absorbance is not None and maps.absorbance_wavelength_nm is not None:
        for j, w in enumerate(maps.absorbance_wavelength_nm.tolist()):
            channels[f"P_{w:g}"] = maps.absorbance[index, j]
    for name, value in (extra or {}).items():
        if name in MAP_CHANNELS:
            raise ValueError(f"extra channel {name} would overwrite a parameter")
        channels[name] = value
    return write_exr(path, channels, {"mm_per_pixel": float(maps.mm_per_pixel), **(attributes or {})})


def read_absorbance(path: str | Path) -> tuple[torch.Tensor, torch.Tensor, float]:
    """An interface absorbance file: ``(L, H, W)`` absorbance, ``(L,)`` wavelengths, mm per pixel."""
    path = Path(path)
    channels, header = read_exr(path)
    bands = _bands(channels, "P")
    if not bands:
        raise MapsError(f"{path}: no absorbance channels P_<nm> (has: {', '.join(sorted(channels)) or 'none'})")
    stack = torch.stack([torch.from_numpy(channels[n].copy()) for _, n in bands])
    for (w, n), layer in zip(bands, stack):
        if not bool(torch.isfinite(layer).all()) or bool((layer < 0).any()):
            raise MapsError(f"{path}: channel {n} must be finite and >= 0")
    return stack, torch.tensor([w for w, _ in bands], dtype=torch.float64), _float_attr(header, "mm_per_pixel", path)


def write_spectral(path: str | Path, image: torch.Tensor, wavelength_nm: torch.Tensor, mm_per_pixel: float,
                   prefix: str = "R", attributes: dict | None = None) -> Path:
    """Write ``(L, H, W)`` as channels ``<prefix>_<nm>`` with the wavelengths in the header."""
    wl = [float(w) for w in torch.as_tensor(wavelength_nm).reshape(-1)]
    if image.ndim != 3 or image.shape[0] != len(wl):
        raise ValueError(f"spectral image must be (L, H, W) with L = {len(wl)}, got {tuple(image.shape)}")
    channels = {f"{prefix}_{w:g}": image[j] for j, w in enumerate(wl)}
    return write_exr(path, channels, {"wavelengths_nm": wl, "mm_per_pixel": float(mm_per_pixel), **(attributes or {})})


def read_spectral(path: str | Path, prefix: str = "R") -> tuple[torch.Tensor, torch.Tensor, dict]:
    """``(L, H, W)`` image, ``(L,)`` wavelengths and the header of a spectral EXR."""
    path = Path(path)
    channels, header = read_exr(path)
    bands = _bands(channels, prefix)
    if not bands:
        raise MapsError(f"{path}: no channels {prefix}_<nm> (has: {', '.join(sorted(channels)) or 'none'})")
    image = torch.stack([torch.from_numpy(channels[n].copy()) for _, n in bands])
    return image, torch.tensor([w for w, _ in bands], dtype=torch.float64), header
