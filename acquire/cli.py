"""Commands acquisition contributes to ``skinlayers``: capture."""

from __future__ import annotations

import sys
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Optional

import typer

from ..formats.errors import InputError
from ..formats.version import software_version
from ..formats.threads import THREADS_HELP, command_threads

__all__ = ["capture_progress", "register"]


class _PromptingOperator:
    """Asks the person at the rig (``--yes`` answers for them); places the target on a simulated bench."""

    def __init__(self, assume_yes: bool, devices) -> None:
        self.assume_yes, self.devices = assume_yes, devices

    def place(self, target: str, instruction: str) -> None:
        self.devices.place(target)
        if self.assume_yes:
            typer.echo(f"operator: {instruction} (--yes)", err=True)
            return
        if not sys.stdin.isatty():
            raise InputError(f"the session needs the operator to act ({instruction}); "
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
    physics: Optional[str] = typer.Option(
        None, "--physics", help="Simulated skin rendered by diffusion (the model) or transport (the Monte Carlo reference; slow: use a small cube)."),
    photons: Optional[int] = typer.Option(None, "--photons", help="--physics transport: photons per wavelength node of each band."),
    threads: Optional[str] = typer.Option(None, "--threads", help=THREADS_HELP),
) -> None:
    """Capture a session: a black frame, a Spectralon reference per band, the skin at every band.

    Examples:
      skinlayers capture --sim --out session1
      skinlayers capture --rig my_rig.yaml --subject S01 --site "inner forearm" --out S01
      skinlayers capture --sim-camera --wheel-port /dev/pts/5 --out bench_test
      skinlayers capture --sim --out session1 --resume
      skinlayers capture --sim --physics transport --photons 2000000 --rig small_rig.yaml --out mc_session
    """
    from .connect import open_devices  # noqa: PLC0415
    from .session import run_session  # noqa: PLC0415
    from .simulator.simulation_settings import truth_overrides  # noqa: PLC0415

    rig, sim = _session_rig(out, sim, sim_camera, rig_file, wheel_port, resume)
    command_threads(threads)
    truth = truth_overrides(physics, photons)
    start = time.perf_counter()
    try:
        with open_devices(rig, simulated=sim, scene=scene, simulation=sim_settings, seed=seed, wheel_time_scale=wheel_speed,
                          wheel_port=wheel_port, device=None if device == "auto" else device, truth=truth) as devices:
            typer.echo(f"wheel:  {devices.wheel.identify()}", err=True)
            typer.echo(f"camera: {devices.camera.identify()}", err=True)
            with capture_progress() as progress:
                summary = run_session(out, devices.rig, devices.wheel, devices.camera, _PromptingOperator(yes, devices), resume=resume,
                                      subject=subject, site=site, operator_name=operator, simulated=devices.simulated,
                                      notes=devices.notes, software_version=software_version(), progress=progress)
            if devices.bench is not None and not (out / "truth" / "reflectance.exr").exists():
                typer.echo("writing the simulation's truth …", err=True)
                devices.bench.write_truth(out)
    except KeyboardInterrupt:
        typer.echo(f"interrupted: the session in {out} is consistent; continue it with --resume", err=True)
        raise typer.Exit(130) from None
    _print_summary(out, devices, summary, time.perf_counter() - start)


def _session_rig(out: Path, sim: bool, sim_camera: bool, rig_file: Optional[Path], wheel_port: Optional[str], resume: bool):
    """The rig to capture with (a resumed session's own, else the file's with the options applied) and
    whether everything is simulated; refuses options that do not go together."""
    from ..formats.manifest import read_manifest  # noqa: PLC0415
    from ..formats.outputs import refuse_inside_session  # noqa: PLC0415
    from .hardware.rig import load_rig  # noqa: PLC0415

    if sim and sim_camera:
        raise InputError("choose one of --sim and --sim-camera")
    if not resume:
        refuse_inside_session(out.parent, "session")
    if sim_camera and not (wheel_port or rig_file):
        raise InputError("--sim-camera needs the wheel's serial port: --wheel-port PORT (or a --rig that names it)")
    if not resume and out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise InputError(f"{out}: exists and is not empty; a session is never overwritten "
                         "(choose a new folder, or --resume to continue the session in it)")
    if resume and not (out / "manifest.json").exists():
        raise InputError(f"{out}: no session to resume (no manifest.json)")
    if resume and rig_file is None:
        manifest = read_manifest(out)
        return manifest.rig_config(), sim or (manifest.simulated and not sim_camera)
    overrides: dict = {}
    if sim or sim_camera:
        overrides["camera"] = {"driver": "simulated"}
    if wheel_port:
        overrides["wheel"] = {"port": wheel_port}
    return load_rig(rig_file, **overrides), sim


