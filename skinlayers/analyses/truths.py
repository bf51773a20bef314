"""Transport truths the analyses reuse: Monte Carlo runs made once and shipped as package data.

The analyses (``skinlayers tradeoff``, ``skinlayers stability``) measure the model against light it did
not make, but photons cost minutes a band on two CPU cores. So the Monte Carlo (``model/transport``) runs
once, by ``python -m skinlayers.analyses.truths`` (its time is recorded in each file), and what it made ships in
``skinlayers/data/truths/``:

- ``forward_scenes.csv``: exitance profiles M/E of five heterogeneous scenes (``FORWARD_SCENES``) on
  Table 2's III interior at ``FORWARD_WAVELENGTHS_NM``, with their standard errors;
- ``session_<seed>.npz`` + ``.json``: for each of ``SESSION_SEEDS``, the simulated bench's skin as the
  transport reference rendered it (the demo's scene at a ``SESSION_PX``² cube, every band's camera channels
  and truth on the truth grid, and the truth's standard error). A session photographed from these
  (``session_renders``) goes through the rig, the camera's noise and the calibration like any other, with
  no photon walked.
"""

from __future__ import annotations

import csv
import json
import math
import os
import pickle
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

__all__ = ["FORWARD_SCENES", "FORWARD_WAVELENGTHS_NM", "SESSIONS", "SESSION_PX", "SESSION_PX_64", "SESSION_SEEDS",
           "SESSION_SEEDS_64", "TRUTH_DIR", "HYPERSPECTRAL_BANDS", "RIG_BANDS", "hyperspectral_bands", "ForwardScene", "MIN_RECTIFY_PX", "demo_scene", "session_rig",
           "forward_scene", "forward_truth", "make_forward_truths", "make_session_truth", "session_renders",
           "shipped_session"]

#: The coarsest rectified window the calibration works on: at 64 px the gray card's region, moved by the
#: subject's motion, reaches into the window's (so --size 32 rectifies at 128 px, not 64).
MIN_RECTIFY_PX = 128
#: The default rig's bands, and the hyperspectral rig's (Hyper-Skin's layout: a band of the width every
#: 10 nm across the visible), setting 1 its closed state.
RIG_BANDS = 9
HYPERSPECTRAL_BANDS = 31
HYPERSPECTRAL_FIRST_NM, HYPERSPECTRAL_LAST_NM, HYPERSPECTRAL_FWHM_NM = 400.0, 700.0, 10.0
#: Where the shipped truths live (package data).
TRUTH_DIR = Path(__file__).resolve().parents[1] / "data" / "truths"
#: The forward scenes' wavelengths: blue, green and red light reach the dermis differently.
FORWARD_WAVELENGTHS_NM = (470.0, 560.0, 650.0)
#: Scene pixel (mm) and row width (px) of the y-invariant scenes; the window scene's side (px).
SCENE_MM = 0.1
ROW_PX = 80
WINDOW_SCENE_PX = 90
#: Rows a y-invariant scene is rendered on.
RENDER_ROWS = 16
#: Rows about the window scene's centre line averaged into its profile.
WINDOW_ROWS = 20
#: Lit skin beyond the profiles' maps (the dermis's diffusion length at 650 nm is about 2 mm).
MARGIN_MM = 8.0
FORWARD_PHOTONS = 500_000
#: The sessions: seeds no default was tuned on, the cube's side, photons per wavelength node.
SESSION_SEEDS = (41, 42, 43)
SESSION_PX = 32
SESSION_PHOTONS = 150_000
#: Sessions at the size a user fits: 64² cubes. Photons per node so that the truth's Monte Carlo error per
#: cube pixel is at most half the camera's there (a test checks it): the error per pixel grows with the
#: pixels a node's photons are shared by. These seeds chose transport's node spacings and set its model
#: floor (63 only checks the floor): scores on them are not held out (docs/transport.md).
SESSION_SEEDS_64 = (61, 62, 63)
SESSION_PX_64 = 64
SESSION_PHOTONS_64 = 250_000
#: Every shipped session: seed -> (cube side in px, photons per wavelength node).
SESSIONS = {**{s: (SESSION_PX, SESSION_PHOTONS) for s in SESSION_SEEDS},
            **{s: (SESSION_PX_64, SESSION_PHOTONS_64) for s in SESSION_SEEDS_64}}
