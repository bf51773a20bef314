"""What napari shows of skinlayers' files, as napari's layer data: ``(data, keyword arguments, layer type)``.

No napari here: these functions return plain tuples (napari's ``LayerDataTuple``), so the reader of the
plugin (``napari.yaml``) is this module, and a script or a test gets the same layers without a viewer.

- ``maps.exr`` (a fit): each map as an image in its unit and colour map, the maps' σ (hidden), the
  residual fit − measured as a stack on the wavelength axis, the residual RMS, and the flags as labels
  (each pixel's first flag; its names in the layer's features).
- a cube (``cube.exr``, ENVI, TIFF, ``.npz``, HDF5: ``formats.foreign.cubes``): the reflectance as a stack
  on a wavelength axis (in nm where the bands are evenly spaced) and the cube's mask as labels.
- a session folder (its ``manifest.json``): the skin frames and the reference frames, each a stack of
  one superpixel image per band.

Every layer is scaled to millimetres on the skin (a session's frames: camera superpixels) and carries in
its ``metadata["skinlayers"]`` the file it came from and what it is, which the pixel inspector
(``skinlayers.viewer.inspector``) reads.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np

__all__ = ["MAP_LOOKS", "cube_layers", "get_reader", "maps_layers", "read_layers", "session_layers"]

#: Each map's name, unit and colour map in the viewer (units: docs/model.md, "Constants and units").
MAP_LOOKS: dict[str, tuple[str, str, str]] = {
    "C_m": ("melanin C_m", "volume fraction", "magma"),
    "beta_m": ("eumelanin share β_m", "fraction of the melanin", "cividis"),
    "C_he": ("epidermal blood C_he", "volume fraction", "reds"),
    "C_bc": ("carotene C_bc", "volume fraction", "yellow"),
    "C_hd": ("dermal blood C_hd", "volume fraction", "inferno"),
}
#: The suffixes the reader takes (a folder is taken when it holds a session's manifest).
CUBE_SUFFIXES = (".exr", ".hdr", ".tif", ".tiff", ".npz", ".h5", ".hdf5")
#: Of the wavelength axis: band centres this close to even spacing (nm) are drawn in nm on the slider.
EVEN_SPACING_NM = 1e-3

LayerData = tuple  # (data, kwargs, layer_type): napari's LayerDataTuple


def get_reader(path: str | list[str]) -> Callable[[str | list[str]], list[LayerData]] | None:
    """napari's reader hook: ``read_layers`` for a path skinlayers reads, None for any other."""
    if isinstance(path, list):
        if len(path) != 1:
            return None
        path = path[0]
    p = Path(path)
    if p.is_dir():
        return read_layers if (p / "manifest.json").is_file() else None
    return read_layers if p.suffix.lower() in CUBE_SUFFIXES else None


def read_layers(path: str | list[str]) -> list[LayerData]:
    """The layers of a maps file, a cube file or a session folder (see the module's docstring)."""
    p = Path(path[0] if isinstance(path, list) else path)
    if p.is_dir():
        return session_layers(p)
    if p.suffix.lower() == ".exr" and _is_maps(p):
        return maps_layers(p)
    return cube_layers(p)


def _is_maps(path: Path) -> bool:
    """A fit's maps file (its channels hold the maps), not a cube (its channels are bands)."""
    from ..formats.exr import read_exr_header  # noqa: PLC0415 (OpenEXR only when a file is opened)
    from ..model import PARAMETER_NAMES  # noqa: PLC0415

    names = {getattr(c, "name", str(c)) for c in read_exr_header(path)[2].get("channels", [])}
    return set(PARAMETER_NAMES) <= names


def _meta(kind: str, path: Path, **more) -> dict:
    return {"skinlayers": {"kind": kind, "path": str(path.resolve()), **more}}


def maps_layers(path: str | Path) -> list[LayerData]:
    """A fit's ``maps.exr`` as layers: maps, σ, residual stack, residual RMS and flags."""
    from ..formats.exr import json_attribute  # noqa: PLC0415
    from ..formats.maps import read_map_file  # noqa: PLC0415

    path = Path(path)
    f = read_map_file(path)
    mm = float(f.mm_per_pixel)
    header = f.header
    flag_bits = json_attribute(header, "flag_bits", {})
    wavelengths = [float(w) for w in json_attribute(header, "wavelengths_nm", [])]
    scale2 = {"scale": (mm, mm), "units": ("mm", "mm"), "axis_labels": ("y", "x")}
    layers: list[LayerData] = []
    for n, (label, unit, cmap) in MAP_LOOKS.items():
        layers.append((f.params[n].numpy(), {"name": label, "colormap": cmap, **scale2,
                                             "metadata": _meta("map", path, parameter=n, unit=unit)}, "image"))
    for n, (label, unit, _) in MAP_LOOKS.items():
        sigma = f.extra.get(f"sigma_{n}")
        if sigma is not None:
            layers.append((sigma.numpy(), {"name": f"σ {label}", "colormap": "gray", "visible": False, **scale2,
                                           "metadata": _meta("sigma", path, parameter=n, unit=unit)}, "image"))
    residual = [f.extra[f"res_{w:g}"].numpy() for w in wavelengths if f"res_{w:g}" in f.extra]
    if residual and len(residual) == len(wavelengths):
        stack = np.stack(residual)
        lim = float(np.nanpercentile(np.abs(stack), 99)) or 1.0
        layers.append((stack, {"name": "fit − measured", "colormap": "bwr", "contrast_limits": (-lim, lim), "visible": False,
                               **_wavelength_axis(wavelengths, mm),
                               "metadata": _meta("residual", path, unit="reflectance", wavelengths_nm=wavelengths)}, "image"))
    if "residual_rms" in f.extra:
        layers.append((f.extra["residual_rms"].numpy(), {"name": "residual RMS", "colormap": "inferno", "visible": False,
                                                         **scale2, "metadata": _meta("residual_rms", path, unit="reflectance")},
                       "image"))
    if "flags" in f.extra:
        layers.append(_flags_layer(f.extra["flags"].numpy().astype(np.int64), flag_bits, path, scale2))
    return layers


