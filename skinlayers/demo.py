"""``skinlayers demo``: the whole job on embedded defaults, into a fresh folder.

A simulated capture (the default scene, rig and camera), its calibration into a reflectance cube, the
map fit, and a report that sets the fitted maps against the simulation's truth. Each step is the library
call the matching command makes (``open_devices`` and ``run_session``, ``calibrate_session``,
``fit_cube`` and ``write_outputs``), with the same progress bars.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Optional

import typer

from .formats.cube import CUBE_NAME
from .formats.errors import InputError
from .formats.outputs import refuse_inside_session
from .formats.version import software_version
from .formats.threads import THREADS_HELP, command_threads

__all__ = ["accuracy_against_truth", "demo", "map_errors", "register", "scored_pixels", "sigma_coverage", "simulate_session"]

#: Folder the demo writes to when none is given; taken with a suffix (-2, -3, …) when it exists.
DEFAULT_FOLDER = "skinlayers-demo"



def fresh_folder(base: Path) -> Path:
    """``base`` when it does not exist (or is an empty folder), else the first free ``base-N``."""
    if not base.exists() or (base.is_dir() and not any(base.iterdir())):
        return base
    n = 2
    while (candidate := base.with_name(f"{base.name}-{n}")).exists():
        n += 1
    return candidate


def accuracy_against_truth(session: Path, reconstruction: Path, cube: Path) -> dict:
    """Fitted maps against the simulation's truth (``truth/maps.exr`` box-averaged to the fit's grid):
    per parameter the median error over the pixels in the fit (relative; β_m absolute), the truth's
    and the fit's medians, the fit's median uncertainty and its coverage (``sigma_coverage``: the share of
    those pixels whose truth lies within ±2σ of the fit); the residual RMS beside the cube's noise
    RMS (the cube against ``truth/reflectance.exr``, the noise floor), both over the same pixels and
    the bands the fit used. Pixels flagged for a high residual (hairs and
    veins, which the fit leaves to the residual) are counted out, and the count is given."""
    import numpy as np  # noqa: PLC0415
    import torch  # noqa: PLC0415

    from .formats.exr import read_exr  # noqa: PLC0415
    from .model.patch.maps_io import read_maps  # noqa: PLC0415
    from .reconstruct.diagnosis.checks import FLAG_BITS  # noqa: PLC0415

    truth = read_maps(session / "truth" / "maps.exr")
    fit = read_maps(reconstruction / "maps.exr")
    channels, _ = read_exr(reconstruction / "maps.exr")
    flags = torch.as_tensor(np.asarray(channels["flags"])).to(torch.int64)
    keep = scored_pixels(flags)
    summary = json.loads((reconstruction / "fit.json").read_text())
    out: dict = {"pixels": int(keep.sum()), "high_residual_pixels": int(((flags >> FLAG_BITS["high_residual"]) & 1).sum()),
                 "parameters": map_errors(truth, fit, keep)}
    for name, entry in out["parameters"].items():
        sigma = channels.get(f"sigma_{name}")
        entry["sigma_median"] = float(np.nanmedian(np.asarray(sigma)[keep.numpy()])) if sigma is not None else None
        # the share of scored pixels whose truth lies within ±2σ of the fit (0.95 for an honest normal σ)
        entry["sigma_coverage"] = None if sigma is None else _covered(truth, fit, name, torch.as_tensor(np.asarray(sigma)), keep)
        entry["determined"] = summary["parameters"][name].get("determined", True)
    cube_channels, _ = read_exr(cube)
    truth_r, _ = read_exr(session / "truth" / "reflectance.exr")
    bands = [f"{w:g}" for w in summary["wavelengths_nm"]]
    used = [b for b in bands if summary["residual"]["per_band"].get(b, {}).get("used", True)]
    out["residual_rms"] = float(np.sqrt(np.mean(np.stack([np.asarray(channels[f"res_{b}"]) for b in used])[:, keep.numpy()] ** 2)))
    if truth_r[f"R_{bands[0]}"].shape == cube_channels[f"R_{bands[0]}"].shape:
        noise = np.stack([np.asarray(cube_channels[f"R_{b}"]) - np.asarray(truth_r[f"R_{b}"]) for b in used])
        out["cube_noise_rms"] = float(np.sqrt(np.mean(noise[:, keep.numpy()] ** 2)))
    return out


def scored_pixels(flags):
    """The pixels a fit is scored on ``(H, W)`` bool, from its ``flags`` ``(H, W)``: visible, not flagged for a
    high residual (hairs and veins, which the fit leaves to the residual) nor as a hair's or its halo."""
    from .reconstruct.diagnosis.checks import FLAG_BITS  # noqa: PLC0415

    flags = flags.to("cpu").long()
    return (((flags >> FLAG_BITS["masked"]) & 1) == 0) & (((flags >> FLAG_BITS["high_residual"]) & 1) == 0) \
        & (((flags >> FLAG_BITS["hair"]) & 1) == 0)


