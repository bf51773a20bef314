"""Calibrated reflectance cubes from other hyperspectral cameras and tools, read into the one ``Cube``.

A lab with a push-broom or snapshot camera (ENVI ``.hdr``/``.img`` from Specim, Headwall, Resonon),
or cubes kept as multi-page TIFF, NumPy ``.npz`` or HDF5, fits them like skinlayers' own ``cube.exr``:
``read_cube_file`` returns the same typed ``Cube`` (reflectance factor ``(L, H, W)``, a validity mask,
a ``CubeHeader``), so ``reconstruct`` and ``batch`` take any of them.

What each file must say, and where (a file that lacks a wavelength or a scale is refused in one line):

| what | ENVI header | TIFF (tifffile's JSON description) | ``.npz`` array / HDF5 dataset or attribute |
|---|---|---|---|
| bands' centres | ``wavelength`` (+ ``wavelength units``) | ``wavelengths_nm`` | ``wavelengths_nm`` |
| bands' widths (optional) | ``fwhm`` | ``fwhm_nm`` | ``fwhm_nm`` |
| reflectance scale | ``reflectance scale factor`` | ``reflectance_scale`` | ``reflectance_scale`` |
| pixel side on the skin | ``mm per pixel`` | ``mm_per_pixel`` | ``mm_per_pixel`` |
| validity mask (optional) | a band named ``mask`` | ``mask`` (true: the last page) | ``mask`` ``(H, W)`` |
| camera off the light's axis (optional, °) | ``camera angle`` | ``camera_angle_deg`` | ``camera_angle_deg`` |

The pixels: ENVI in any interleave (``spectral`` reads it); TIFF one page per band ``(L, H, W)``; NumPy
and HDF5 the array ``reflectance`` ``(L, H, W)``. The reflectance is the stored value divided by the
scale (a scale of 1 where the values are floats already within 0–``MAX_FLOAT_REFLECTANCE``; integers
need one). Pixels that are NaN, infinite or ENVI's ``data ignore value`` in any band are masked out.
Where no width is given, each band's width is taken as its spacing to its neighbours (the header says
so in its provenance). The pixel side may come from the command line (``--mm-per-pixel``) instead.
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from pydantic import ValidationError

from ..cube import Cube, CubeError, CubeHeader, Provenance, read_cube
from ..settings import format_validation_error

__all__ = ["CUBE_READERS", "CUBE_WRITERS", "ForeignCube", "read_cube_file", "write_cube_file"]

#: Float reflectance above this (anywhere in the cube) is taken for percent or counts: a scale is needed.
MAX_FLOAT_REFLECTANCE = 2.0
#: ENVI's wavelength units, as the factor to nanometres.
_UNITS_TO_NM = {"nm": 1.0, "nanometers": 1.0, "nanometer": 1.0, "um": 1e3, "µm": 1e3, "micrometers": 1e3,
                "micrometer": 1e3, "microns": 1e3, "micron": 1e3}
#: Below this, band centres without units are taken for micrometres (no skin band lies under 5 nm).
_MICROMETRES_BELOW = 5.0


class ForeignCube:
    """What a reader found in a file, before it becomes a ``Cube``: the stored values ``(L, H, W)``, the
    bands' centres (nm) and widths (nm or None), the scale, the pixel side (mm or None), a mask or None,
    the value that marks a missing pixel, the camera's angle (° or None)."""

    def __init__(self, values: np.ndarray, wavelengths_nm: list[float], fwhm_nm: list[float] | None, scale: float | None,
                 mm_per_pixel: float | None, mask: np.ndarray | None, ignore_value: float | None = None,
                 camera_angle_deg: float | None = None) -> None:
        self.values, self.wavelengths_nm, self.fwhm_nm = values, wavelengths_nm, fwhm_nm
        self.scale, self.mm_per_pixel, self.mask, self.ignore_value = scale, mm_per_pixel, mask, ignore_value
        self.camera_angle_deg = camera_angle_deg


