"""Commands acquisition contributes to ``skinlayers``: capture."""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Optional

import typer

__all__ = ["register"]


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version  # noqa: PLC0415

    try:
        return version("skinlayers")
    except PackageNotFoundError:
        return "0+unknown"


class _PromptingOperator:
    """Asks the person at the rig (``--yes`` answers for them); tells the simulated bench, if any."""

    def __init__(self, assume_yes: bool, bench=None) -> None:
        self.assume_yes, self.bench = assume_yes, bench

    def place(self, target: str, instruction: str) -> None:
        if self.bench is not None:
            self.bench.set_target(target)
        if self.assume_yes:
            typer.echo(f"operator: {instruction} (--yes)", err=True)
            return
        if not sys.stdin.isatty():
            raise ValueError(f"the session needs the operator to act ({instruction}); "
                             "run it at a terminal, or pass --yes to answer prompts automatically")
        if not typer.confirm(f"{instruction} Ready?", default=True):
            raise KeyboardInterrupt


def capture(
    out: Path = typer.Option(..., "--out", "-o", help="Session folder to create (never overwritten)."),
    sim: bool = typer.Option(False, "--sim", help="Everything simulated: wheel, camera, flash and a synthetic skin scene."),
    rig_file: Optional[Path] = typer.Option(None, "--rig", help="Rig YAML (bands, wheel port, camera); default: the embedded rig."),
    sim_camera: bool = typer.Option(False, "--sim-camera", help="Simulated camera with a real (or virtual) wheel on --wheel-port."),
    wheel_port: Optional[str] = typer.Option(None, "--wheel-port", help="Serial port of the filter wheel (overrides the rig's)."),
    scene: Optional[Path] = typer.Option(None, "--scene", help="Scene YAML for the simulated skin (default: configs/scene.yaml)."),
    sim_settings: Optional[Path] = typer.Option(None, "--sim-settings", help="Simulation YAML (sensor, optics; default: configs/simulation.yaml)."),
    seed: int = typer.Option(0, "--seed", help="Seed of the simulated scene, noise, flash and motion."),
    resume: bool = typer.Option(False, "--resume", help="Continue the session in --out, taking only the frames it lacks."),
    yes: bool = typer.Option(False, "--yes", "-y", help="Answer operator prompts automatically."),
    subject: str = typer.Option("", "--subject", help="Subject identifier recorded in the manifest."),
    site: str = typer.Option("", "--site", help="Body site recorded in the manifest (e.g. 'interior forearm')."),
    operator: str = typer.Option("", "--operator", help="Operator recorded in the manifest."),
    wheel_speed: float = typer.Option(1.0, "--sim-wheel-time", help="Simulated wheel: move time scale (0: instant)."),
    device: str = typer.Option("auto", "--device", help="Where the simulator renders: auto, cpu or cuda."),
) -> None:
    """Capture a session: a black frame, a Spectralon reference per band, the skin at every band.

    Examples:
      skinlayers capture --sim --out session1
      skinlayers capture --rig my_rig.yaml --subject S01 --site "inner forearm" --out S01
      skinlayers capture --sim-camera --wheel-port /dev/pts/5 --out bench_test
      skinlayers capture --sim --out session1 --resume
    """
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn  # noqa: PLC0415

    from .manifest import read_manifest  # noqa: PLC0415
    from .rig import load_rig  # noqa: PLC0415
    from .session import run_session  # noqa: PLC0415

    modes = sum([sim, sim_camera])
    if modes > 1:
        raise ValueError("choose one of --sim and --sim-camera")
    if sim_camera and not (wheel_port or rig_file):
        raise ValueError("--sim-camera needs the wheel's serial port: --wheel-port PORT (or a --rig that names it)")
    if not resume and out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise ValueError(f"{out}: exists and is not empty; a session is never overwritten "
                         "(choose a new folder, or --resume to continue the session in it)")
    if resume and not (out / "manifest.json").exists():
        raise ValueError(f"{out}: no session to resume (no manifest.json)")
    if resume and rig_file is None:
        rig = read_manifest(out).rig_config()
        simulated = read_manifest(out).simulated
        sim = sim or (simulated and not sim_camera)
    else:
        overrides = {}
        if sim or sim_camera:
            overrides["camera"] = {"driver": "simulated"}
        if wheel_port:
            overrides["wheel"] = {"port": wheel_port}
        rig = load_rig(rig_file, **overrides)
    bench = wheel = camera = None
    notes: dict = {}
    try:
        if sim or sim_camera or rig.camera.driver == "simulated":
            from .scene import load_scene  # noqa: PLC0415
            from .simdevices import SimulatedCamera, SimulatedWheel  # noqa: PLC0415
            from .simulated import SimulatedBench  # noqa: PLC0415
            from .simulation_settings import load_simulation_settings  # noqa: PLC0415

            dev = None if device == "auto" else device
            bench = SimulatedBench(rig, load_scene(scene), load_simulation_settings(sim_settings), seed, device=dev)
            rig = bench.rig_as_used()
            notes = {"seed": seed, "scene": str(scene or "configs/scene.yaml (embedded)"),
                     "simulation": str(sim_settings or "configs/simulation.yaml (embedded)")}
        if sim:
            wheel = SimulatedWheel(rig.wheel.position_count, time_scale=wheel_speed)
        else:
            from .fw102c import FW102C  # noqa: PLC0415

            port = wheel_port or rig.wheel.port
            if not port:
                raise ValueError("no filter wheel port: set wheel.port in the rig file or pass --wheel-port")
            wheel = FW102C.open(port, rig.wheel)
        if bench is not None:
            camera = SimulatedCamera(bench, wheel)
        else:
            from .gphoto import GPhotoCamera  # noqa: PLC0415

            camera = GPhotoCamera(rig.camera)
        typer.echo(f"wheel:  {wheel.identify()}", err=True)
        typer.echo(f"camera: {camera.identify()}", err=True)
        start = time.perf_counter()
        with Progress(TextColumn("{task.description:<22}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                      transient=False) as bar:
            task = bar.add_task("capture", total=1)

            def progress(done: int, total: int, label: str) -> None:
                bar.update(task, completed=done, total=total, description=label)

            summary = run_session(out, rig, wheel, camera, _PromptingOperator(yes, bench), resume=resume, subject=subject,
                                  site=site, operator_name=operator, simulated=bench is not None, notes=notes,
                                  software_version=_version(), progress=progress)
        if bench is not None and not (out / "truth" / "reflectance.exr").exists():
            typer.echo("writing the simulation's truth …", err=True)
            bench.write_truth(out)
    except KeyboardInterrupt:
        typer.echo(f"interrupted: the session in {out} is consistent; continue it with --resume", err=True)
        raise typer.Exit(130) from None
    finally:
        for device_ in (camera, wheel):
            if device_ is not None:
                device_.close()
    bands = ", ".join(f"{b:g}" for b in summary.bands_nm)
    exposures = sorted({(b.iso, b.shutter_s, b.aperture_f) for b in rig.bands})
    typer.echo(f"session: {out}")
    typer.echo(f"frames:  {summary.frames_taken} taken now, {summary.frames_before} before, {summary.frames_total} in all "
               f"(1 black, {len(rig.bands)} references, {len(rig.bands)} skin)")
    typer.echo(f"bands:   {bands} nm")
    typer.echo("exposure: " + "; ".join(f"ISO {i}, {s:g} s, f/{a:g}" for i, s, a in exposures))
    typer.echo(f"time:    {time.perf_counter() - start:.1f} s")
    if bench is not None:
        typer.echo(f"truth:   {out / 'truth'}")
    typer.echo(f"next:    skinlayers calibrate {out}")


def example_maps(
    out: Path = typer.Argument(..., help="Maps file to write (OpenEXR, the renderer's map format)."),
    size: int = typer.Option(256, "--size", help="Pixels per side."),
    mm_per_pixel: float = typer.Option(7.5 / 256, "--mm-per-pixel", help="Pixel size in mm."),
    seed: int = typer.Option(0, "--seed", help="Seed of the scene's variation, freckles, scar, veins and hairs."),
    scene: Optional[Path] = typer.Option(None, "--scene", help="Scene YAML (default: configs/scene.yaml)."),
) -> None:
    """Write a synthetic patch — the simulator's scene: smooth variation, freckles, a scar, veins, hairs.

    Example: skinlayers example-maps maps.exr && skinlayers render maps.exr --light window:5 -o out
    """
    import torch  # noqa: PLC0415

    from ..model.maps_io import write_maps  # noqa: PLC0415
    from .scene import SkinScene, load_scene  # noqa: PLC0415

    if not 8 <= size <= 4096:
        raise ValueError("--size must be 8–4096 pixels")
    if not 0 < mm_per_pixel < 10:
        raise ValueError("--mm-per-pixel must be a pixel size in mm (0–10)")
    wavelengths = torch.arange(400.0, 701.0, 25.0, dtype=torch.float64)  # veins and hairs, interpolated between
    maps = SkinScene(load_scene(scene), seed).maps(mm_per_pixel, size, wavelengths)
    write_maps(out, maps, attributes={"software": "skinlayers example-maps", "seed": str(seed)})
    typer.echo(f"wrote {out}: {size}×{size} px, {size * mm_per_pixel:.2f} mm across")


def register(app: typer.Typer) -> None:
    app.command("capture")(capture)
    app.command("example-maps")(example_maps)