#: The scenes, by name: what each holds (the feature; the skin around it is Table 2's III interior).
FORWARD_SCENES = {
    "stripe": "a 1-mm stripe of dermal blood (C_hd 0.08), uniform light",
    "vessel": "a thin vessel: 0.3 mm of dermal blood C_hd 0.2, uniform light",
    "hair": "one 0.1-mm column of interface absorbance 2 (a hair), uniform light",
    "step": "a melanin step (C_m ×6 for x > 0), uniform light",
    "window": "homogeneous skin under a 5-mm window of light (the fall-off outside its edge)",
}
#: Per-pixel errors leave out the feature's first this many mm (its edge is sub-pixel).
FEATURE_EDGE_MM = 0.1


def demo_scene() -> dict:
    """The demo's scene: the simulator's default without hairs. Hairs are interface absorbance the fit's
    model does not hold; their halo in red light biases the maps around them (measured in docs/accuracy.md)."""
    from ..acquire.simulator.scene import load_scene  # noqa: PLC0415

    scene = load_scene(None).model_dump(mode="json")
    scene["hairs"]["count"] = 0
    return scene


def session_rig(size: int, bands: int = RIG_BANDS):
    """The default rig at a ``size``² cube, its camera simulated (as the demo photographs with); with
    ``bands`` = ``HYPERSPECTRAL_BANDS`` the hyperspectral rig of ``hyperspectral_bands``."""
    from ..acquire.hardware.rig import load_rig  # noqa: PLC0415

    over = {"geometry": {"cube_px": size, "rectify_px": max(2 * size, MIN_RECTIFY_PX)}, "camera": {"driver": "simulated"}}
    if bands != RIG_BANDS:
        if bands != HYPERSPECTRAL_BANDS:
            raise ValueError(f"a session rig has {RIG_BANDS} or {HYPERSPECTRAL_BANDS} bands, not {bands}")
        nine = load_rig(**over)
        over["bands"] = hyperspectral_bands(nine.bands)
        over["wheel"] = {"position_count": len(over["bands"]) + 1}
        over["name"] = f"{bands} bands, {HYPERSPECTRAL_FIRST_NM:g}-{HYPERSPECTRAL_LAST_NM:g} nm"
    return load_rig(**over)


def hyperspectral_bands(nine: list) -> list[dict]:
    """``HYPERSPECTRAL_BANDS`` bands of ``HYPERSPECTRAL_FWHM_NM`` from ``HYPERSPECTRAL_FIRST_NM`` to
    ``HYPERSPECTRAL_LAST_NM`` (Hyper-Skin's layout, as a tunable filter would take them), exposed as the
    nine bands are: each band's ISO makes flash × filter × sensor × ISO the nine bands' median (they lie
    within 0.84–1 of one another), taken to the nearest third stop the simulated camera offers. Below
    420 nm and above 680 nm the light falls under 7% of 550 nm's and the top ISO leaves those frames
    darker (noisier) than the rest, as on a real bench."""
    from ..acquire.simulator._optics import band_spectrum  # noqa: PLC0415
    from ..acquire.simulator.simulation_settings import load_simulation_settings  # noqa: PLC0415

    sim = load_simulation_settings(None)

    def signal(centre_nm: float, fwhm_nm: float) -> float:
        spectrum = band_spectrum(centre_nm, fwhm_nm, sim.filters.wavelength_samples, sim.flash.temperature_k, sim.sensor.sensitivity)
        return float(spectrum.channel_signal.max())

    exposure = float(np.median([signal(b.wavelength_nm, b.fwhm_nm) * b.iso for b in nine]))
    stops = np.log(np.asarray(sim.sensor.iso_values, dtype=np.float64))
    centres = np.linspace(HYPERSPECTRAL_FIRST_NM, HYPERSPECTRAL_LAST_NM, HYPERSPECTRAL_BANDS)
    isos = [int(round(math.exp(stops[np.abs(stops - math.log(exposure / signal(w, HYPERSPECTRAL_FWHM_NM))).argmin()])))
            for w in centres]
    ref = nine[0]
    return [{"wavelength_nm": float(w), "fwhm_nm": HYPERSPECTRAL_FWHM_NM, "filter_position": i + 2, "iso": iso,
             "shutter_s": ref.shutter_s, "aperture_f": ref.aperture_f} for i, (w, iso) in enumerate(zip(centres, isos))]