def read_cube_file(path: str | Path, mm_per_pixel: float | None = None) -> Cube:
    """Any cube: skinlayers' ``cube.exr``, or one of ``CUBE_READERS``' formats; ``mm_per_pixel`` where the
    file does not say it (the file's own value wins where both are given and agree; refused where they differ)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".exr":
        cube = read_cube(path)
        _same_pixel(path, cube.mm_per_pixel, mm_per_pixel)
        return cube
    if suffix not in CUBE_READERS:
        raise CubeError(f"{path}: not a cube file skinlayers reads (.exr, {', '.join(sorted(CUBE_READERS))})")
    if not path.is_file():
        raise CubeError(f"{path}: no such file")
    found = CUBE_READERS[suffix](path)
    return _to_cube(path, found, mm_per_pixel)


def _to_cube(path: Path, found: ForeignCube, mm_per_pixel: float | None) -> Cube:
    values = np.asarray(found.values)
    if values.ndim != 3 or values.shape[0] != len(found.wavelengths_nm):
        raise CubeError(f"{path}: {len(found.wavelengths_nm)} wavelengths for pixels of shape {values.shape} "
                        "(expected one (H, W) image per band)")
    scale = _scale(path, values, found.scale)
    _same_pixel(path, found.mm_per_pixel, mm_per_pixel)
    mm = found.mm_per_pixel if found.mm_per_pixel is not None else mm_per_pixel
    if mm is None:
        raise CubeError(f"{path}: the pixel's side on the skin is not in the file: give --mm-per-pixel")
    reflectance = torch.from_numpy(values.astype(np.float64) / scale).float()
    valid = torch.isfinite(reflectance).all(0)
    if found.ignore_value is not None:
        valid &= ~torch.from_numpy(np.any(values == found.ignore_value, axis=0))
    if found.mask is not None:
        mask = np.asarray(found.mask)
        if mask.shape != values.shape[1:]:
            raise CubeError(f"{path}: the mask is {mask.shape}, the bands {values.shape[1:]}")
        valid &= torch.from_numpy(mask != 0)
    reflectance = torch.where(torch.isfinite(reflectance), reflectance, torch.zeros(()))  # masked pixels keep their values
    fwhm, source = (found.fwhm_nm, "the file") if found.fwhm_nm is not None else (_spacing(found.wavelengths_nm), "the bands' spacing")
    try:
        header = CubeHeader(wavelengths_nm=[float(w) for w in found.wavelengths_nm], band_fwhm_nm=[float(w) for w in fwhm],
                            mm_per_pixel=float(mm), camera_angle_deg=found.camera_angle_deg,
                            provenance=Provenance(made_by=f"{path.suffix.lower()} file, read by skinlayers", session=str(path)),
                            calibration={"reflectance_scale": scale, "band_fwhm_from": source})
    except ValidationError as exc:
        raise CubeError(f"{path}: {format_validation_error(exc)}") from None
    return Cube(reflectance, valid, header)


def _scale(path: Path, values: np.ndarray, scale: float | None) -> float:
    if scale is not None:
        if not (math.isfinite(scale) and scale > 0):
            raise CubeError(f"{path}: reflectance scale {scale!r}: must be a positive number")
        return float(scale)
    if np.issubdtype(values.dtype, np.integer):
        raise CubeError(f"{path}: integer values ({values.dtype}) and no reflectance scale in the file: "
                        "say what value a reflectance of 1 is stored as (ENVI: reflectance scale factor)")
    top = float(np.nanmax(np.where(np.isfinite(values), values, np.nan))) if values.size else 0.0
    if top > MAX_FLOAT_REFLECTANCE:
        raise CubeError(f"{path}: values up to {top:g} and no reflectance scale in the file: a reflectance factor "
                        "is 0–1; say what value a reflectance of 1 is stored as")
    return 1.0


def _same_pixel(path: Path, in_file: float | None, given: float | None) -> None:
    if in_file is not None and given is not None and abs(in_file - given) > 1e-6 * in_file:
        raise CubeError(f"{path}: the file says {in_file:g} mm a pixel, --mm-per-pixel {given:g}")


def _spacing(wavelengths_nm: list[float]) -> list[float]:
    """Each band's width taken as its spacing: the mean distance to its neighbours (one neighbour at the ends)."""
    wl = [float(w) for w in wavelengths_nm]
    if len(wl) < 2:
        raise CubeError("one band and no fwhm: its width cannot be taken from the spacing")
    gaps = [b - a for a, b in zip(wl, wl[1:])]
    return [gaps[0]] + [(a + b) / 2 for a, b in zip(gaps, gaps[1:])] + [gaps[-1]]


