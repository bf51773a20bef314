"""The reflectance cube: calibration's output and reconstruction's input, defined once here.

``cube.exr`` is a float32 OpenEXR with one channel ``R_<nm>`` per band (reflectance factor, 0–1 for
skin; the ratio to an ideal white diffuser seen the same way) and a channel ``mask`` (1 where a pixel
is valid in every band, 0 where it is saturated, under-exposed, outside the window or otherwise
flagged). Header: ``wavelengths_nm`` (float list), ``mm_per_pixel``, ``software_version`` and
``meta`` (a JSON string: window corners per band, the camera angle, the session it came from, …).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import torch

from ..model.maps import MapsError
from ..model.maps_io import read_exr, write_exr

__all__ = ["Cube", "CubeError", "read_cube", "write_cube"]


class CubeError(ValueError):
    """A cube file that cannot be used; the message names the file and the problem."""


@dataclass
class Cube:
    """Reflectance ``(L, H, W)`` at ``wavelength_nm`` ``(L,)``, a validity ``mask`` ``(H, W)`` (bool)."""

    reflectance: torch.Tensor
    wavelength_nm: torch.Tensor
    mask: torch.Tensor
    mm_per_pixel: float
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        r = self.reflectance
        if r.ndim != 3:
            raise CubeError(f"reflectance must be (L, H, W), got {tuple(r.shape)}")
        if self.wavelength_nm.numel() != r.shape[0]:
            raise CubeError(f"{self.wavelength_nm.numel()} wavelengths for {r.shape[0]} bands")
        if tuple(self.mask.shape) != tuple(r.shape[1:]):
            raise CubeError(f"mask has shape {tuple(self.mask.shape)}, the bands {tuple(r.shape[1:])}")
        if not self.mm_per_pixel > 0:
            raise CubeError(f"mm_per_pixel must be > 0, got {self.mm_per_pixel!r}")

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self.reflectance.shape)  # type: ignore[return-value]


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version  # noqa: PLC0415

    try:
        return version("skinlayers")
    except PackageNotFoundError:
        return "0+unknown"


def write_cube(path: str | Path, cube: Cube) -> Path:
    """Write a cube atomically."""
    wl = [float(w) for w in cube.wavelength_nm.reshape(-1).tolist()]
    channels = {f"R_{w:g}": cube.reflectance[j] for j, w in enumerate(wl)}
    channels["mask"] = cube.mask.to(torch.float32)
    attributes = {
        "wavelengths_nm": wl,
        "mm_per_pixel": float(cube.mm_per_pixel),
        "software_version": _version(),
        "meta": json.dumps(cube.meta, sort_keys=True, default=str),
    }
    return write_exr(path, channels, attributes)


def read_cube(path: str | Path) -> Cube:
    """Read a cube; ``CubeError`` names the file and what is wrong (no bands, no mask, NaN, …)."""
    path = Path(path)
    try:
        channels, header = read_exr(path)
    except MapsError as exc:
        raise CubeError(str(exc)) from None
    bands = []
    for name in channels:
        if name.startswith("R_"):
            try:
                bands.append((float(name[2:]), name))
            except ValueError:
                raise CubeError(f"{path}: channel {name} is not R_<nm>") from None
    if not bands:
        raise CubeError(f"{path}: no reflectance channels R_<nm> (has: {', '.join(sorted(channels)) or 'none'})")
    if "mask" not in channels:
        raise CubeError(f"{path}: channel mask is missing")
    bands.sort()
    refl = torch.stack([torch.from_numpy(channels[n].copy()) for _, n in bands])
    for (w, n), layer in zip(bands, refl):
        if not bool(torch.isfinite(layer).all()):
            raise CubeError(f"{path}: channel {n} has {int((~torch.isfinite(layer)).sum())} NaN or infinite pixel(s)")
    if "mm_per_pixel" not in header:
        raise CubeError(f"{path}: header attribute mm_per_pixel is missing")
    try:
        mm = float(f"{float(header['mm_per_pixel']):.7g}")
    except (TypeError, ValueError):
        raise CubeError(f"{path}: header attribute mm_per_pixel must be a number") from None
    meta: dict = {}
    if "meta" in header:
        raw = header["meta"]
        try:
            meta = json.loads(raw.decode() if isinstance(raw, bytes) else str(raw))
        except json.JSONDecodeError:
            raise CubeError(f"{path}: header attribute meta is not valid JSON") from None
    mask = torch.from_numpy(channels["mask"].copy()) > 0.5
    return Cube(refl, torch.tensor([w for w, _ in bands], dtype=torch.float64), mask, mm, meta)