def map_errors(truth, fit, keep) -> dict:
    """Per map, the fit's median error against the truth over the ``keep`` pixels ``(H, W)`` of the fit's
    grid (the truth ``SkinMaps`` box-averaged onto it): relative, β_m absolute; the truth's and the fit's
    medians."""
    from .model import PARAMETER_NAMES  # noqa: PLC0415

    keep = keep.to("cpu")
    out = {}
    for name in PARAMETER_NAMES:
        t, f = _on_fit_grid(truth, fit, name)
        err = (f - t)[keep]
        relative = name != "beta_m"
        value = (err.abs() / t[keep].clamp_min(1e-12)).median() if relative else err.abs().median()
        out[name] = {"median_error": float(value), "error_kind": "relative" if relative else "absolute",
                     "truth_median": float(t[keep].median()), "fit_median": float(f[keep].median())}
    return out


def sigma_coverage(truth, fit, sigma, pixels, names) -> dict[str, float]:
    """Per map of ``names``, the share of ``pixels`` ``(H, W)`` bool of the fit's grid where the truth
    (``SkinMaps``, box-averaged onto that grid) lies within 2σ of the fit; ``sigma`` ``(N_PARAMS, H, W)``
    in ``PARAMETER_NAMES`` order. A pixel without a finite σ counts as not covered (a σ the fit could not
    give covers nothing)."""
    from .model import PARAMETER_NAMES  # noqa: PLC0415

    return {name: _covered(truth, fit, name, sigma[PARAMETER_NAMES.index(name)], pixels) for name in names}


def _covered(truth, fit, name: str, sigma, pixels) -> float:
    """The share of ``pixels`` ``(H, W)`` where map ``name``'s truth lies within 2σ of the fit (``sigma`` ``(H, W)``)."""
    t, f = _on_fit_grid(truth, fit, name)
    within = (f - t).abs() <= 2 * sigma.double().cpu()
    return float(within[pixels.to("cpu")].double().mean())


def _on_fit_grid(truth, fit, name: str):
    """One map of the truth ``SkinMaps`` box-averaged onto the fit's grid, and the fit's, ``(H, W)`` float64 on the CPU."""
    import torch.nn.functional as F  # noqa: PLC0415

    k = truth.shape[-1] // fit.shape[-1]
    t = getattr(truth, name)[None].double().cpu()
    return (F.avg_pool2d(t, k) if k > 1 else t)[0, 0], getattr(fit, name)[0].double().cpu()


