"""The fit's model error through each filter, for ``design-bands``: what the fit's renderer misses of the skin.

The bound of ``band_design`` counts the camera's noise, but the fit also misses what its model cannot
hold: the simulator renders the skin on a finer grid, with every wavelength of the filter's quadrature,
a tighter series and the skin beyond the window as it is, and a cube pixel's reflectance is the mean
over its area, not the reflectance of its mean maps. Only a render shows it, so it is
measured (``measure_discrepancy``): the demo's scene rendered as the simulator renders it
(``SimulatedBench.render_band``: the truth grid, each filter's full quadrature, box-averaged to the cube
grid) against the fit's own renderer (``SkinRenderer`` with the default settings, the cube grid, the
band's three nodes and weights, ``reconstruct/levels/problem.py``) at the truth's maps box-averaged to the cube
grid; the rig's whole window, lit as the rig lights it, on a cube of ``cube_px``² pixels (the rig's own
where it is smaller). Not on a patch of the rig's pixel size: the window's size changes the result while
the pixel's does not (docs/band_design.md, "The model's error").

Per filter, relative to the fit's render: the mean over the window (``bias_rel``: the same in every pixel,
a systematic no sharing of a map over pixels averages away) and the standard deviation (``spread_rel``:
different from pixel to pixel, it acts on the fit as noise does). Measured once per rig window,
filters and settings (``discrepancy``), each filter kept in the cache (``model/tables.default_cache_dir``).
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import dataclass
from typing import Sequence

import torch

__all__ = ["DISCREPANCY_CUBE_PX", "DISCREPANCY_SEED", "Discrepancy", "discrepancy", "measure_discrepancy"]

#: The scene's seed: the prior's (``band_information.PRIOR_SEED``); the pipeline's checks use others.
DISCREPANCY_SEED = 20
#: The side of the cube it is measured on (pixels; the rig's cube where that is smaller).
DISCREPANCY_CUBE_PX = 64
#: Filters rendered by one bench: the scene's absorbance is kept at every node of its filters (memory).
DISCREPANCY_CHUNK = 6
#: Bumped when what is measured changes: cached measurements of an older version are not used.
FORMAT_VERSION = 2  # 2: the whole window on a coarser cube, not a patch of the rig's pixel size


@dataclass(frozen=True)
class Discrepancy:
    """Per filter (``centre_nm``, ``fwhm_nm``, each ``(F,)``), the simulator's render over the fit's less 1:
    its mean over the window's pixels (``bias_rel``) and their standard deviation (``spread_rel``), on a
    ``cube_px``² cube of ``mm_per_pixel``; ``seconds`` spent measuring (0: all read from the cache)."""

    centre_nm: list[float]
    fwhm_nm: list[float]
    bias_rel: list[float]
    spread_rel: list[float]
    mm_per_pixel: float
    cube_px: int
    seed: int
    seconds: float

    def at(self, filters) -> tuple[torch.Tensor, torch.Tensor]:
        """``bias_rel`` and ``spread_rel`` ``(F,)`` float64 of ``filters`` (each measured here)."""
        index = {(c, w): i for i, (c, w) in enumerate(zip(self.centre_nm, self.fwhm_nm))}
        rows = [index[(f.centre_nm, f.fwhm_nm)] for f in filters]
        return (torch.tensor([self.bias_rel[i] for i in rows], dtype=torch.float64),
                torch.tensor([self.spread_rel[i] for i in rows], dtype=torch.float64))


def _measuring_rig(rig, cube_px: int):
    """The rig with its cube at most ``cube_px``² (its window unchanged), photographed by the simulator."""
    from .truths import MIN_RECTIFY_PX  # noqa: PLC0415

    g = rig.geometry
    n = min(cube_px, g.cube_px)
    geometry = {"cube_px": n, "rectify_px": max(2 * n, MIN_RECTIFY_PX)}
    return rig.model_copy(update={"geometry": g.model_copy(update=geometry),
                                  "camera": rig.camera.model_copy(update={"driver": "simulated"})})


def measure_discrepancy(rig, filters: Sequence, *, simulation=None, seed: int = DISCREPANCY_SEED,
                        cube_px: int = DISCREPANCY_CUBE_PX, device: str | torch.device = "cpu") -> Discrepancy:
    """The simulator's render of the demo's scene through each filter against the fit's renderer at the
    same maps (the module docstring); minutes for a catalogue of tens of filters on two CPU cores."""
    from ..acquire.simulator._optics import band_spectrum  # noqa: PLC0415
    from ..acquire.simulator.scene import scene_from_dict  # noqa: PLC0415
    from ..acquire.simulator.simulated import SimulatedBench  # noqa: PLC0415
    from .truths import demo_scene  # noqa: PLC0415

    start = time.perf_counter()
    filters = list(dict.fromkeys(filters))
    measured = _measuring_rig(rig, cube_px)
    scene = scene_from_dict(demo_scene())
    rows, cube = {}, None
    for chunk in _chunks(filters):  # a few filters a bench: the scene's maps at their nodes only
        bench = SimulatedBench(measured, scene, simulation, seed=seed, device=device)
        s = bench.settings
        bench.spectra = {f.centre_nm: band_spectrum(f.centre_nm, f.fwhm_nm, s.filters.wavelength_samples, s.flash.temperature_k,
                                                     s.sensor.sensitivity) for f in chunk}
        truth = bench.on_cube(torch.stack([bench.render_band(f.centre_nm).truth for f in chunk])).cpu()  # (F, n', n')
        if cube is None:  # the truth's maps on the cube grid (the same scene in every bench)
            maps = bench.scene_maps()
            cube = maps.replace(**{p: bench.on_cube(getattr(maps, p)) for p in ("C_m", "beta_m", "C_he", "C_bc", "C_hd")},
                                mm_per_pixel=measured.geometry.window_mm / measured.geometry.cube_px, absorbance=None,
                                absorbance_wavelength_nm=None, rho_s=None)
        for f, r in zip(chunk, (truth / _fit_render(cube, measured, chunk) - 1.0).reshape(len(chunk), -1)):
            rows[f] = r
    relative = torch.stack([rows[f] for f in filters])
    return Discrepancy([f.centre_nm for f in filters], [f.fwhm_nm for f in filters], relative.mean(1).tolist(),
                       relative.std(1).tolist(), cube.mm_per_pixel, measured.geometry.cube_px, seed, time.perf_counter() - start)


def _chunks(filters: Sequence) -> list[list]:
    """``filters`` (distinct) in groups of at most ``DISCREPANCY_CHUNK``, no two of a group with the same
    centre (a bench keeps a band's spectrum and render by its centre)."""
    chunks: list[list] = []
    for f in filters:
        group = next((c for c in chunks if len(c) < DISCREPANCY_CHUNK and all(g.centre_nm != f.centre_nm for g in c)), None)
        if group is None:
            chunks.append([f])
        else:
            group.append(f)
    return chunks


def _fit_render(maps, rig, filters) -> torch.Tensor:
    """The fit's renderer (default settings) at ``maps`` on the cube grid through each filter ``(F, H, W)``:
    its three nodes per band and their weights, the window lit, seen from the rig's camera."""
    from ..model.render.illumination import Light  # noqa: PLC0415
    from ..model.render.renderer import SkinRenderer  # noqa: PLC0415
    from ..model.settings import ModelSettings  # noqa: PLC0415
    from ..reconstruct.levels.problem import BAND_WEIGHTS, band_nodes  # noqa: PLC0415

    nodes = band_nodes(torch.tensor([f.centre_nm for f in filters], dtype=torch.float64),
                       torch.tensor([f.fwhm_nm for f in filters], dtype=torch.float64))  # (F, 3)
    light = Light("window", size_mm=rig.geometry.window_mm)
    renderer = SkinRenderer(ModelSettings())
    with torch.no_grad():
        image = renderer.render(maps.to(dtype=torch.float64), light, nodes.reshape(-1), under_gel=True, light_angle_deg=0.0,
                                view_angle_deg=rig.camera.angle_deg).image[0]
    weights = torch.tensor(BAND_WEIGHTS, dtype=torch.float64, device=image.device)
    return (image.reshape(len(filters), len(BAND_WEIGHTS), *image.shape[-2:]) * weights[None, :, None, None]).sum(1).cpu()


def discrepancy(rig, filters: Sequence, *, simulation=None, seed: int = DISCREPANCY_SEED, cube_px: int = DISCREPANCY_CUBE_PX,
                device: str | torch.device = "cpu", say=None) -> Discrepancy:
    """``measure_discrepancy`` of ``filters`` (distinct), each filter kept in the cache under everything its
    measurement depends on (the rig's window and camera angle, the scene, seed, simulation and model
    settings): a later design reads back the filters measured before and measures the others only;
    ``say`` reports a measurement's start."""
    from ..acquire.simulator.simulation_settings import load_simulation_settings  # noqa: PLC0415
    from .truths import demo_scene  # noqa: PLC0415
    from ..formats.files import atomic_write  # noqa: PLC0415
    from ..model.settings import ModelSettings  # noqa: PLC0415
    from ..model.column.tables import default_cache_dir  # noqa: PLC0415

    filters = list(dict.fromkeys(filters))
    settings = simulation if simulation is not None else load_simulation_settings(None)
    measured = _measuring_rig(rig, cube_px)
    key = json.dumps({"version": FORMAT_VERSION, "seed": seed, "geometry": measured.geometry.model_dump(mode="json"),
                      "angle": rig.camera.angle_deg, "scene": demo_scene(), "simulation": settings.model_dump(mode="json"),
                      "model": ModelSettings().model_dump(mode="json")}, sort_keys=True)
    folder = default_cache_dir() / "band_discrepancy" / hashlib.sha256(key.encode()).hexdigest()[:24]
    path = lambda f: folder / f"{f.centre_nm:.6g}nm-{f.fwhm_nm:.6g}nm.json"  # noqa: E731
    kept, seconds = {}, 0.0
    for f in filters:
        try:
            kept[f] = json.loads(path(f).read_text())
        except (OSError, ValueError):
            pass  # not measured yet (or an unreadable file): measured below
    missing = [f for f in filters if f not in kept]
    if missing:
        if say is not None:
            say(f"measuring the fit's model error through {len(missing)} filters (once for this rig window; minutes)")
        found = measure_discrepancy(rig, missing, simulation=settings, seed=seed, cube_px=cube_px, device=device)
        for f, bias, spread in zip(missing, found.bias_rel, found.spread_rel):
            kept[f] = {"bias_rel": bias, "spread_rel": spread}
            atomic_write(path(f), json.dumps(kept[f]).encode())
        seconds = found.seconds
    return Discrepancy([f.centre_nm for f in filters], [f.fwhm_nm for f in filters], [kept[f]["bias_rel"] for f in filters],
                       [kept[f]["spread_rel"] for f in filters], measured.geometry.window_mm / measured.geometry.cube_px,
                       measured.geometry.cube_px, seed, seconds)
