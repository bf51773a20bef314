"""The simulated bench: a skin scene, the black tape with its window, a Spectralon target and a gray
card, photographed through the filter wheel by a 30° camera with a xenon flash (DWRR08 §6.1–6.2).

``SimulatedBench`` holds the scene, the rig, the simulation settings and the seed. It renders each
band's skin once with the model at higher fidelity than any fit (finer grid, several wavelengths
across the band, every Gaussian blurred, a tighter series) and composes camera frames from it:

    skin-plane image (tape + skin in the window, or Spectralon; the gray card fixed to the rig)
    → the subject's motion → perspective of the 30° camera, supersampled → Gaussian lens blur
    → per channel: flash × filter × sensitivity, vignetting, flash jitter → electrons
    → shot and read noise, quantisation, black level, saturation → RGGB mosaic.

Every target's signal is multiplied by its crossed-polarizer factor (rig ``polarization``); the tape
and the gray card are Lambertian at the angles used. Ambient light is nil and the flash far shorter
than the shutter, so the shutter time does not change the picture; the aperture does, as 1/N². Wheel
positions without a band filter are treated as blanked (as a cap would), giving a black frame.
"""

from __future__ import annotations

import hashlib
import json
import math
import time
from collections import Counter
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable, Literal, Optional

import numpy as np
import torch

from ...formats.exr import write_spectral
from ...formats.files import atomic_write
from ...formats.resources import require_memory
from ...model.render.illumination import Light
from ...model.patch.maps import SkinMaps
from ...model.patch.maps_io import write_maps
from ...model.render.renderer import SkinRenderer, render_bytes
from ...model.transport import BYTES_PER_PHOTON, TransportRenderer
from ...model.settings import ModelSettings
from ._optics import (BandSpectrum, CameraGeometry, band_spectrum, bilinear, gaussian_blur, sample_points, sensor_geometry,
                      to_subject, vignetting)
from ._sensor import e_per_dn, expose, mosaic
from ..hardware.devices import ExposureSettings
from ..hardware.rig import BandConfig, RigConfig, load_rig, rig_from_dict
from .scene import SceneConfig, SkinScene, load_scene
from .simulation_settings import SimulationError, SimulationSettings, load_simulation_settings

__all__ = ["SimulatedBench", "SimulatedFrame", "Target", "flash_power"]

Target = Literal["skin", "spectralon"]
_ROWS_PER_CHUNK = 128  # rows of the sensor warped at once (bounds the memory of the supersampled grid)


@dataclass(frozen=True)
class SimulatedFrame:
    """What the bench did for one frame: the truth of its flash and motion."""

    index: int
    position: int
    band_nm: Optional[float]
    target: str
    iso: int
    shutter_s: float
    aperture_f: float
    flash: float
    shift_px: tuple[float, float]
    rotation_deg: float


@dataclass(frozen=True)
class BandRender:
    """A band's skin on the truth grid: per channel the band-weighted reflectance factor ``(3, N, N)``
    and the truth, weighted by the four Bayer positions together ``(N, N)``; rendered by transport, the
    truth's Monte Carlo standard error ``(N, N)``."""

    spectrum: BandSpectrum
    channels: torch.Tensor
    truth: torch.Tensor
    seconds: float
    truth_std_error: torch.Tensor | None = None