def _figure(session: Path, reconstruction: Path, path: Path) -> None:
    """Truth, fit and their difference for C_m, β_m, C_he and C_hd."""
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415
    import torch.nn.functional as F  # noqa: PLC0415

    from .model.patch.maps_io import read_maps  # noqa: PLC0415

    truth, fit = read_maps(session / "truth" / "maps.exr"), read_maps(reconstruction / "maps.exr")
    k = truth.shape[-1] // fit.shape[-1]
    names = ("C_m", "beta_m", "C_he", "C_hd")
    fig, axes = plt.subplots(3, len(names), figsize=(3.2 * len(names), 9.0))
    for j, name in enumerate(names):
        t = getattr(truth, name)[None].float()
        t = (F.avg_pool2d(t, k) if k > 1 else t)[0, 0].numpy()
        f = getattr(fit, name)[0].float().numpy()
        lo, hi = float(min(t.min(), f.min())), float(max(t.max(), f.max()))
        for i, (image, label) in enumerate(((t, "truth"), (f, "fit"))):
            shown = axes[i, j].imshow(image, vmin=lo, vmax=hi, cmap="magma")
            axes[i, j].set_title(f"{name} {label}", fontsize=9)
            fig.colorbar(shown, ax=axes[i, j], fraction=0.046)
        d = f - t
        span = float(abs(d).max()) or 1.0
        shown = axes[2, j].imshow(d, vmin=-span, vmax=span, cmap="coolwarm")
        axes[2, j].set_title(f"{name} fit − truth", fontsize=9)
        fig.colorbar(shown, ax=axes[2, j], fraction=0.046)
    for ax in axes.ravel():
        ax.set_xticks([])
        ax.set_yticks([])
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def demo(
    out: Optional[Path] = typer.Option(None, "--out", "-o", help=f"Folder to create (default: ./{DEFAULT_FOLDER}, or -2, -3 … when taken)."),
    seed: int = typer.Option(0, "--seed", help="Seed of the simulated scene, flash, motion and noise."),
    size: int = typer.Option(256, "--size", help="Side of the calibrated cube in pixels (the rig's 256; 128 or 64 run faster)."),
    device: str = typer.Option("auto", "--device", help="Where the simulator and the fit run: auto, cpu or cuda."),
    scene: Optional[Path] = typer.Option(
        None, "--scene",
        help="Scene YAML (keys of configs/scene.yaml). Default: configs/scene.yaml without hairs (the acceptance scene: smooth "
             "variation, freckles, a scar, a vein).",
    ),
    physics: str = typer.Option(
        "diffusion", "--physics",
        help="The simulated skin's light transport: diffusion (the fit's own model) or transport (the Monte Carlo reference: "
             "the fit measured on physics it did not make; slow, use --size 32; --size 64 with --seed 61, 62 or 63 photographs "
             "the shipped render).",
    ),
    photons: Optional[int] = typer.Option(None, "--photons", help="--physics transport: photons per wavelength node of each band."),
    threads: Optional[str] = typer.Option(None, "--threads", help=THREADS_HELP),
) -> None:
    """Simulated capture → calibration → reconstruction → report, on embedded defaults.

    Example: skinlayers demo            (the rig's 256×256 cube; the README states its time, the first run longer)
             skinlayers demo --size 64  (a 64×64 cube, quicker)
             skinlayers demo --size 32 --physics transport --photons 200000   (the truth by Monte Carlo)
    """
    truth = _checked_options(out, size, device, scene, physics, photons)
    typer.echo(f"threads: {command_threads(threads).describe()}")
    folder = out if out is not None else fresh_folder(Path(DEFAULT_FOLDER))
    folder.mkdir(parents=True, exist_ok=True)
    session, calibrated, reconstruction = folder / "session", folder / "calibrated", folder / "reconstruction"
    kept = _shipped_renders(truth, seed, size, scene_given=scene is not None)
    rig, scene = _write_setup(folder, size, scene)
    times: dict[str, float] = {}

    def step(title: str) -> float:
        typer.secho(f"\n── {title} ──", bold=True, err=True)
        return time.perf_counter()

    t = step(f"1/4 capture (simulated rig, seed {seed}) → {session}")
    simulate_session(session, rig, scene, seed, device, truth, kept_renders=kept)
    times["capture_s"] = time.perf_counter() - t
    t = step(f"2/4 calibrate → {calibrated}")
    _calibrate(session, calibrated)
    times["calibrate_s"] = time.perf_counter() - t
    t = step(f"3/4 reconstruct → {reconstruction}")
    _reconstruct(calibrated / CUBE_NAME, reconstruction, device, len(rig.bands))
    times["reconstruct_s"] = time.perf_counter() - t
    t = step("4/4 report: the fit against the simulation's truth")
    accuracy = accuracy_against_truth(session, reconstruction, calibrated / CUBE_NAME)
    accuracy["times_s"] = {k: round(v, 1) for k, v in times.items()}
    (folder / "accuracy.json").write_text(json.dumps(accuracy, indent=2))
    _figure(session, reconstruction, folder / "truth_vs_fit.png")
    _print_accuracy(accuracy)
    _print_folder(folder, session, calibrated / CUBE_NAME, reconstruction, times)