def _number(text) -> float | None:
    if text is None:
        return None
    try:
        return float(np.asarray(text).reshape(-1)[0]) if not isinstance(text, str) else float(text)
    except (TypeError, ValueError, IndexError):
        return None


def _numbers(path: Path, name: str, values) -> list[float] | None:
    if values is None:
        return None
    try:
        out = [float(v) for v in np.asarray(values, dtype=object).reshape(-1)]
    except (TypeError, ValueError):
        raise CubeError(f"{path}: {name} is not a list of numbers") from None
    return out


# -- ENVI ----------------------------------------------------------------------------------------------

def _read_envi(path: Path) -> ForeignCube:
    from spectral.io import envi  # noqa: PLC0415
    from spectral.utilities.errors import SpyException  # noqa: PLC0415

    try:
        image = envi.open(str(path))
    except (SpyException, OSError, ValueError) as exc:  # not a header, no data file beside it, a damaged field
        raise CubeError(f"{path}: not a readable ENVI cube ({exc})") from None
    meta = image.metadata
    if "wavelength" not in meta:
        raise CubeError(f"{path}: no wavelength in the ENVI header: the bands' centres are needed")
    wl = _numbers(path, "wavelength", meta["wavelength"])
    units = str(meta.get("wavelength units", "")).strip().lower()
    if units and units not in _UNITS_TO_NM:
        raise CubeError(f"{path}: wavelength units {units!r}: expected nanometers or micrometers")
    factor = _UNITS_TO_NM[units] if units else (1e3 if max(wl) < _MICROMETRES_BELOW else 1.0)
    fwhm = _numbers(path, "fwhm", meta.get("fwhm"))
    with warnings.catch_warnings():  # spectral warns of NaN pixels: they are masked below, and said in the mask's share
        warnings.simplefilter("ignore")
        values = np.asarray(image.load()).transpose(2, 0, 1)  # (rows, cols, bands) → (L, H, W)
    names = [str(n).strip().lower() for n in meta.get("band names", [])]
    mask = None
    if "mask" in names:
        k = names.index("mask")
        mask, values = values[k], np.delete(values, k, axis=0)
        wl, fwhm = wl[:k] + wl[k + 1:], None if fwhm is None else fwhm[:k] + fwhm[k + 1:]
    return ForeignCube(values, [w * factor for w in wl], None if fwhm is None else [w * factor for w in fwhm],
                       _number(meta.get("reflectance scale factor")), _number(meta.get("mm per pixel")), mask,
                       _number(meta.get("data ignore value")), _number(meta.get("camera angle")))


# -- TIFF ----------------------------------------------------------------------------------------------

def _read_tiff(path: Path) -> ForeignCube:
    import tifffile  # noqa: PLC0415

    try:
        with tifffile.TiffFile(path) as tif:
            meta = tif.shaped_metadata[0] if tif.shaped_metadata else {}
            values = tif.asarray()
    except (OSError, ValueError, tifffile.TiffFileError) as exc:
        raise CubeError(f"{path}: not a readable TIFF ({exc})") from None
    if "wavelengths_nm" not in meta:
        raise CubeError(f"{path}: no wavelengths_nm in the TIFF's description: the bands' centres are needed")
    values = values.reshape(-1, *values.shape[-2:])
    mask = None
    if meta.get("mask"):
        mask, values = values[-1], values[:-1]
    return ForeignCube(values, _numbers(path, "wavelengths_nm", meta["wavelengths_nm"]), _numbers(path, "fwhm_nm", meta.get("fwhm_nm")),
                       _number(meta.get("reflectance_scale")), _number(meta.get("mm_per_pixel")), mask,
                       camera_angle_deg=_number(meta.get("camera_angle_deg")))


# -- NumPy and HDF5 ------------------------------------------------------------------------------------

def _read_npz(path: Path) -> ForeignCube:
    try:
        with np.load(path, allow_pickle=False) as data:
            fields = {k: data[k] for k in data.files}
    except (OSError, ValueError) as exc:
        raise CubeError(f"{path}: not a readable .npz ({exc})") from None
    return _from_fields(path, fields)


def _read_hdf5(path: Path) -> ForeignCube:
    import h5py  # noqa: PLC0415

    try:
        with h5py.File(path, "r") as f:
            fields = {k: np.asarray(f[k]) for k in f.keys() if isinstance(f[k], h5py.Dataset)}
            fields.update({k: np.asarray(v) for k, v in f.attrs.items() if k not in fields})
    except OSError as exc:
        raise CubeError(f"{path}: not a readable HDF5 file ({exc})") from None
    return _from_fields(path, fields)