@dataclass(frozen=True)
class ForwardScene:
    """A forward scene: its maps ``(1, H, W)`` at ``SCENE_MM``, its light, whether it is y-invariant (one
    row, rendered as a profile) and the pixels ``(W,)`` its per-pixel error is taken over."""

    name: str
    maps: object
    light: object
    profile: bool
    keep: torch.Tensor
    x_mm: torch.Tensor

    def render_maps(self):
        """The maps the renderer draws: a y-invariant row repeated over ``RENDER_ROWS`` rows (the renderer
        needs rows for its blurs; ``scene_profile`` takes the middle one), the window scene as it is."""
        from ..model.patch.maps import SkinMaps  # noqa: PLC0415

        m = self.maps
        if not self.profile:
            return m
        return SkinMaps(*(v.expand(1, RENDER_ROWS, v.shape[-1]).contiguous() for v in m.params().values()),
                        mm_per_pixel=m.mm_per_pixel, absorbance_wavelength_nm=m.absorbance_wavelength_nm,
                        absorbance=None if m.absorbance is None else m.absorbance.expand(1, -1, RENDER_ROWS, -1).contiguous())


def _x(width_px: int) -> torch.Tensor:
    return (torch.arange(width_px, dtype=torch.float64) - (width_px - 1) / 2.0) * SCENE_MM


