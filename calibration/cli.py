"""Commands calibration contributes to ``skinlayers``: calibrate."""

from __future__ import annotations

import json
from contextlib import contextmanager
from pathlib import Path
from typing import Optional

import typer

from .pipeline import calibrate_session, default_out_dir
from .settings import SettingsFileError, load_calibration_settings
from ..formats.threads import THREADS_HELP, command_threads

__all__ = ["calibration_progress", "print_summary", "register"]


def _parse_roi(text: str) -> list[int]:
    try:
        values = [int(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 4:
        raise SettingsFileError(f"--gray-card-roi {text!r}: expected x0,y0,x1,y1 in raw pixels, e.g. 40,220,110,290")
    return values


def calibrate(
    session: Path = typer.Argument(..., help="Session folder (holding manifest.json and the raw frames)."),
    out: Optional[Path] = typer.Option(None, "-o", "--out", help="Output folder (default: <SESSION>_calibrated beside the session)."),
    config: Optional[Path] = typer.Option(None, "--config", help="Calibration settings YAML (configs/calibration.yaml)."),
    no_dark_frame: bool = typer.Option(False, "--no-dark-frame", help="Subtract only the raw tags' black level."),
    no_flat_field: bool = typer.Option(False, "--no-flat-field", help="Divide by the reference's median, not pixel by pixel."),
    no_gray_card: bool = typer.Option(False, "--no-gray-card", help="No flash correction by the gray card (exposure ratio only)."),
    no_polarization: bool = typer.Option(False, "--no-polarization", help="Leave out the polarization factors."),
    no_spectralon: bool = typer.Option(False, "--no-spectralon-reflectance", help="Take the Spectralon as a perfect white."),
    no_align: bool = typer.Option(False, "--no-align", help="Do not align the bands to each other."),
    gray_card_roi: Optional[str] = typer.Option(None, "--gray-card-roi", help="x0,y0,x1,y1: the gray card in raw pixels."),
    force: bool = typer.Option(False, "--force", help="Replace an earlier calibration in the output folder."),
    as_json: bool = typer.Option(False, "--json", help="Print calibration.json (without the settings) instead of a table."),
    threads: Optional[str] = typer.Option(None, "--threads", help=THREADS_HELP),
) -> None:
    """Calibrate a session into a reflectance cube: cube.exr, calibration.json, contact_sheet.png.

    Example: skinlayers calibrate sessions/arm-01 -o cubes/arm-01
    """
    switches = {
        "dark_frame": no_dark_frame, "flat_field": no_flat_field, "gray_card": no_gray_card,
        "polarization": no_polarization, "spectralon_reflectance": no_spectralon, "align_bands": no_align,
    }
    overrides: dict = {key: False for key, off in switches.items() if off}
    if gray_card_roi is not None:
        overrides["gray_card_roi_px"] = _parse_roi(gray_card_roi)
    settings = load_calibration_settings(config, **overrides)

    command_threads(threads)
    with calibration_progress() as progress:
        result = calibrate_session(session, out if out is not None else default_out_dir(session), settings, progress, overwrite=force)
    report = result.report
    if as_json:
        typer.echo(json.dumps({k: v for k, v in report.items() if k != "settings"}))
        return
    print_summary(report, result)


@contextmanager
def calibration_progress():
    """A progress bar over the calibration's steps; yields the ``calibrate_session`` progress callback."""
    from rich.console import Console  # noqa: PLC0415
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn  # noqa: PLC0415

    with Progress(
        TextColumn("[bold]calibrate[/]"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
        TextColumn("{task.description}"), TimeElapsedColumn(), console=Console(stderr=True), transient=True,
    ) as bar:
        task = bar.add_task("reading the manifest", total=None)
        yield lambda done, total, message: bar.update(task, completed=done, total=total, description=message)


def print_summary(report: dict, result) -> None:
    """The calibration as a table of bands, its flags and its times."""
    from rich.console import Console  # noqa: PLC0415
    from rich.table import Table  # noqa: PLC0415

    console = Console()
    table = Table(title=f"{Path(report['session']).name}: {len(report['bands'])} bands → {result.out_dir}")
    for col in ("band nm", "flash ×", "shift px (cube)*", "SNR", "saturated", "under-exp.", "median R"):
        table.add_column(col, justify="right")
    for b in report["bands"]:
        dx, dy = b["alignment_shift_px"]
        table.add_row(
            f"{b['wavelength_nm']:g}",
            f"{b['flash_factor']:.3f}",
            "—" if dx is None else f"{dx:+.2f}, {dy:+.2f}" + (" applied" if b["alignment_applied"] else ""),
            "—" if b["snr"] is None else f"{b['snr']:.0f}",
            f"{b['saturated_fraction']:.2%}",
            f"{b['underexposed_fraction']:.2%}",
            "—" if b["median_reflectance"] is None else f"{b['median_reflectance']:.3f}",
        )
    console.print(table)
    shift = report["settings"]["align_min_shift_px"]
    console.print(f"* measured by ECC against {report['reference_band_nm']:g} nm; applied only from {shift:g} cube px on")
    for f in report["flags"]:
        console.print(f"[yellow]flag[/] {f['code']}: {f['message']}")
    t = report["timings_s"]
    console.print(
        f"{report['cube_px']}×{report['cube_px']} px at {report['mm_per_pixel'] * 1000:.1f} µm, "
        f"{report['mask_valid_fraction']:.0%} valid, {len(report['flags'])} flag(s), {t['total']:.1f} s "
        f"(window {t.get('window', 0):.1f} s, align {t.get('align', 0):.1f} s); "
        f"{result.cube_path.name}, {result.report_path.name}, {result.contact_sheet_path.name} in {result.out_dir}"
    )


def register(app: typer.Typer) -> None:
    app.command("calibrate")(calibrate)