class SimulatedBench:
    """The bench of a simulated session; ``SimulatedCamera`` photographs it, ``set_target`` places targets."""

    def __init__(
        self, rig: RigConfig | None = None, scene: SceneConfig | SkinScene | None = None,
        settings: SimulationSettings | None = None, seed: int = 0, *, model_settings: ModelSettings | None = None,
        device: torch.device | str | None = None,
    ) -> None:
        self.rig = rig or load_rig()
        self.settings = settings or load_simulation_settings()
        self.seed = int(seed)
        self.scene = scene if isinstance(scene, SkinScene) else SkinScene(scene or load_scene(), self.seed)
        self.device = torch.device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
        s, g = self.settings, self.rig.geometry
        self.geometry: CameraGeometry = sensor_geometry(
            g.window_mm, s.camera.window_span_px or 2 * g.rectify_px, s.camera.distance_mm, self.rig.camera.angle_deg,
            s.camera.field_of_view_mm,
        )
        self._window_region = self._window_in_view()
        self.gray_card_roi_px = self._card_roi()
        self._check_card_clear_of_window()
        self.truth_mm_per_pixel = g.window_mm / (g.cube_px * s.truth.oversample)
        self._window_px = g.cube_px * s.truth.oversample
        self._margin_px = math.ceil(s.truth.margin_mm / self.truth_mm_per_pixel)
        self.truth_size_px = self._window_px + 2 * self._margin_px
        base = model_settings or ModelSettings()
        t = s.truth
        self.renderer = SkinRenderer(base.model_copy(update={"render": base.render.model_copy(update={
            "blur": t.blur, "identity_below_px": t.identity_below_px, "series_tolerance": t.series_tolerance})}))
        sens = s.sensor.sensitivity
        self.spectra = {b.wavelength_nm: band_spectrum(b.wavelength_nm, b.fwhm_nm, s.filters.wavelength_samples,
                                                       s.flash.temperature_k, sens) for b in self.rig.bands}
        reference = band_spectrum(550.0, 10.0, s.filters.wavelength_samples, s.flash.temperature_k, sens)
        self._reference_signal = reference.channel_signal[1]  # green, 10-nm filter at 550 nm: white_electrons' unit
        self._require_memory()
        self._by_position = {b.filter_position: b for b in self.rig.bands}
        self.white_electrons = s.sensor.white_electrons or self._flash_power()
        self._vignetting = vignetting(self.geometry, s.camera.vignetting, torch.float32, self.device)
        self._renders: dict[float, BandRender] = {}
        self._maps: SkinMaps | None = None
        self._counts: Counter = Counter()
        self.target: Target = "skin"
        self.frames: list[SimulatedFrame] = []

    def _require_memory(self) -> None:
        """Refuse, before any session starts, a truth grid whose band renders would not fit in memory
        (each band is rendered once at its filter's nodes and kept)."""
        nodes = max(len(sp.nodes_nm) for sp in self.spectra.values())
        mm, n = self.truth_mm_per_pixel, self.truth_size_px
        border = Light("window", size_mm=self.rig.geometry.window_mm, border_mm=self.settings.truth.border_mm).border_px(mm)
        if self.settings.truth.physics == "transport":  # photons walk in batches: their memory, not the grid's
            render = BYTES_PER_PHOTON * self.renderer.settings.transport.batch_photons
        else:
            render = render_bytes(1, nodes, n, n, border, weight_cache_mb=self.renderer.settings.render.weight_cache_mb)
        kept = len(self.spectra) * 4 * n * n * 4  # each band's three channels and truth, float32
        require_memory(render + kept, f"simulating a {n}×{n} px truth grid at {len(self.spectra)} bands",
                       "Lower the rig's geometry.cube_px or the simulation's truth.oversample.", self.device)

    def _flash_power(self) -> float:
        return flash_power(self.settings, self.rig, self.spectra, self._reference_signal)

    def electrons_per_reflectance(self, band_nm: float, aperture_f: float) -> np.ndarray:
        """Mean electrons ``(3,)`` (red, green, blue) at the image centre per unit reflectance factor,
        the flash at its nominal energy."""
        return self.white_electrons * (10.0 / aperture_f) ** 2 * self.spectra[band_nm].channel_signal / self._reference_signal

    # -- geometry -----------------------------------------------------------------------------
    def _card_roi(self) -> list[int]:
        """The gray card's region in raw px [x0, y0, x1, y1], half-open: whole pixels inside the card,
        clear of its blurred edge, on whole 2×2 Bayer cells."""
        x0, y0, x1, y1 = self.settings.scene.gray_card_mm
        geo = self.geometry
        left = max(geo.project(x0, y0)[0], geo.project(x0, y1)[0])
        right = min(geo.project(x1, y0)[0], geo.project(x1, y1)[0])
        top, bottom = geo.project(0.0, y0)[1], geo.project(0.0, y1)[1]
        inset = math.ceil(3 * self.settings.camera.psf_sigma_px) + 1
        c0 = 2 * math.ceil((math.ceil(left + 0.5) + inset) / 2)
        c1 = 2 * math.floor((math.floor(right - 0.5) + 1 - inset) / 2)
        r0 = 2 * math.ceil((math.ceil(top + 0.5) + inset) / 2)
        r1 = 2 * math.floor((math.floor(bottom - 0.5) + 1 - inset) / 2)
        roi = [max(c0, 0), max(r0, 0), min(c1, geo.width_px), min(r1, geo.height_px)]
        if roi[2] - roi[0] < 2 or roi[3] - roi[1] < 2:
            raise SimulationError(
                f"scene.gray_card_mm {list(self.settings.scene.gray_card_mm)} leaves no whole 2×2 cell of the card on the "
                f"{geo.width_px}×{geo.height_px} sensor (camera.field_of_view_mm, camera.window_span_px)")
        return roi

    def window_corners_px(self, shift_px: tuple[float, float] = (0.0, 0.0), rotation_deg: float = 0.0) -> np.ndarray:
        """Raw-pixel corners ``(4, 2)`` of the window (top-left, top-right, bottom-right, bottom-left) with
        the subject moved by ``shift_px`` (at the window centre) and ``rotation_deg``."""
        h = self.rig.geometry.window_mm / 2.0
        sx, sy = self._shift_mm(shift_px)
        phi = math.radians(rotation_deg)
        out = []
        for px, py in ((-h, -h), (h, -h), (h, h), (-h, h)):
            wx = math.cos(phi) * px - math.sin(phi) * py + sx
            wy = math.sin(phi) * px + math.cos(phi) * py + sy
            out.append(self.geometry.project(wx, wy))
        return np.array(out)

    def _shift_mm(self, shift_px: tuple[float, float]) -> tuple[float, float]:
        sx, sy = self.geometry.px_per_mm
        return shift_px[0] / sx, shift_px[1] / sy

    def _window_in_view(self) -> tuple[np.ndarray, np.ndarray]:
        """The raw-px box the window can reach as the subject moves (blur included); it must lie on the sensor."""
        m = self.settings.motion
        margin = m.max_shift_px + 4 * self.settings.camera.psf_sigma_px + 2
        corners = np.concatenate([self.window_corners_px((0.0, 0.0), a) for a in (-m.max_rotation_deg, m.max_rotation_deg)])
        lo, hi = corners.min(axis=0) - margin, corners.max(axis=0) + margin
        geo = self.geometry
        if lo[0] < 0 or lo[1] < 0 or hi[0] > geo.width_px - 1 or hi[1] > geo.height_px - 1:
            raise SimulationError(f"the window with its motion (motion.max_shift_px {m.max_shift_px}) does not fit the "
                                  f"{geo.width_px}×{geo.height_px} sensor: widen camera.field_of_view_mm")
        return lo, hi

    def _check_card_clear_of_window(self) -> None:
        lo, hi = self._window_region
        x0, y0, x1, y1 = self.gray_card_roi_px
        if not (x1 <= lo[0] or x0 >= hi[0] or y1 <= lo[1] or y0 >= hi[1]):
            raise SimulationError(f"scene.gray_card_mm overlaps the window's region (raw px {lo.round().tolist()}–"
                                  f"{hi.round().tolist()}) once the subject moves")

    # -- the rig as the session saves it ---------------------------------------------------------
    def rig_as_used(self) -> RigConfig:
        """The rig with the simulated camera and the gray card's region (``geometry.gray_card_roi_px``)."""
        data = self.rig.model_dump(mode="json")
        data["camera"]["driver"] = "simulated"
        data["geometry"]["gray_card_roi_px"] = list(self.gray_card_roi_px)
        return rig_from_dict(data, "simulated rig")

    def band_at(self, position: int) -> BandConfig | None:
        """The band whose filter sits at ``position``; None for the opaque slot and unused positions."""
        if not 1 <= position <= self.rig.wheel.position_count:
            raise ValueError(f"wheel position {position} outside 1–{self.rig.wheel.position_count}")
        return self._by_position.get(position)

    def set_target(self, target: Target) -> None:
        """Place the skin patch (with its tape) or the Spectralon target under the camera."""
        if target not in ("skin", "spectralon"):
            raise ValueError(f"target must be 'skin' or 'spectralon', got {target!r}")
        self.target = target

    # -- the true skin ----------------------------------------------------------------------------
    def scene_maps(self) -> SkinMaps:
        """The scene on the truth grid (window plus margin), absorbance at every band's nodes."""
        if self._maps is None:
            nodes = sorted({float(w) for sp in self.spectra.values() for w in sp.nodes_nm})
            self._maps = self.scene.maps(self.truth_mm_per_pixel, self.truth_size_px, torch.tensor(nodes, dtype=torch.float64),
                                         optics=self.renderer.settings.optics, device=self.device)
        return self._maps

    def render_band(self, band_nm: float) -> BandRender:
        """The band's skin, rendered once and kept."""
        if band_nm not in self._renders:
            spectrum = self.spectra[band_nm]
            start = time.perf_counter()
            light = Light("window", size_mm=self.rig.geometry.window_mm, border_mm=self.settings.truth.border_mm)
            nodes = torch.tensor(spectrum.nodes_nm)
            se = None
            with torch.no_grad():
                if self.settings.truth.physics == "transport":
                    result = TransportRenderer(self.renderer.settings).render(
                        self.scene_maps().to(dtype=torch.float64), light, nodes, photons=self.settings.truth.photons,
                        seed=_transport_seed(self.seed, band_nm), view_angle_deg=self.rig.camera.angle_deg,
                    )
                    image, se = result.image[0], result.image_std_error[0]
                else:
                    image = self._render_nodes(light, nodes).to(torch.float64)
            w = torch.as_tensor(spectrum.weights / spectrum.weights.sum(axis=1, keepdims=True), device=image.device)
            channels = torch.einsum("ck,khw->chw", w, image).to(torch.float32)
            tw = torch.as_tensor(spectrum.truth_weights(), device=image.device)
            truth = torch.einsum("k,khw->hw", tw, image)
            truth_se = None if se is None else torch.einsum("k,khw->hw", tw**2, se**2).sqrt().to(torch.float32)  # independent nodes
            self._renders[band_nm] = BandRender(spectrum, channels, truth.to(torch.float32), time.perf_counter() - start, truth_se)
        return self._renders[band_nm]

    def _render_nodes(self, light: Light, nodes_nm: torch.Tensor) -> torch.Tensor:
        """The band's wavelength nodes ``(K,)`` rendered one at a time, with the series terms of all of
        them (the same image as at once, ``(K, H, W)``): a third of the images per render stay in the
        processor's cache (docs/speed.md, "Cut 3")."""
        maps = self.scene_maps()
        terms = self.renderer.series_terms_for(maps, nodes_nm)
        return torch.cat([
            self.renderer.render(maps, light, nodes_nm[k:k + 1], under_gel=True, light_angle_deg=0.0,
                                 view_angle_deg=self.rig.camera.angle_deg, series_terms=terms).image[0]
            for k in range(nodes_nm.numel())
        ])

    def prepare(self, progress: Callable[[int, int], None] | None = None) -> None:
        """Render every band now (the first frame of a band would otherwise wait for it)."""
        for i, band in enumerate(self.rig.bands):
            self.render_band(band.wavelength_nm)
            if progress is not None:
                progress(i + 1, len(self.rig.bands))

    def band_renders(self) -> dict[str, torch.Tensor]:
        """Every band's skin as rendered (each band rendered now if it was not yet), stacked in the rig's
        band order for keeping: ``channels`` ``(L, 3, N, N)``, ``truth`` ``(L, N, N)`` and, rendered by
        transport, ``std_error`` ``(L, N, N)`` (float32, CPU)."""
        renders = [self.render_band(b.wavelength_nm) for b in self.rig.bands]
        out = {"channels": torch.stack([r.channels for r in renders]).cpu(), "truth": torch.stack([r.truth for r in renders]).cpu()}
        if renders[0].truth_std_error is not None:
            out["std_error"] = torch.stack([r.truth_std_error for r in renders]).cpu()
        return out

    def adopt_band(self, band_nm: float, render: BandRender) -> None:
        """Take one band's skin as ``render_band`` made it earlier (with this bench's rig, scene, seed and truth
        settings), e.g. kept by an interrupted run, instead of rendering it again."""
        self._renders[band_nm] = render

    def adopt_renders(self, kept: dict[str, torch.Tensor]) -> None:
        """Photograph skin rendered earlier (``band_renders`` of a bench with the same rig, scene, seed and
        truth settings; e.g. a shipped Monte Carlo) instead of rendering it again."""
        n, bands = self.truth_size_px, self.rig.bands
        if tuple(kept["truth"].shape) != (len(bands), n, n) or tuple(kept["channels"].shape) != (len(bands), 3, n, n):
            raise SimulationError(f"kept band renders of shape {tuple(kept['truth'].shape)} do not fit this bench's "
                                  f"{len(bands)} bands on a {n}×{n} px truth grid")
        se = kept.get("std_error")
        for i, b in enumerate(bands):
            self._renders[b.wavelength_nm] = BandRender(
                self.spectra[b.wavelength_nm], kept["channels"][i].to(self.device, torch.float32),
                kept["truth"][i].to(self.device, torch.float32), 0.0,
                None if se is None else se[i].to(self.device, torch.float32))

    def truth_reflectance(self) -> torch.Tensor:
        """The true reflectance factor per band on the calibrated cube grid ``(L, cube_px, cube_px)``:
        the window's truth box-averaged from the truth grid."""
        return self.on_cube(torch.stack([self.render_band(b.wavelength_nm).truth for b in self.rig.bands]))

    def on_cube(self, images: torch.Tensor) -> torch.Tensor:
        """Truth-grid images ``(L, N, N)`` (window and margin) cut to the window and box-averaged to the
        calibrated cube grid ``(L, cube_px, cube_px)``, float64."""
        m, n, k = self._margin_px, self._window_px, self.settings.truth.oversample
        return torch.nn.functional.avg_pool2d(images[:, m:m + n, m:m + n].double()[:, None], k)[:, 0]

    def truth_std_error(self) -> torch.Tensor | None:
        """The truth's Monte Carlo standard error on the cube grid ``(L, cube_px, cube_px)`` (pixels of the
        truth grid are independent: the box average divides it by the oversampling), None for diffusion."""
        if self.settings.truth.physics != "transport":
            return None
        m, n, k = self._margin_px, self._window_px, self.settings.truth.oversample
        se = torch.stack([self.render_band(b.wavelength_nm).truth_std_error[m:m + n, m:m + n] for b in self.rig.bands]).double()
        return (torch.nn.functional.avg_pool2d((se**2)[:, None], k)[:, 0] / (k * k)).sqrt()

    def write_truth(self, folder: str | Path) -> list[Path]:
        """Write ``truth/maps.exr`` (the maps over the window, truth grid), ``truth/reflectance.exr``
        (``R_<nm>`` on the cube grid) and ``truth/simulation.json`` (seed, scene, settings, frames)."""
        out = Path(folder) / "truth"
        m, n = self._margin_px, self._window_px
        maps = self.scene_maps()
        crop = {k: getattr(maps, k)[:, m:m + n, m:m + n] for k in ("C_m", "beta_m", "C_he", "C_bc", "C_hd")}
        window = maps.replace(**crop, absorbance=maps.absorbance[..., m:m + n, m:m + n])
        attrs = {"software": "skinlayers simulated bench", "seed": str(self.seed)}
        paths = [write_maps(out / "maps.exr", window, attributes=attrs)]
        g = self.rig.geometry
        se = self.truth_std_error()
        t = self.settings.truth
        attrs = {**attrs, "physics": t.physics, **({"photons_per_node": str(t.photons)} if t.physics == "transport" else {})}
        paths.append(write_spectral(out / "reflectance.exr", self.truth_reflectance().float(), torch.tensor(self.rig.wavelengths_nm),
                                    g.window_mm / g.cube_px, attributes=attrs, extra=None if se is None else {"SE": se.float()}))
        physics = {"physics": t.physics}
        if se is not None:
            physics.update(photons_per_node=t.photons, anisotropy=self.renderer.settings.transport.anisotropy,
                           std_error_median_per_band={f"{w:g}": float(v.median()) for w, v in zip(self.rig.wavelengths_nm, se)},
                           seconds_per_band={f"{b.wavelength_nm:g}": round(self.render_band(b.wavelength_nm).seconds, 1) for b in self.rig.bands})
        record = {"seed": self.seed, "truth_physics": physics, "scene": self.scene.config.model_dump(mode="json"),
                  "settings": self.settings.model_dump(mode="json"), "rig": self.rig_as_used().model_dump(mode="json"),
                  "frames": [asdict(f) for f in self.frames]}
        paths.append(_write_json(out / "simulation.json", record))
        return paths

    # -- frames -----------------------------------------------------------------------------------
    def frame(self, position: int, exposure: ExposureSettings) -> np.ndarray:
        """The raw RGGB mosaic ``(H, W)`` uint16 of one exposure with the wheel at ``position``."""
        band = self.band_at(position)
        state = "dark" if band is None else self.target
        self._counts[(state, position)] += 1
        seed = _frame_seed(self.seed, state, position, self._counts[(state, position)])
        gen = torch.Generator(device=self.device).manual_seed(seed)
        u = torch.rand(4, generator=gen, device=self.device, dtype=torch.float64).tolist()
        s = self.settings
        flash = 1.0 + s.flash.jitter * (2.0 * u[0] - 1.0)
        radius, angle = s.motion.max_shift_px * math.sqrt(u[1]), 2.0 * math.pi * u[2]
        shift = (radius * math.cos(angle), radius * math.sin(angle))
        rotation = s.motion.max_rotation_deg * (2.0 * u[3] - 1.0)
        self.frames.append(SimulatedFrame(len(self.frames), position, None if band is None else band.wavelength_nm, state,
                                          exposure.iso, exposure.shutter_s, exposure.aperture_f, flash, shift, rotation))
        geo = self.geometry
        if band is None:
            mean = torch.zeros(geo.height_px, geo.width_px, dtype=torch.float64, device=self.device)
        else:
            image = gaussian_blur(self._scene_image(band, self._shift_mm(shift), rotation), s.camera.psf_sigma_px)
            scale = flash * self.electrons_per_reflectance(band.wavelength_nm, exposure.aperture_f)
            image = image * torch.as_tensor(scale, dtype=image.dtype, device=image.device)[:, None, None]
            mean = mosaic(image) * self._vignetting
        return expose(mean, s.sensor, exposure.iso, gen)

    def _scene_image(self, band: BandConfig, shift_mm: tuple[float, float], rotation_deg: float) -> torch.Tensor:
        """Per channel, the reflectance factor (times the target's polarization factor) each raw pixel
        sees, averaged over its sub-pixel samples: ``(3, H, W)``."""
        s, rig, geo = self.settings, self.rig, self.geometry
        half = rig.geometry.window_mm / 2.0
        x0, y0, x1, y1 = s.scene.gray_card_mm
        if self.target == "skin":
            render = self.render_band(band.wavelength_nm)
            skin = render.channels * rig.polarization.skin_factor
        else:
            flat = rig.targets.spectralon_at(band.wavelength_nm) * rig.polarization.spectralon_factor
        out = torch.empty(3, geo.height_px, geo.width_px, dtype=torch.float32, device=self.device)
        for r0 in range(0, geo.height_px, _ROWS_PER_CHUNK):
            rows = slice(r0, min(r0 + _ROWS_PER_CHUNK, geo.height_px))
            x, y = sample_points(geo, s.camera.supersample, rows, self.device)
            if self.target == "skin":
                px, py = to_subject(x, y, shift_mm, rotation_deg)
                # the share of each sample's cell inside the window, not a yes/no at its centre: a
                # point test draws the tape's edge as a staircase of 1/supersample px steps
                fx, fy = self._sample_footprint_mm(rows)
                inside = ((half - px.abs()) / fx + 0.5).clamp(0.0, 1.0) * ((half - py.abs()) / fy + 0.5).clamp(0.0, 1.0)
                inside = inside.to(torch.float32)
                value = bilinear(skin, px, py, self.truth_mm_per_pixel) * inside + s.scene.tape_reflectance * (1.0 - inside)
            else:
                value = torch.full((3, *x.shape), flat, dtype=torch.float32, device=self.device)
            card = ((x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)).to(torch.float32)
            value = value * (1.0 - card) + rig.targets.gray_card_reflectance * card
            out[:, rows] = value.mean(dim=1)
        return out


    def _sample_footprint_mm(self, rows: slice) -> tuple[torch.Tensor, torch.Tensor]:
        """Extent along the skin plane's x and y of one sub-pixel sample's cell, per raw pixel of ``rows``
        ``(R, W)``: the cell is a small parallelogram under the camera's perspective."""
        geo, n = self.geometry, self.settings.camera.supersample
        v = torch.arange(rows.start, rows.stop, dtype=torch.float64, device=self.device)[:, None]
        u = torch.arange(geo.width_px, dtype=torch.float64, device=self.device)[None, :]
        x0, y0 = geo.unproject(u, v)
        xu, yu = geo.unproject(u + 1.0, v)
        xv, yv = geo.unproject(u, v + 1.0)
        return ((xu - x0).abs() + (xv - x0).abs()) / n, ((yu - y0).abs() + (yv - y0).abs()) / n