def _flags_layer(flags: np.ndarray, flag_bits: dict[str, int], path: Path, scale2: dict) -> LayerData:
    """Each pixel's first flag (lowest bit) as a label, 0 where none; the labels' names in ``features``."""
    from ..reconstruct.diagnosis.checks import first_flag  # noqa: PLC0415

    first = first_flag(flags, flag_bits).astype(np.int32)
    names = ["none", *(name for name, _ in sorted(flag_bits.items(), key=lambda kv: kv[1]))]
    features = {"index": list(range(len(names))), "flag": names}
    return (first, {"name": "flags (first set)", "features": features, "opacity": 0.5, **scale2,
                    "metadata": _meta("flags", path, flag_bits=flag_bits, flags=flags)}, "labels")


def _wavelength_axis(wavelengths_nm: list[float], mm: float) -> dict:
    """A stack's scale, translate, units and labels: the first axis in nm where the bands are evenly
    spaced (the slider then reads the wavelength), else the band's index."""
    steps = np.diff(wavelengths_nm)
    even = len(wavelengths_nm) > 1 and bool(np.all(np.abs(steps - steps[0]) < EVEN_SPACING_NM)) and steps[0] > 0
    if even:
        return {"scale": (float(steps[0]), mm, mm), "translate": (float(wavelengths_nm[0]), 0.0, 0.0),
                "units": ("nm", "mm", "mm"), "axis_labels": ("wavelength", "y", "x")}
    return {"scale": (1.0, mm, mm), "units": ("pixel", "mm", "mm"), "axis_labels": ("band", "y", "x")}


def cube_layers(path: str | Path) -> list[LayerData]:
    """A reflectance cube as a stack on its wavelength axis, and its mask."""
    from ..formats.foreign.cubes import read_cube_file  # noqa: PLC0415

    path = Path(path)
    cube = read_cube_file(path)
    mm = float(cube.header.mm_per_pixel)
    wavelengths = [float(w) for w in cube.header.wavelengths_nm]
    mask = cube.mask.numpy()
    return [
        (cube.reflectance.numpy(), {"name": "reflectance", "colormap": "gray", **_wavelength_axis(wavelengths, mm),
                                    "metadata": _meta("cube", path, unit="reflectance factor", wavelengths_nm=wavelengths)}, "image"),
        ((~mask).astype(np.int32), {"name": "masked", "opacity": 0.4, "scale": (mm, mm), "units": ("mm", "mm"),
                                    "features": {"index": [0, 1], "pixel": ["valid", "masked"]},
                                    "metadata": _meta("mask", path)}, "labels"),
    ]


def session_layers(folder: str | Path) -> list[LayerData]:
    """A capture session's skin and reference frames, each a stack of one superpixel image (DN above
    black, the 2×2 sum) per band, in camera superpixels."""
    from ..calibration.raw import read_raw  # noqa: PLC0415
    from ..formats.manifest import read_manifest  # noqa: PLC0415

    folder = Path(folder)
    manifest = read_manifest(folder)
    layers = []
    for role in ("skin", "reference"):
        frames = sorted((f for f in manifest.frames if f.role == role and f.band_nm is not None), key=lambda f: f.band_nm)
        if not frames:
            continue
        stack = np.stack([read_raw(folder / f.file, label=f"{role} frame, {f.band_nm:g} nm").superpixel() for f in frames])
        wavelengths = [float(f.band_nm) for f in frames]
        axis = _wavelength_axis(wavelengths, 1.0)
        axis["units"] = (axis["units"][0], "pixel", "pixel")
        layers.append((stack, {"name": f"{role} frames", "colormap": "gray", **axis,
                               "metadata": _meta("frames", folder, role=role, unit="DN above black (2×2 sum)",
                                                 wavelengths_nm=wavelengths, files=[f.file for f in frames])}, "image"))
    return layers