def _from_fields(path: Path, fields: dict) -> ForeignCube:
    for name in ("reflectance", "wavelengths_nm"):
        if name not in fields:
            raise CubeError(f"{path}: no {name!r} (has: {', '.join(sorted(fields)) or 'nothing'})")
    return ForeignCube(fields["reflectance"], _numbers(path, "wavelengths_nm", fields["wavelengths_nm"]),
                       _numbers(path, "fwhm_nm", fields.get("fwhm_nm")), _number(fields.get("reflectance_scale")),
                       _number(fields.get("mm_per_pixel")), fields.get("mask"), camera_angle_deg=_number(fields.get("camera_angle_deg")))


# -- writers: a cube out again, for other tools (and the tests' round trips) ------------------------------

def _fields(cube: Cube) -> dict:
    h = cube.header
    return {"wavelengths_nm": list(h.wavelengths_nm), "fwhm_nm": h.band_fwhm_nm, "mm_per_pixel": h.mm_per_pixel,
            "camera_angle_deg": h.camera_angle_deg}


def _write_envi(path: Path, cube: Cube) -> None:
    from spectral.io import envi  # noqa: PLC0415

    f = _fields(cube)
    data = torch.cat([cube.reflectance, cube.mask[None].float()]).permute(1, 2, 0).numpy().astype(np.float32)
    meta = {"wavelength": f["wavelengths_nm"] + [0.0], "wavelength units": "Nanometers", "mm per pixel": f["mm_per_pixel"],
            "band names": [f"R_{w:g}" for w in f["wavelengths_nm"]] + ["mask"], "reflectance scale factor": 1.0}
    if f["fwhm_nm"] is not None:
        meta["fwhm"] = list(f["fwhm_nm"]) + [0.0]
    if f["camera_angle_deg"] is not None:
        meta["camera angle"] = f["camera_angle_deg"]
    envi.save_image(str(path), data, metadata=meta, interleave="bsq", force=True, ext=".img")


def _write_tiff(path: Path, cube: Cube) -> None:
    import tifffile  # noqa: PLC0415

    meta = {k: v for k, v in _fields(cube).items() if v is not None} | {"mask": True, "reflectance_scale": 1.0}
    pages = torch.cat([cube.reflectance, cube.mask[None].float()]).numpy().astype(np.float32)
    tifffile.imwrite(path, pages, photometric="minisblack", metadata=meta)


def _write_npz(path: Path, cube: Cube) -> None:
    f = {k: np.asarray(v) for k, v in _fields(cube).items() if v is not None}
    np.savez(path, reflectance=cube.reflectance.numpy(), mask=cube.mask.numpy(), **f)


def _write_hdf5(path: Path, cube: Cube) -> None:
    import h5py  # noqa: PLC0415

    with h5py.File(path, "w") as out:
        out["reflectance"], out["mask"] = cube.reflectance.numpy(), cube.mask.numpy()
        for k, v in _fields(cube).items():
            if v is not None:
                out.attrs[k] = np.asarray(v)


def write_cube_file(path: str | Path, cube: Cube) -> Path:
    """Write ``cube`` as the format its suffix names (``CUBE_WRITERS``), float32, the mask beside it."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in CUBE_WRITERS:
        raise CubeError(f"{path}: write a cube as {', '.join(sorted(CUBE_WRITERS))} (or cube.exr)")
    CUBE_WRITERS[suffix](path, cube)
    return path


#: The formats read besides ``cube.exr``, by file suffix.
CUBE_READERS: dict[str, Callable[[Path], ForeignCube]] = {
    ".hdr": _read_envi,
    ".tif": _read_tiff,
    ".tiff": _read_tiff,
    ".npz": _read_npz,
    ".h5": _read_hdf5,
    ".hdf5": _read_hdf5,
}

#: The formats written besides ``cube.exr``, by file suffix.
CUBE_WRITERS: dict[str, Callable[[Path, Cube], None]] = {
    ".hdr": _write_envi,
    ".tif": _write_tiff,
    ".tiff": _write_tiff,
    ".npz": _write_npz,
    ".h5": _write_hdf5,
    ".hdf5": _write_hdf5,
}