def _transport_seed(seed: int, band_nm: float) -> int:
    """The photons of one band's truth: fixed by the session's seed and the band."""
    return int(hashlib.sha256(f"transport {seed} {band_nm:g}".encode()).hexdigest()[:12], 16)


def _frame_seed(seed: int, state: str, position: int, count: int) -> int:
    """A frame's own random stream, keyed by what it is (the n-th exposure of this state and position),
    not by what came before: a session resumed on a new bench gets, for each frame it still has to
    take, the picture the unbroken session would have got."""
    digest = hashlib.sha256(f"{seed}|{state}|{position}|{count}".encode()).digest()
    return int.from_bytes(digest[:8], "little") & ((1 << 63) - 1)


def _write_json(path: Path, data: dict) -> Path:
    return atomic_write(path, (json.dumps(data, indent=2) + "\n").encode())


def flash_power(settings: SimulationSettings, rig: RigConfig, spectra: dict, reference_signal: float) -> float:
    """``white_electrons`` at which the brightest reference frame of ``rig`` (Spectralon at the image
    centre, the flash at its strongest) reaches ``sensor.reference_fill`` of the range; ``spectra``: each
    band's ``BandSpectrum`` by wavelength, ``reference_signal``: the unit's (green, 10 nm at 550 nm)."""
    s = settings
    brightest = max(
        spectra[b.wavelength_nm].channel_signal.max() / reference_signal
        * rig.targets.spectralon_at(b.wavelength_nm) * rig.polarization.spectralon_factor
        * (1.0 + s.flash.jitter) * (10.0 / b.aperture_f) ** 2 / e_per_dn(s.sensor, b.iso)
        for b in rig.bands
    )
    return s.sensor.reference_fill * (s.sensor.white_level - max(s.sensor.black_level)) / brightest