@contextmanager
def capture_progress():
    """A progress bar over the session's frames; yields the ``progress(done, total, label)`` callback."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn  # noqa: PLC0415

    with Progress(TextColumn("{task.description:<22}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(), transient=False) as bar:
        task = bar.add_task("capture", total=1)
        yield lambda done, total, label: bar.update(task, completed=done, total=total, description=label)


def _print_summary(out: Path, devices, summary, seconds: float) -> None:
    rig = devices.rig
    bands = ", ".join(f"{b:g}" for b in summary.bands_nm)
    exposures = sorted({(b.iso, b.shutter_s, b.aperture_f) for b in rig.bands})
    typer.echo(f"session: {out}")
    typer.echo(f"frames:  {summary.frames_taken} taken now, {summary.frames_before} before, {summary.frames_total} in all "
               f"(1 black, {len(rig.bands)} references, {len(rig.bands)} skin)")
    typer.echo(f"bands:   {bands} nm")
    typer.echo("exposure: " + "; ".join(f"ISO {i}, {s:g} s, f/{a:g}" for i, s, a in exposures))
    typer.echo(f"time:    {seconds:.1f} s")
    if devices.bench is not None:
        typer.echo(f"truth:   {out / 'truth'}")
    typer.echo(f"next:    skinlayers calibrate {out}")


def example_maps(
    out: Path = typer.Argument(..., help="Maps file to write (OpenEXR, the renderer's map format)."),
    size: int = typer.Option(256, "--size", help="Pixels per side."),
    mm_per_pixel: float = typer.Option(7.5 / 256, "--mm-per-pixel", help="Pixel size in mm."),
    seed: int = typer.Option(0, "--seed", help="Seed of the scene's variation, freckles, scar, veins and hairs."),
    scene: Optional[Path] = typer.Option(None, "--scene", help="Scene YAML (default: configs/scene.yaml)."),
    force: bool = typer.Option(False, "--force", help="Replace OUT if it exists."),
) -> None:
    """Write a synthetic patch — the simulator's scene: smooth variation, freckles, a scar, veins, hairs.

    Example: skinlayers example-maps maps.exr && skinlayers render maps.exr --light window:5 -o out
    """
    import torch  # noqa: PLC0415

    from ..formats.maps import MAX_MM_PER_PIXEL, MIN_MM_PER_PIXEL  # noqa: PLC0415
    from ..formats.outputs import check_outputs, write_file  # noqa: PLC0415
    from ..model.patch.maps_io import write_maps  # noqa: PLC0415
    from .simulator.scene import SkinScene, load_scene  # noqa: PLC0415

    if not 8 <= size <= 4096:
        raise InputError("--size must be 8–4096 pixels")
    if not MIN_MM_PER_PIXEL <= mm_per_pixel < MAX_MM_PER_PIXEL:
        raise InputError(f"--mm-per-pixel must be a pixel size in mm ({MIN_MM_PER_PIXEL:g}–{MAX_MM_PER_PIXEL:g})")
    check_outputs(out.parent, [out.name], force=force, what="maps")
    wavelengths = torch.arange(400.0, 701.0, 25.0, dtype=torch.float64)  # veins and hairs, interpolated between
    maps = SkinScene(load_scene(scene), seed).maps(mm_per_pixel, size, wavelengths)
    write_file(out, lambda path: write_maps(path, maps, attributes={"software": "skinlayers example-maps", "seed": str(seed)}),
               force=force, what="maps")
    typer.echo(f"wrote {out}: {size}×{size} px, {size * mm_per_pixel:.2f} mm across")


def register(app: typer.Typer) -> None:
    app.command("capture")(capture)
    app.command("example-maps")(example_maps)