def _write_setup(folder: Path, size: int, scene: Path | None):
    """The rig at ``size`` and the scene (the demo's where none is given), written into ``folder`` as
    rig.yaml and scene.yaml; returns the rig and the scene file."""
    import yaml  # noqa: PLC0415

    from .analyses.truths import demo_scene, session_rig  # noqa: PLC0415

    rig = session_rig(size)
    (folder / "rig.yaml").write_text(yaml.safe_dump(rig.model_dump(mode="json"), sort_keys=False))
    if scene is None:
        scene = folder / "scene.yaml"
        scene.write_text(yaml.safe_dump(demo_scene(), sort_keys=False))
    return rig, scene


def _shipped_renders(truth: dict, seed: int, size: int, scene_given: bool) -> dict | None:
    """With ``--physics transport`` on the demo's scene: the shipped Monte Carlo of this seed and size
    (``skinlayers.analyses.truths``), photographed anew instead of walking the photons again; else None. Sets
    ``truth["photons"]`` to the shipped render's, which the session's truth record then states."""
    if truth.get("physics") != "transport" or scene_given:
        return None
    from .analyses.truths import shipped_session  # noqa: PLC0415

    shipped = shipped_session(seed, size, truth.get("photons"))
    if shipped is None:
        return None
    record, kept = shipped
    truth["photons"] = record["photons_per_node"]
    typer.echo(f"the skin: the shipped Monte Carlo render of seed {seed} ({record['photons_per_node']:,} photons a node, "
               f"made in {record['seconds']:.0f} s), photographed anew", err=True)
    return kept


def _checked_options(out: Path | None, size: int, device: str, scene: Path | None, physics: str,
                     photons: int | None) -> dict:
    """The demo's options checked before any folder is made; the simulation's truth overrides."""
    from .acquire.simulator.simulation_settings import truth_overrides  # noqa: PLC0415

    if size < 16 or size % 8:
        raise InputError(f"--size {size}: expected a multiple of 8, at least 16 (e.g. 64, 128, 256)")
    if device not in ("cpu", "cuda", "auto"):
        raise InputError(f"--device {device!r}: expected cpu, cuda or auto")
    truth = truth_overrides(physics, photons)
    if scene is not None:  # a bad scene file is refused before any folder is made
        from .acquire.simulator.scene import load_scene  # noqa: PLC0415

        load_scene(scene)
    if out is not None:
        refuse_inside_session(out, "demo")
    if out is not None and out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise InputError(f"{out}: exists and is not empty; the demo writes into a fresh folder")
    return truth


def _print_folder(folder: Path, session: Path, cube: Path, reconstruction: Path, times: dict[str, float]) -> None:
    """Where the demo wrote what, and each step's time."""
    typer.echo("")
    typer.echo(f"demo folder:    {folder}")
    typer.echo(f"  session:      {session}   (raw DNG frames, manifest.json, truth/)")
    typer.echo(f"  cube:         {cube}   (+ calibration.json, contact_sheet.png)")
    typer.echo(f"  maps:         {reconstruction / 'maps.exr'}   (+ fit.json, report.png)")
    typer.echo(f"  accuracy:     {folder / 'accuracy.json'}, {folder / 'truth_vs_fit.png'}")
    typer.echo("times: " + ", ".join(f"{k[:-2]} {v:.0f} s" for k, v in times.items()))


