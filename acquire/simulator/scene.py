"""Synthetic skin scenes for the simulated bench: parameter maps from a YAML description and a seed.

A scene is a base skin (a DWRR08 Table 2 row or explicit values) with smooth variation of every
chromophore, freckles (melanin spots), a scar, veins and hairs. Veins and hairs live in the thin
interface layer as extra absorbance (DWRR08 §4.2, Fig. 15): a vein absorbs as deoxygenated blood along
the chord through a cylindrical vessel, a hair absorbs the same at every wavelength.

Every feature is a function of position in mm (skin-plane coordinates, origin at the window centre,
x right, y down), drawn once from the seed; a grid only samples those functions at its pixel centres,
so a finer grid renders the same scene. Each kind of feature draws from its own stream of the seed,
so adding freckles does not move the veins.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Optional

import numpy as np
import torch
from pydantic import AfterValidator, Field, model_validator

from ...model.patch.maps import SkinMaps
from ...model.optics.params import PARAMETER_BOUNDS, PARAMETER_NAMES, TABLE2
from ...formats.errors import SettingsError
from ...formats.settings import Strict, load_settings, validate_settings
from ...model.settings import SkinOptics
from ...model.optics.spectra import chromophore_spectra

__all__ = ["SceneConfig", "SceneError", "SkinScene", "load_scene", "scene_from_dict"]


class SceneError(SettingsError):
    """A scene file or value that cannot be used; the message names the file, the key and the problem."""


def _ordered(value: tuple[float, float]) -> tuple[float, float]:
    if value[0] > value[1]:
        raise ValueError(f"a range [lo, hi] needs lo <= hi, got {list(value)}")
    return value


#: A range [lo, hi] drawn from uniformly.
Range = Annotated[tuple[float, float], AfterValidator(_ordered)]


class BaseSkin(Strict):
    """The skin the features vary around."""

    preset: Optional[str] = Field("III interior", description="A DWRR08 Table 2 row; values given below override it.")
    C_m: Optional[float] = Field(None, ge=0, le=0.5)
    beta_m: Optional[float] = Field(None, ge=0, le=1)
    C_he: Optional[float] = Field(None, ge=0, le=0.05)
    C_bc: Optional[float] = Field(None, ge=0, le=0.05)
    C_hd: Optional[float] = Field(None, ge=0, le=0.1)

    @model_validator(mode="after")
    def _complete(self) -> "BaseSkin":
        if self.preset is not None and self.preset not in TABLE2:
            raise ValueError(f"preset {self.preset!r} is not a Table 2 row; choose one of: {', '.join(TABLE2)}")
        if self.preset is None and any(getattr(self, n) is None for n in PARAMETER_NAMES):
            raise ValueError(f"without a preset, all of {', '.join(PARAMETER_NAMES)} must be given")
        return self

    def values(self) -> dict[str, float]:
        out = dict(TABLE2[self.preset]) if self.preset is not None else {}
        out.update({n: getattr(self, n) for n in PARAMETER_NAMES if getattr(self, n) is not None})
        return out


class VariationConfig(Strict):
    """Smooth variation: each chromophore times exp(a·f), f a unit-variance random field."""

    length_scale_mm: float = Field(1.5, gt=0, description="Typical wavelength of the variation (mm).")
    modes: int = Field(32, ge=1, le=512, description="Plane waves per field.")
    C_m: float = Field(0.25, ge=0, le=2)
    beta_m: float = Field(0.3, ge=0, le=4, description="Amplitude on the logit of β_m.")
    C_he: float = Field(0.3, ge=0, le=2)
    C_bc: float = Field(0.3, ge=0, le=2)
    C_hd: float = Field(0.25, ge=0, le=2)
    blood_correlation: float = Field(0.87, ge=-1, le=1, description="Correlation of the C_he and C_hd fields (DWRR08 §7: 0.87).")


class FrecklesConfig(Strict):
    count: int = Field(10, ge=0, le=10000)
    radius_mm: Range = (0.12, 0.35)
    melanin_factor: Range = (2.0, 4.0)
    edge_mm: float = Field(0.03, gt=0)


class ScarConfig(Strict):
    count: int = Field(1, ge=0, le=100)
    length_mm: Range = (3.0, 5.0)
    width_mm: Range = (0.4, 0.8)
    curvature_per_mm: Range = (-0.15, 0.15)
    edge_mm: float = Field(0.05, gt=0)
    melanin_factor: float = Field(0.4, ge=0)
    epidermal_blood_factor: float = Field(0.5, ge=0)
    dermal_blood_factor: float = Field(1.5, ge=0)


class VeinsConfig(Strict):
    count: int = Field(1, ge=0, le=100)
    radius_mm: Range = (0.25, 0.4)
    meander_mm: Range = (0.2, 0.6)
    meander_period_mm: Range = (5.0, 9.0)
    blood_path_mm: float = Field(0.01, ge=0, description="Deoxygenated-blood path at the vessel's centre line (mm).")


class HairsConfig(Strict):
    count: int = Field(5, ge=0, le=10000)
    length_mm: Range = (2.0, 5.0)
    width_mm: Range = (0.04, 0.08)
    curvature_per_mm: Range = (-0.3, 0.3)
    absorbance: float = Field(3.0, ge=0, description="Interface absorbance on a hair's centre line (all wavelengths).")


class SceneConfig(Strict):
    """A synthetic skin patch (``configs/scene.yaml`` is the embedded default)."""

    extent_mm: float = Field(8.5, gt=0, le=100, description="Side of the square, centred on the window, where features lie.")
    base: BaseSkin = BaseSkin()
    variation: VariationConfig = VariationConfig()
    freckles: FrecklesConfig = FrecklesConfig()
    scar: ScarConfig = ScarConfig()
    veins: VeinsConfig = VeinsConfig()
    hairs: HairsConfig = HairsConfig()


def default_scene_path() -> Path:
    from ...configs import config_path  # noqa: PLC0415

    return config_path("scene.yaml")


def load_scene(path: str | Path | None = None) -> SceneConfig:
    """The scene of a YAML file (the embedded ``configs/scene.yaml`` when ``path`` is None)."""
    return load_settings(SceneConfig, path, SceneError, "scene", default_path=default_scene_path())


def scene_from_dict(data: dict, source: str = "scene") -> SceneConfig:
    return validate_settings(SceneConfig, data, SceneError, source)


# -- the drawn scene ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class _Field:
    """A unit-variance random field: sqrt(2/M) Σ cos(k·x + φ)."""

    k_per_mm: np.ndarray  # (M, 2)
    phase: np.ndarray  # (M,)

    def __call__(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """At points ``(...)``."""
        k = torch.as_tensor(self.k_per_mm, dtype=x.dtype, device=x.device)
        ph = torch.as_tensor(self.phase, dtype=x.dtype, device=x.device)
        out = torch.zeros_like(x)
        for j in range(k.shape[0]):
            out += torch.cos(k[j, 0] * x + k[j, 1] * y + ph[j])
        return out * math.sqrt(2.0 / k.shape[0])

    def grid(self, x_axis: torch.Tensor, y_axis: torch.Tensor) -> torch.Tensor:
        """On the grid ``y_axis (H,) × x_axis (W,)`` → ``(H, W)``: cos(a + b) = Re(e^{ia} e^{ib}) makes the
        sum over modes one complex matrix product, far cheaper than a cosine per pixel and mode."""
        k = torch.as_tensor(self.k_per_mm, dtype=x_axis.dtype, device=x_axis.device)
        ph = torch.as_tensor(self.phase, dtype=x_axis.dtype, device=x_axis.device)
        rows = torch.polar(torch.ones_like(k[:, 1]), y_axis[:, None] * k[:, 1] + ph)  # (H, M)
        cols = torch.polar(torch.ones_like(k[:, 0]), x_axis[:, None] * k[:, 0])  # (W, M)
        return (rows @ cols.T).real * math.sqrt(2.0 / k.shape[0])


@dataclass(frozen=True)
class _Arc:
    """A circular arc (a segment when straight) from ``start`` along ``heading`` for ``length`` mm."""

    start: tuple[float, float]
    heading: float
    length: float
    curvature: float

    def distance(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        sx, sy = self.start
        ux, uy = math.cos(self.heading), math.sin(self.heading)
        if abs(self.curvature) * self.length < 1e-6:
            t = ((x - sx) * ux + (y - sy) * uy).clamp(0.0, self.length)
            return torch.hypot(x - sx - t * ux, y - sy - t * uy)
        radius = 1.0 / abs(self.curvature)
        side = math.copysign(1.0, self.curvature)
        cx, cy = sx - side * uy * radius, sy + side * ux * radius  # centre to the left (κ > 0) or right
        a0 = math.atan2(sy - cy, sx - cx)
        sweep = self.length / radius
        rel = torch.remainder(side * (torch.atan2(y - cy, x - cx) - a0), 2 * math.pi)
        on_arc = torch.hypot(x - cx, y - cy).sub(radius).abs()
        ex, ey = cx + radius * math.cos(a0 + side * sweep), cy + radius * math.sin(a0 + side * sweep)
        ends = torch.minimum(torch.hypot(x - sx, y - sy), torch.hypot(x - ex, y - ey))
        return torch.where(rel <= sweep, on_arc, ends)


def _chord(distance: torch.Tensor, radius: float) -> torch.Tensor:
    """Path through a cylinder of ``radius`` at ``distance`` from its axis, over its diameter (0–1)."""
    return (1.0 - (distance / radius) ** 2).clamp(min=0.0).sqrt()


def _inside(distance: torch.Tensor, radius: float, edge: float) -> torch.Tensor:
    """1 inside ``radius``, 0 outside, a logistic border of width ``edge``."""
    return torch.sigmoid((radius - distance) / edge)


class SkinScene:
    """A scene drawn from its config and a seed; ``maps`` samples it on any grid."""

    def __init__(self, config: SceneConfig | None = None, seed: int = 0) -> None:
        self.config = config or SceneConfig()
        self.seed = int(seed)
        streams = [np.random.default_rng(s) for s in np.random.SeedSequence(self.seed).spawn(5)]
        c = self.config
        half = c.extent_mm / 2.0
        self._base = c.base.values()
        self._fields = self._draw_fields(streams[0])
        g = streams[1]
        f = c.freckles
        self._freckles = [
            (g.uniform(-half, half, 2), g.uniform(*f.radius_mm), g.uniform(*f.melanin_factor)) for _ in range(f.count)
        ]
        self._scars = [self._draw_arc(streams[2], half / 2, c.scar) for _ in range(c.scar.count)]
        g = streams[3]
        v = c.veins
        self._veins = [
            dict(centre=g.uniform(-half / 2, half / 2, 2), heading=g.uniform(0, math.pi), radius=g.uniform(*v.radius_mm),
                 amplitude=g.uniform(*v.meander_mm), period=g.uniform(*v.meander_period_mm), phase=g.uniform(0, 2 * math.pi))
            for _ in range(v.count)
        ]
        self._hairs = [self._draw_arc(streams[4], half, c.hairs) for _ in range(c.hairs.count)]

    def _draw_fields(self, g: np.random.Generator) -> dict[str, _Field]:
        v = self.config.variation

        def field() -> _Field:
            angle = g.uniform(0, 2 * math.pi, v.modes)
            wavelength = v.length_scale_mm * np.exp(g.uniform(math.log(0.5), math.log(2.0), v.modes))
            k = (2 * math.pi / wavelength)[:, None] * np.stack([np.cos(angle), np.sin(angle)], axis=1)
            return _Field(k, g.uniform(0, 2 * math.pi, v.modes))

        return {"C_m": field(), "beta_m": field(), "C_he": field(), "C_bc": field(), "blood_b": field()}

    @staticmethod
    def _draw_arc(g: np.random.Generator, half: float, cfg: ScarConfig | HairsConfig) -> tuple[_Arc, float]:
        """An arc starting within ±``half`` mm and its width (mm)."""
        start = g.uniform(-half, half, 2)
        arc = _Arc((float(start[0]), float(start[1])), float(g.uniform(0, 2 * math.pi)), float(g.uniform(*cfg.length_mm)),
                   float(g.uniform(*cfg.curvature_per_mm)))
        return arc, float(g.uniform(*cfg.width_mm))

    # -- evaluation at points ---------------------------------------------------------------------
    def parameters_at(self, x_mm: torch.Tensor, y_mm: torch.Tensor) -> dict[str, torch.Tensor]:
        """The five chromophore maps at points ``(...)`` (float64 recommended), clipped to Table 1's ranges."""
        return self._parameters(x_mm, y_mm, {k: fld(x_mm, y_mm) for k, fld in self._fields.items()})

    def _parameters(self, x_mm: torch.Tensor, y_mm: torch.Tensor, f: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        c = self.config
        v = c.variation
        rho = v.blood_correlation
        blood_d = rho * f["C_he"] + math.sqrt(max(1.0 - rho * rho, 0.0)) * f["blood_b"]
        base = self._base
        c_m = base["C_m"] * torch.exp(v.C_m * f["C_m"])
        beta0 = min(max(base["beta_m"], 1e-4), 1 - 1e-4)
        beta = torch.sigmoid(math.log(beta0 / (1 - beta0)) + v.beta_m * f["beta_m"])
        c_he = base["C_he"] * torch.exp(v.C_he * f["C_he"])
        c_bc = base["C_bc"] * torch.exp(v.C_bc * f["C_bc"])
        c_hd = base["C_hd"] * torch.exp(v.C_hd * blood_d)
        spots = torch.ones_like(x_mm)
        for centre, radius, factor in self._freckles:
            d = torch.hypot(x_mm - centre[0], y_mm - centre[1])
            spots = spots + (factor - 1.0) * _inside(d, radius, c.freckles.edge_mm)
        c_m = c_m * spots
        s = c.scar
        for arc, width in self._scars:
            mark = _inside(arc.distance(x_mm, y_mm), width / 2.0, s.edge_mm)
            c_m = c_m * (1.0 + (s.melanin_factor - 1.0) * mark)
            c_he = c_he * (1.0 + (s.epidermal_blood_factor - 1.0) * mark)
            c_hd = c_hd * (1.0 + (s.dermal_blood_factor - 1.0) * mark)
        out = {"C_m": c_m, "beta_m": beta, "C_he": c_he, "C_bc": c_bc, "C_hd": c_hd}
        return {n: out[n].clamp(*PARAMETER_BOUNDS[n]) for n in PARAMETER_NAMES}

    def vessel_path_at(self, x_mm: torch.Tensor, y_mm: torch.Tensor) -> torch.Tensor:
        """Deoxygenated-blood path seen by the interface layer (mm) at points ``(...)``."""
        out = torch.zeros_like(x_mm)
        for vein in self._veins:
            ux, uy = math.cos(vein["heading"]), math.sin(vein["heading"])
            s = (x_mm - vein["centre"][0]) * ux + (y_mm - vein["centre"][1]) * uy
            n = -(x_mm - vein["centre"][0]) * uy + (y_mm - vein["centre"][1]) * ux
            w = 2 * math.pi / vein["period"]
            offset = vein["amplitude"] * torch.sin(w * s + vein["phase"])
            slope = vein["amplitude"] * w * torch.cos(w * s + vein["phase"])
            d = (n - offset).abs() / torch.sqrt(1.0 + slope**2)  # distance to a gently meandering centre line
            out = out + self.config.veins.blood_path_mm * _chord(d, vein["radius"])
        return out

    def hair_absorbance_at(self, x_mm: torch.Tensor, y_mm: torch.Tensor) -> torch.Tensor:
        """Interface absorbance of the hairs at points ``(...)`` (the same at every wavelength)."""
        out = torch.zeros_like(x_mm)
        for arc, width in self._hairs:
            out = out + self.config.hairs.absorbance * _chord(arc.distance(x_mm, y_mm), width / 2.0)
        return out

    # -- on a grid ------------------------------------------------------------------------------
    def maps(
        self, mm_per_pixel: float, size_px: int, wavelength_nm: torch.Tensor, *, optics: SkinOptics | None = None,
        dtype: torch.dtype = torch.float32, device: torch.device | str | None = None,
    ) -> SkinMaps:
        """``SkinMaps`` (B = 1) on a ``size_px`` square grid centred on the window, pixel centres at
        ``(i - (size_px - 1)/2) · mm_per_pixel``, with the interface absorbance of veins and hairs at
        ``wavelength_nm`` ``(L,)`` (deoxygenated blood as ``optics`` sets it)."""
        if not (mm_per_pixel > 0 and size_px >= 1):
            raise ValueError(f"a scene grid needs mm_per_pixel > 0 and size_px >= 1, got {mm_per_pixel}, {size_px}")
        wl = torch.as_tensor(wavelength_nm, dtype=torch.float64).reshape(-1)
        axis = (torch.arange(size_px, dtype=torch.float64, device=device) - (size_px - 1) / 2.0) * mm_per_pixel
        y, x = torch.meshgrid(axis, axis, indexing="ij")
        fields = {k: fld.grid(axis, axis) for k, fld in self._fields.items()}
        params = {n: v.to(dtype)[None] for n, v in self._parameters(x, y, fields).items()}
        blood = chromophore_spectra(wl, optics or SkinOptics()).deoxy_blood.to(device)
        vessels, hairs = self.vessel_path_at(x, y), self.hair_absorbance_at(x, y)
        absorbance = blood[:, None, None] * vessels[None] + hairs[None]
        return SkinMaps(**params, mm_per_pixel=float(mm_per_pixel), absorbance=absorbance.to(dtype)[None],
                        absorbance_wavelength_nm=wl).validate("scene")
