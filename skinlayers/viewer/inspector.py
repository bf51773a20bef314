"""A fit at one pixel: the measured spectrum with its noise, the fitted one, the maps with their σ and
the flags set there. What the napari dock widget (``skinlayers.viewer.widget``) draws under the cursor;
no napari and no Qt here.

The fitted spectrum is the fit's render: ``maps.exr`` keeps the residual per band (``res_<nm>``: the
render less the cube), so the cube plus the residual is the render the fit ended on (to float32
rounding). The cube's spectrum is the one the fit read (``fit.json``'s ``input``, or a cube given), its ±2σ each band's noise
as the fit estimates it (``band_noise``: the cube's own pixel-to-pixel scatter).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["FitAtPixels", "PixelReport"]


@dataclass(frozen=True)
class PixelReport:
    """One pixel (row, column) of a fit: spectra ``(L,)`` (reflectance factor) at ``wavelength_nm``,
    ``parameters`` name → (value, σ), the names of the flags set."""

    row: int
    col: int
    wavelength_nm: np.ndarray
    measured: np.ndarray | None
    noise_sigma: np.ndarray | None
    fitted: np.ndarray | None
    parameters: dict[str, tuple[float, float]] = field(default_factory=dict)
    flags: list[str] = field(default_factory=list)

    def lines(self) -> list[str]:
        """The parameters with their σ and the flags, one line each, as the widget prints them."""
        out = [f"pixel (row {self.row}, column {self.col})"]
        out += [f"{n} = {v:.4g} ± {s:.2g}" for n, (v, s) in self.parameters.items()]
        out.append("flags: " + (", ".join(self.flags) if self.flags else "none"))
        return out


class FitAtPixels:
    """A fit's ``maps.exr`` (and the cube it fitted, where found) read once, asked pixel by pixel.

    ``cube``: the cube's path; None: ``fit.json``'s ``input`` beside the maps, taken as written, then
    relative to the fit's folder and its parent. Without a cube only the maps, σ and flags are known.
    """

    def __init__(self, maps_path: str | Path, cube: str | Path | None = None) -> None:
        from ..formats.exr import json_attribute  # noqa: PLC0415
        from ..formats.maps import read_map_file  # noqa: PLC0415
        from ..model import PARAMETER_NAMES  # noqa: PLC0415

        self.maps_path = Path(maps_path)
        f = read_map_file(self.maps_path)
        self.mm_per_pixel = float(f.mm_per_pixel)
        self.flag_bits: dict[str, int] = dict(json_attribute(f.header, "flag_bits", {}))
        self.wavelength_nm = np.asarray(json_attribute(f.header, "wavelengths_nm", []), dtype=np.float64)
        self.params = {n: f.params[n].numpy() for n in PARAMETER_NAMES}
        self.sigma = {n: f.extra[f"sigma_{n}"].numpy() for n in PARAMETER_NAMES if f"sigma_{n}" in f.extra}
        self.flags = f.extra["flags"].numpy().astype(np.int64) if "flags" in f.extra else None
        names = [f"res_{w:g}" for w in self.wavelength_nm]
        self.residual = np.stack([f.extra[n].numpy() for n in names]) if all(n in f.extra for n in names) and names else None
        self.cube_path = Path(cube) if cube is not None else self._cube_from_fit()
        self.measured = self.noise_sigma = None
        self.cube_problem = ""
        if self.cube_path is not None:
            try:
                self._read_cube(self.cube_path)
            except (ValueError, OSError) as exc:  # a cube that is not this fit's, or too small for its noise
                self.measured = self.noise_sigma = None
                self.cube_problem = str(exc)

    @property
    def shape(self) -> tuple[int, int]:
        return next(iter(self.params.values())).shape

    def _cube_from_fit(self) -> Path | None:
        summary = self.maps_path.parent / "fit.json"
        if not summary.is_file():
            return None
        source = json.loads(summary.read_text()).get("input") or ""
        for candidate in (Path(source), self.maps_path.parent / source, self.maps_path.parent.parent / source):
            if source and candidate.is_file():
                return candidate
        return None

    def _read_cube(self, path: Path) -> None:
        from ..formats.cube import CubeError  # noqa: PLC0415
        from ..formats.foreign.cubes import read_cube_file  # noqa: PLC0415
        from ..reconstruct.choice.grid_choice import band_noise  # noqa: PLC0415

        try:
            cube = read_cube_file(path)
        except CubeError:  # a foreign cube that does not say its pixel side: the maps' (the fit was given it)
            cube = read_cube_file(path, self.mm_per_pixel)
        if tuple(cube.reflectance.shape[1:]) != self.shape or len(cube.header.wavelengths_nm) != len(self.wavelength_nm):
            raise ValueError(f"{path}: the cube's {tuple(cube.reflectance.shape)} does not match the maps' "
                             f"{len(self.wavelength_nm)} bands × {self.shape}")
        self.measured = cube.reflectance.numpy()
        self.noise_sigma = band_noise(cube.reflectance, cube.mask).numpy()

    def pixel_of(self, y_mm: float, x_mm: float) -> tuple[int, int] | None:
        """The pixel whose centre is nearest (``y_mm``, ``x_mm``) on the maps' grid (pixel (0, 0)'s centre
        at 0 mm, as napari draws a layer scaled by the pixel's side); None outside the maps."""
        row, col = round(y_mm / self.mm_per_pixel), round(x_mm / self.mm_per_pixel)
        h, w = self.shape
        return (row, col) if 0 <= row < h and 0 <= col < w else None

    def at(self, row: int, col: int) -> PixelReport:
        """The fit at pixel (``row``, ``col``)."""
        measured = None if self.measured is None else self.measured[:, row, col].astype(np.float64)
        fitted = None if measured is None or self.residual is None else measured + self.residual[:, row, col]
        params = {n: (float(v[row, col]), float(self.sigma[n][row, col]) if n in self.sigma else float("nan"))
                  for n, v in self.params.items()}
        flags = [] if self.flags is None else [n for n, b in sorted(self.flag_bits.items(), key=lambda kv: kv[1])
                                               if (int(self.flags[row, col]) >> b) & 1]
        return PixelReport(row, col, self.wavelength_nm, measured, self.noise_sigma, fitted, params, flags)