def simulate_session(session: Path, rig, scene: Path, seed: int, device: str = "auto", truth: dict | None = None,
                     kept_renders: dict | None = None, simulation: Path | None = None) -> None:
    """A simulated session on the instant simulated wheel, its truth beside the frames (``truth``: the
    simulation's ``truth`` overrides, e.g. ``{"physics": "transport", "photons": 300_000}``; ``kept_renders``:
    the skin as rendered earlier with those settings, ``SimulatedBench.band_renders``, photographed anew;
    ``simulation``: a simulation settings file, None for the embedded one)."""
    from .acquire.cli import capture_progress  # noqa: PLC0415
    from .acquire.connect import open_devices  # noqa: PLC0415
    from .acquire.session import AutoOperator, run_session  # noqa: PLC0415

    with open_devices(rig, simulated=True, scene=scene, simulation=simulation, seed=seed, wheel_time_scale=0.0,
                      device=None if device == "auto" else device, truth=truth or {}) as devices, capture_progress() as progress:
        if kept_renders is not None:
            devices.bench.adopt_renders(kept_renders)
        run_session(session, devices.rig, devices.wheel, devices.camera, AutoOperator(devices.place), subject="demo",
                    site="simulated forearm", operator_name="skinlayers demo", simulated=True, notes=devices.notes,
                    software_version=software_version(), progress=progress)
    devices.bench.write_truth(session)
    typer.echo(f"session: {session} ({len(rig.bands)} bands; truth in {session / 'truth'})", err=True)


def _calibrate(session: Path, calibrated: Path) -> None:
    from .calibration import calibrate_session  # noqa: PLC0415
    from .calibration.cli import calibration_progress, print_summary  # noqa: PLC0415

    with calibration_progress() as progress:
        result = calibrate_session(session, calibrated, progress=progress)
    print_summary(result.report, result)


def _reconstruct(cube_path: Path, reconstruction: Path, device: str, bands: int) -> None:
    from .reconstruct import load_fit_settings, reconstruct_cube  # noqa: PLC0415
    from .reconstruct.cli import fit_progress, print_fit_summary  # noqa: PLC0415

    settings = load_fit_settings(None)
    with fit_progress(settings, bands) as on_event:
        fit, _ = reconstruct_cube(cube_path, reconstruction, settings, device=device, progress=on_event)
    print_fit_summary(fit, settings)


def _print_accuracy(accuracy: dict) -> None:
    from rich.console import Console  # noqa: PLC0415
    from rich.table import Table  # noqa: PLC0415

    table = Table(title=f"fit against truth ({accuracy['pixels']} px; {accuracy['high_residual_pixels']} high-residual px left out)")
    for column in ("parameter", "truth median", "fit median", "median error", "median σ", "truth within ±2σ"):
        table.add_column(column, justify="right")
    for name, p in accuracy["parameters"].items():
        error = f"{100 * p['median_error']:.1f}%" if p["error_kind"] == "relative" else f"{p['median_error']:.3f}"
        sigma = "" if p["sigma_median"] is None else f"{p['sigma_median']:.3g}"
        cover = "" if p.get("sigma_coverage") is None else f"{100 * p['sigma_coverage']:.0f}%"
        if not p.get("determined", True):
            sigma, cover = "undetermined", ""
        table.add_row(name, f"{p['truth_median']:.4g}", f"{p['fit_median']:.4g}", error, sigma, cover)
    console = Console()
    console.print(table)
    noise = accuracy.get("cube_noise_rms")
    console.print(f"residual RMS {accuracy['residual_rms']:.4f}" + (f"; the cube's own noise against the truth, RMS {noise:.4f}" if noise else ""))


def register(app: typer.Typer) -> None:
    app.command("demo")(demo)