def forward_scene(name: str) -> ForwardScene:
    """The scene ``name`` of ``FORWARD_SCENES`` (float64 maps)."""
    from ..model import TABLE2  # noqa: PLC0415
    from ..model.render.illumination import Light  # noqa: PLC0415
    from ..model.patch.maps import SkinMaps  # noqa: PLC0415

    base = TABLE2["III interior"]
    if name not in FORWARD_SCENES:
        raise ValueError(f"unknown forward scene {name!r}; the scenes are {', '.join(FORWARD_SCENES)}")
    if name == "window":
        x = _x(WINDOW_SCENE_PX)
        maps = SkinMaps.uniform(base, (WINDOW_SCENE_PX, WINDOW_SCENE_PX), SCENE_MM, dtype=torch.float64)
        keep = (x.abs() < 2.4) | ((x.abs() > 2.6) & (x.abs() < 3.5))
        return ForwardScene(name, maps, Light("window", size_mm=5.0), False, keep, x)
    x = _x(ROW_PX)
    row = SkinMaps.uniform(base, (1, ROW_PX), SCENE_MM, dtype=torch.float64)

    def with_(key: str, inside: torch.Tensor, value: float):
        return row.replace(**{key: torch.where(inside, value, base[key]).reshape(1, 1, ROW_PX)})

    half = {"stripe": 0.5, "vessel": 0.15, "hair": 0.05, "step": 0.0}[name]
    if name == "stripe":
        maps = with_("C_hd", x.abs() < 0.5, 0.08)
    elif name == "vessel":
        maps = with_("C_hd", x.abs() < 0.15, 0.2)
    elif name == "step":
        maps = with_("C_m", x > 0, 6 * base["C_m"])
    else:
        wl = torch.tensor(FORWARD_WAVELENGTHS_NM, dtype=torch.float64)
        p = torch.zeros(1, wl.numel(), 1, ROW_PX, dtype=torch.float64)
        p[..., ROW_PX // 2] = 2.0
        maps = row.replace(absorbance=p, absorbance_wavelength_nm=wl)
    keep = (x.abs() > half + FEATURE_EDGE_MM) if half > 0 else (x.abs() > FEATURE_EDGE_MM)
    return ForwardScene(name, maps, Light("uniform"), True, keep, x)


def scene_profile(scene: ForwardScene, image: torch.Tensor) -> torch.Tensor:
    """A render's exitance ``(L, H, W)`` of ``scene`` as its profile ``(L, W)``: the one row of a
    y-invariant scene, the mean of the ``WINDOW_ROWS`` centre rows of the window."""
    if scene.profile:
        return image[:, image.shape[1] // 2]
    c = image.shape[1] // 2
    return image[:, c - WINDOW_ROWS // 2: c + WINDOW_ROWS // 2].mean(1)


# -- the Monte Carlo, run once -------------------------------------------------------------------------


def make_forward_truths(out: Path = TRUTH_DIR, photons: int = FORWARD_PHOTONS, scenes=tuple(FORWARD_SCENES)) -> Path:
    """Run the Monte Carlo of every forward scene and write ``forward_scenes.csv`` (row by row per scene:
    a scene already in the file is kept, so an interrupted run continues)."""
    from ..model import ModelSettings  # noqa: PLC0415
    from ..model.transport import TransportRenderer  # noqa: PLC0415

    out.mkdir(parents=True, exist_ok=True)
    path = out / "forward_scenes.csv"
    done = {r["scene"] for r in _read_csv(path)} if path.exists() else set()
    transport = TransportRenderer(ModelSettings.model_validate({"transport": {"margin_mm": MARGIN_MM}}))
    wl = torch.tensor(FORWARD_WAVELENGTHS_NM, dtype=torch.float64)
    if not path.exists():
        path.write_text(
            "# Exitance profiles M/E of heterogeneous scenes by the project's Monte Carlo (model/transport), made by\n"
            "#   python -m skinlayers.analyses.truths; Table 2's III interior, 0.1-mm pixels, the model's optics (n 1.40 / 1.38,\n"
            "#   the interface absorber), isotropic scattering with sigma_s = sigma_s', lit 8 mm beyond the maps.\n"
            "# Units: x_mm in mm from the scene's centre; exitance and std_error: exitance over irradiance (1).\n"
            "# window: the mean of the 20 rows about the centre line of a 90x90 px render.\n"
            "scene,wavelength_nm,x_mm,exitance,std_error,photons,seconds\n")
    for name in scenes:
        if name in done:
            continue
        scene = forward_scene(name)
        start = time.perf_counter()
        if scene.profile:
            result = transport.profile(scene.maps, scene.light, wl, photons=photons)
        else:
            result = transport.render(scene.maps, scene.light, wl, photons=photons)
        seconds = time.perf_counter() - start
        mean = scene_profile(scene, result.exitance[0])
        # the window's profile is a mean of rows whose errors are independent
        se = scene_profile(scene, result.exitance_std_error[0].pow(2)).sqrt() / (1.0 if scene.profile else math.sqrt(WINDOW_ROWS))
        with path.open("a", newline="") as f:
            writer = csv.writer(f)
            for j, w in enumerate(FORWARD_WAVELENGTHS_NM):
                for i, x in enumerate(scene.x_mm.tolist()):
                    writer.writerow([name, f"{w:g}", f"{x:.4f}", f"{float(mean[j, i]):.6g}", f"{float(se[j, i]):.3g}", photons,
                                     round(seconds, 1)])
        print(f"forward scene {name}: {seconds:.0f} s", flush=True)
    return path


def _read_csv(path: Path) -> list[dict]:
    with path.open() as f:
        return list(csv.DictReader(line for line in f if not line.startswith("#")))


def forward_truth(name: str, path: Path | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """The shipped Monte Carlo profile of scene ``name``: exitance and its standard error, ``(L, W)`` each."""
    path = path or TRUTH_DIR / "forward_scenes.csv"
    rows = [r for r in _read_csv(path) if r["scene"] == name]
    if not rows:
        raise FileNotFoundError(f"{path}: no Monte Carlo of scene {name!r} (make it with python -m skinlayers.analyses.truths)")
    n = len(FORWARD_WAVELENGTHS_NM)
    mean = torch.tensor([float(r["exitance"]) for r in rows], dtype=torch.float64).reshape(n, -1)
    se = torch.tensor([float(r["std_error"]) for r in rows], dtype=torch.float64).reshape(n, -1)
    return mean, se


def make_session_truth(seed: int, out: Path = TRUTH_DIR, photons: int = SESSION_PHOTONS, size_px: int = SESSION_PX) -> Path:
    """Render the demo's scene by the transport reference for a ``size_px``² session of ``seed`` and write
    ``session_<seed>.npz`` (each band's camera channels ``(L, 3, N, N)``, truth and standard error ``(L, N, N)``,
    float32, on the truth grid) and ``session_<seed>.json`` (what made it, and how long it took).

    Resumable: each band is kept in ``.session_<seed>.partial.pt`` as it is rendered, and a run that finds
    that file (made with the same photons, size, scene, bands and software) renders only the bands it lacks."""
    from ..acquire.simulator.scene import scene_from_dict  # noqa: PLC0415
    from ..acquire.simulator.simulated import SimulatedBench  # noqa: PLC0415
    from ..acquire.simulator.simulation_settings import load_simulation_settings  # noqa: PLC0415
    from ..formats.version import software_version  # noqa: PLC0415

    out.mkdir(parents=True, exist_ok=True)
    rig, scene = session_rig(size_px), demo_scene()
    settings = load_simulation_settings(None, truth={"physics": "transport", "photons": photons})
    bench = SimulatedBench(rig, scene_from_dict(scene), settings, seed, device="cpu")
    partial = out / f".session_{seed}.partial.pt"
    key = {"photons": photons, "size_px": size_px, "scene": scene, "wavelengths_nm": list(rig.wavelengths_nm),
           "software": software_version()}
    kept = _partial_bands(partial, key)
    for nm, render in kept["bands"].items():
        bench.adopt_band(nm, render)
    for band in rig.bands:
        if band.wavelength_nm in kept["bands"]:
            continue
        start = time.perf_counter()
        kept["bands"][band.wavelength_nm] = bench.render_band(band.wavelength_nm)
        kept["seconds"] += time.perf_counter() - start
        torch.save(kept, partial.with_suffix(".tmp"))
        os.replace(partial.with_suffix(".tmp"), partial)  # a kill mid-save leaves the previous bands whole
        print(f"session {seed}: {band.wavelength_nm:g} nm after {kept['seconds']:.0f} s", flush=True)
    renders = bench.band_renders()
    np.savez_compressed(out / f"session_{seed}.npz", **{k: v.numpy() for k, v in renders.items()})
    record = {"seed": seed, "cube_px": size_px, "photons_per_node": photons, "physics": "transport",
              "scene": scene, "wavelengths_nm": list(rig.wavelengths_nm), "seconds": round(kept["seconds"], 1),
              "threads": torch.get_num_threads(), "made": time.strftime("%Y-%m-%d"), "software": software_version(),
              # the standard error of a cube pixel, the mean of oversample² truth pixels (errors independent)
              "cube_std_error_median": round(float((bench.on_cube(renders["std_error"].double() ** 2).sqrt()
                                                    / settings.truth.oversample).median()), 5)
              if "std_error" in renders else None,
              "units": "channels and truth: reflectance factor (1) on the truth grid; std_error: the truth's Monte Carlo "
                       "standard error (1)"}
    (out / f"session_{seed}.json").write_text(json.dumps(record, indent=1) + "\n")
    partial.unlink(missing_ok=True)
    print(f"session {seed}: {kept['seconds']:.0f} s", flush=True)
    return out / f"session_{seed}.npz"


def _partial_bands(partial: Path, key: dict) -> dict:
    """The bands an interrupted run of ``make_session_truth`` kept under ``partial``, when made with the same
    ``key`` (photons, size, scene, wavelengths, software); else an empty record."""
    empty = {"key": key, "bands": {}, "seconds": 0.0}
    if not partial.exists():
        return empty
    try:
        kept = torch.load(partial, weights_only=False)
    except (OSError, RuntimeError, EOFError, pickle.UnpicklingError):
        return empty  # unreadable: the bands are rendered again
    return kept if isinstance(kept, dict) and kept.get("key") == key else empty


def session_renders(seed: int, folder: Path = TRUTH_DIR) -> tuple[dict, dict[str, torch.Tensor]]:
    """The shipped transport session ``seed``: its record (scene, cube size, photons) and its band renders
    (for ``SimulatedBench.adopt_renders``)."""
    record = json.loads((folder / f"session_{seed}.json").read_text())
    with np.load(folder / f"session_{seed}.npz") as data:
        renders = {k: torch.from_numpy(data[k].copy()) for k in data.files}
    return record, renders


def shipped_session(seed: int, size_px: int, photons: int | None = None, folder: Path = TRUTH_DIR):
    """The shipped transport session of ``seed`` when it was rendered for a ``size_px``² cube of the demo's
    scene (and with ``photons`` per node, when given), as ``session_renders`` gives it; else None."""
    if not (folder / f"session_{seed}.json").exists():
        return None
    record = json.loads((folder / f"session_{seed}.json").read_text())

    if record["cube_px"] != size_px or record["scene"] != demo_scene() or photons not in (None, record["photons_per_node"]):
        return None
    return session_renders(seed, folder)


def main() -> None:
    """Make every shipped truth that is missing (forward scenes, then the sessions)."""
    torch.manual_seed(0)
    start = time.perf_counter()
    make_forward_truths()
    for seed, (size_px, photons) in SESSIONS.items():
        if not (TRUTH_DIR / f"session_{seed}.json").exists():
            make_session_truth(seed, photons=photons, size_px=size_px)
    print(f"truths made in {time.perf_counter() - start:.0f} s", flush=True)


if __name__ == "__main__":
    main()
