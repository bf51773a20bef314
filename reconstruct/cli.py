"""Commands reconstruction contributes to ``skinlayers``: fit-spectrum, reconstruct."""

from __future__ import annotations

import json
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Optional

import torch
import typer

from ..formats.cube import CUBE_NAME, calibrated_dir, reconstruction_dir
from ..formats.errors import InputError
from ..formats.outputs import check_outputs, write_file
from ..model import PARAMETER_NAMES, SkinModel, load_model_settings
from .spectrum.spectra_io import read_spectra_csv
from .spectrum.spectrum_fit import METHODS
from .spectrum.spectrum_models import MODEL_CHOICES, candidate_label, select_spectrum_models, spectrum_candidates
from ..formats.threads import THREADS_HELP, command_threads

__all__ = ["fit_progress", "print_fit_summary", "register", "resolve_cube_path"]


def fit_spectrum(
    file: Path = typer.Argument(..., help="CSV: wavelength_nm, then one column of reflectance (0–1) per spectrum."),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON object."),
    wavelength_range: str = typer.Option("400:700", "--range", help="lo:hi in nm, the samples used (within 380–800)."),
    free_scale: bool = typer.Option(False, "--free-scale", help="Fit a radiometric scale per spectrum too."),
    specular_included: bool = typer.Option(
        False, "--specular-included", help="The data include the surface's specular reflection (sphere, SCI)."
    ),
    method: str = typer.Option(
        "exact", "--method", help="exact: iterate on the model itself; tables: on its tabulated totals (faster, same residual)."
    ),
    model_choice: str = typer.Option(
        "auto", "--model",
        help="auto: per spectrum, free the epidermis's thickness, the dermal blood's oxygenation or the dermis's "
             "scattering where BIC says the spectrum supports it; paper: DWRR08's (five chromophores, free scale); "
             "fixed: the five chromophores; or a YAML file (free: [...], free_scale: ...).",
    ),
    noise: Optional[float] = typer.Option(
        None, "--noise", help="The measurement's noise σ (reflectance) for the criterion; default: from the residual."
    ),
    plot: Optional[Path] = typer.Option(None, "--plot", help="Write a figure of measured against fitted spectra."),
    force: bool = typer.Option(False, "--force", help="Replace the --plot file if it exists."),
    config: Optional[Path] = typer.Option(None, "--config", help="Model settings YAML."),
) -> None:
    """Fit C_m, β_m, C_he, C_bc, C_hd (and what each spectrum supports freeing) to measured reflectance
    spectra with the homogeneous model, all spectra in one batched fit.

    Example: skinlayers fit-spectrum tests/data/nist_skin_reflectance_forearm_avg_370-830nm.csv --json
    """
    settings = load_model_settings(config)
    lo, hi = _spectrum_options(wavelength_range, method, noise, model_choice)
    candidates, free_scale = spectrum_candidates(model_choice, free_scale, settings.profiles)
    if plot is not None:  # before the fit: a figure it could not write is refused now, not after it
        check_outputs(plot.parent, [plot.name], force=force, what="figure")
    data = read_spectra_csv(file).select(lo, hi)
    start = time.perf_counter()
    with _spectra_progress(len(candidates), "models") as progress:
        selection = select_spectrum_models(
            data.reflectance, data.wavelength_nm, SkinModel(settings), candidates=candidates, free_scale=free_scale,
            specular_included=specular_included, noise=noise, method=method, progress=progress,
        )
    seconds = time.perf_counter() - start
    spectra = _spectra_entries(data.names, selection, free_scale)
    summary = _spectra_summary(data, selection, {"free_scale": free_scale, "specular_included": specular_included,
                                                 "method": method, "model": model_choice}, seconds)
    if plot is not None:
        _plot_fits(data.names, data.wavelength_nm, data.reflectance, selection.fit.fitted, selection.fit.rms_residual, plot, force)
    if as_json:
        typer.echo(json.dumps({"spectra": spectra, "summary": summary}))
        return
    _print_spectra(file, spectra, summary, free_scale, (lo, hi), len(selection.candidates) > 1)
    if plot is not None:
        typer.echo(f"figure: {plot}")


def _spectrum_options(wavelength_range: str, method: str, noise: float | None, model_choice: str) -> tuple[float, float]:
    """``fit-spectrum``'s options checked; the wavelength range ``(lo, hi)`` nm."""
    lo_hi = wavelength_range.split(":")
    try:
        lo, hi = (float(v) for v in lo_hi)
    except ValueError:
        raise InputError(f"--range {wavelength_range!r}: expected lo:hi in nm, e.g. 400:700") from None
    if not (380.0 <= lo < hi <= 800.0):
        raise InputError(f"--range {wavelength_range!r}: must lie within 380–800 nm with lo < hi")
    if method not in METHODS:
        raise InputError(f"--method {method!r}: choose one of {', '.join(METHODS)}")
    if noise is not None and not noise > 0:
        raise InputError(f"--noise {noise}: must be a positive reflectance (e.g. 0.003)")
    if model_choice not in MODEL_CHOICES and not Path(model_choice).is_file():
        raise InputError(f"--model {model_choice!r}: choose one of {', '.join(MODEL_CHOICES)}, or give a YAML file")
    return lo, hi


def _spectra_entries(names: list[str], selection, free_scale: bool) -> list[dict]:
    """Per spectrum: its parameters, residual, bounds reached, convergence and model (the JSON's ``spectra``)."""
    fit = selection.fit
    spectra = []
    for b, name in enumerate(names):
        entry = {
            "name": name,
            "params": {n: float(getattr(fit.params, n)[b]) for n in PARAMETER_NAMES},
            "rms_residual": float(fit.rms_residual[b]),
            "at_bound": fit.at_bound[b],
            "converged": bool(fit.converged[b]),
            "model": _model_entry(selection, b),
        }
        if free_scale:
            entry["scale"] = float(fit.scale[b])
        spectra.append(entry)
    return spectra


def _spectra_summary(data, selection, options: dict, seconds: float) -> dict:
    """What the fit of every spectrum says at once: residuals, samples, the options, the models chosen."""
    rms = selection.fit.rms_residual
    return {
        "count": len(data.names),
        "median_rms_residual": float(rms.median()),
        "worst_rms_residual": float(rms.max()),
        "worst": data.names[int(rms.argmax())],
        "wavelength_range_nm": [float(data.wavelength_nm[0]), float(data.wavelength_nm[-1])],
        "samples": int(data.wavelength_nm.numel()),
        **options,
        "criterion": selection.criterion_name,
        "chosen": {candidate_label(c): int((selection.choice == j).sum()) for j, c in enumerate(selection.candidates)},
        "seconds": round(seconds, 3),
    }


def _print_spectra(file: Path, spectra: list[dict], summary: dict, free_scale: bool, lo_hi: tuple[float, float],
                   several_models: bool) -> None:
    """The fit-spectrum table (the first ``_TABLE_ROWS`` spectra) and its summary lines."""
    from rich.console import Console  # noqa: PLC0415
    from rich.table import Table  # noqa: PLC0415

    table = Table(title=f"fit-spectrum: {file}")
    table.add_column("spectrum")
    for n in PARAMETER_NAMES:
        table.add_column(n, justify="right")
    if free_scale:
        table.add_column("scale", justify="right")
    table.add_column("freed")
    table.add_column("RMS", justify="right")
    table.add_column("at bound")
    for s in spectra[:_TABLE_ROWS]:
        row = [s["name"], *(f"{s['params'][n]:.4g}" for n in PARAMETER_NAMES)]
        if free_scale:
            row.append(f"{s['scale']:.3f}")
        freed = s["model"]["freed"]
        row += [", ".join(f"{_SHORT[n]} {s['model']['constants'][n]:.3g}" for n in freed) or "—",
                f"{s['rms_residual']:.4f}", ", ".join(s["at_bound"])]
        table.add_row(*row)
    console = Console()
    console.print(table)
    if len(spectra) > _TABLE_ROWS:
        console.print(f"… and {len(spectra) - _TABLE_ROWS} more spectra (--json lists every one)")
    lo, hi = lo_hi
    console.print(
        f"{summary['count']} spectra, {summary['samples']} samples each ({lo:g}–{hi:g} nm): RMS residual median "
        f"{summary['median_rms_residual']:.4f}, worst {summary['worst_rms_residual']:.4f} ({summary['worst']}); "
        f"{summary['seconds']:.2f} s"
    )
    if several_models:
        counts = ", ".join(f"{label} {n}" for label, n in summary["chosen"].items() if n)
        console.print(f"models chosen ({summary['criterion']}): {counts} (--json says why, per spectrum)")


#: ``reconstruct --model`` → the fit settings it sets (over --config's): DWRR08's fit is the renderer
#: with every map per pixel and a free scale (§6.3–6.4).
MAP_MODELS = {
    "auto": {"forward": "auto"},
    "fixed": {"forward": "heterogeneous"},
    "paper": {"forward": "heterogeneous", "map_cell_mm": dict.fromkeys(PARAMETER_NAMES, 0.0), "free_scale": True},
}
#: Spectra the table shows; --json gives all.
_TABLE_ROWS = 200
#: The freed constants' names in the table.
_SHORT = {"epidermis_thickness_mm": "d_epi mm", "oxygenation_dermis": "γ_d", "dermis_scattering_ratio": "σs′ ratio"}


def _model_entry(selection, b: int) -> dict:
    """Spectrum ``b``'s model in fit-spectrum's JSON: what it freed, every constant's value, each
    candidate's criterion and RMS residual, and why the winner won."""
    return {
        "freed": selection.fit.freed[b],
        "constants": {n: float(v[b]) for n, v in selection.fit.constants.items()},
        "criterion": {candidate_label(c): float(selection.criterion[b, j]) for j, c in enumerate(selection.candidates)},
        "rms_residual": {candidate_label(c): float(selection.rms_residual[b, j]) for j, c in enumerate(selection.candidates)},
        "why": selection.reason(b),
    }


@contextmanager
def _spectra_progress(count: int, what: str = "spectra"):
    """A progress bar (over the models fitted, or the spectra); yields the callback."""
    from rich.console import Console  # noqa: PLC0415
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn  # noqa: PLC0415

    with Progress(TextColumn("fit-spectrum"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(), TextColumn("ETA"),
                  TimeRemainingColumn(), console=Console(stderr=True), transient=True) as bar:
        task = bar.add_task(what, total=count)
        yield lambda done, total: bar.update(task, completed=done, total=total)


def _plot_fits(names, wavelength_nm, measured, fitted, rms, path: Path, force: bool) -> None:
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    order = torch.argsort(rms)
    picks = [int(order[0]), int(order[len(order) // 2]), int(order[-1])] if len(order) >= 3 else [int(i) for i in order]
    fig, axes = plt.subplots(1, len(picks) + 1, figsize=(4 * (len(picks) + 1), 3.6))
    for ax, b in zip(axes, picks):
        ax.plot(wavelength_nm, measured[b], "k.", ms=3, label="measured")
        ax.plot(wavelength_nm, fitted[b], "r-", label="fit")
        ax.set_title(f"{names[b]}: RMS {float(rms[b]):.4f}", fontsize=9)
        ax.set_xlabel("wavelength (nm)")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("reflectance")
    axes[0].legend(fontsize=8)
    axes[-1].hist(rms.numpy(), bins=20, color="0.4")
    axes[-1].set_xlabel("RMS residual")
    axes[-1].set_title("all spectra", fontsize=9)
    fig.tight_layout()
    try:
        write_file(path, lambda p: fig.savefig(p, dpi=120, format="png"), force=force, what="figure")
    finally:
        plt.close(fig)


#: Iterations a level's pass usually takes, per method (only the ETA uses them; a level runs
#: 1 + robust_passes passes; fit.json's ``iterations_per_pass`` records what each one took).
_EXPECTED_ITERATIONS = {"gn-hom": 10, "gn": 20, "adam": 150, "paper-fd": 300}


def resolve_cube_path(source: Path) -> Path:
    """A cube file as given; a calibrated folder's ``cube.exr``; or a session folder's cube, which
    ``skinlayers calibrate`` writes beside it (``<SESSION>_calibrated/cube.exr``). Errors say what to do."""
    if source.is_dir():
        if (source / CUBE_NAME).is_file():
            return source / CUBE_NAME
        cube = calibrated_dir(source) / CUBE_NAME
        if not cube.exists():
            raise FileNotFoundError(
                f"{source}: no calibrated cube at {cube}; run `skinlayers calibrate {source}` first"
            )
        return cube
    if not source.exists():
        raise FileNotFoundError(f"{source}: no such session folder or cube file")
    return source


def default_reconstruction_dir(source: Path, cube_path: Path) -> Path:
    """``<SESSION>_reconstruction`` beside a session folder (the session is never written to), else
    ``reconstruction/`` beside the cube."""
    if source.is_dir() and not (source / CUBE_NAME).is_file():
        return reconstruction_dir(source)
    return cube_path.parent / "reconstruction"


def reconstruct(
    source: Path = typer.Argument(..., help="A session folder (uses SESSION_calibrated/cube.exr beside it), a calibrated folder, a cube.exr, "
                                            "or a reflectance cube from another camera: ENVI .hdr, multi-page .tif, .npz or .h5 (docs/formats.md)."),
    out: Optional[Path] = typer.Option(
        None, "-o", "--out", help="Output folder (default: SESSION_reconstruction beside a session, else reconstruction/ beside the cube)."
    ),
    config: Optional[Path] = typer.Option(None, "--config", help="Fit settings YAML (configs/fit.yaml lists every key)."),
    device: str = typer.Option("auto", "--device", help="cpu, cuda or auto (CUDA when available)."),
    method: Optional[str] = typer.Option(None, "--method", help="gn-hom (default), gn, adam or paper-fd (the paper's baseline)."),
    start: Optional[str] = typer.Option(None, "--start", help="homogeneous (default) or paper."),
    model_choice: Optional[str] = typer.Option(
        None, "--model",
        help="auto (default): each pixel's homogeneous model where the renderer says the scene's cross-talk is below "
             "the noise, else the renderer; fixed: always the renderer, maps on the settings' grids; paper: DWRR08's "
             "fit (the renderer, every map per pixel, a free scale).",
    ),
    force: bool = typer.Option(False, "--force", help="Overwrite the outputs of an earlier fit in the output folder."),
    mm_per_pixel: Optional[float] = typer.Option(None, "--mm-per-pixel", help="A cube from another camera: the pixel's side on the skin (mm), where its file does not say it."),
    threads: Optional[str] = typer.Option(None, "--threads", help=THREADS_HELP),
) -> None:
    """Fit chromophore maps to a reflectance cube by inverse rendering (DWRR08 §6.3).

    Writes maps.exr (C_m, beta_m, C_he, C_bc, C_hd, residuals, flags, sigma_*), fit.json, report.png and
    fit_settings.yaml. Example: skinlayers reconstruct my-session  (after skinlayers calibrate my-session)
    """
    from ..formats.foreign.cubes import read_cube_file  # noqa: PLC0415
    from .results.outputs import OUTPUT_NAMES, reconstruct_cube  # noqa: PLC0415
    from .settings import load_fit_settings  # noqa: PLC0415

    if device not in ("cpu", "cuda", "auto"):
        raise InputError(f"--device {device!r}: expected cpu, cuda or auto")
    if model_choice is not None and model_choice not in MAP_MODELS:
        raise InputError(f"--model {model_choice!r}: choose one of {', '.join(MAP_MODELS)}")
    settings = load_fit_settings(config, method=method, start=start, **MAP_MODELS.get(model_choice, {}))
    cube_path = resolve_cube_path(source)
    out_dir = out or default_reconstruction_dir(source, cube_path)
    check_outputs(out_dir, OUTPUT_NAMES, force=force, what="reconstruction")  # refused before any bar or work
    typer.echo(f"threads: {command_threads(threads).describe()}")
    bands = len(read_cube_file(cube_path, mm_per_pixel).header.wavelengths_nm)  # a file that cannot be fitted is refused here
    with fit_progress(settings, bands) as on_event:
        fit, paths = reconstruct_cube(cube_path, out_dir, settings, device=device, force=force, progress=on_event,
                                      mm_per_pixel=mm_per_pixel)
    print_fit_summary(fit, settings)
    for kind, path in paths.items():
        typer.echo(f"{kind}: {path}")


def print_fit_summary(fit, settings) -> None:
    """The fit in a few lines on stderr: size, scale, residual, iterations, time, notes and flags."""
    from rich.console import Console  # noqa: PLC0415

    console = Console(stderr=True)
    flags = {k: int(v) for k, v in _flag_counts(fit).items() if v}
    console.print(
        f"fit {fit.residual_rms.shape[0]}×{fit.residual_rms.shape[1]} px, {fit.wavelength_nm.numel()} bands, method {settings.method}: "
        f"scale {fit.scale:.4f}, residual RMS {_visible_rms(fit):.4f}, {sum(level['iterations'] for level in fit.kept_levels)} iterations, "
        f"{fit.wall_s:.1f} s"
    )
    if fit.forward_choice:
        console.print(f"forward model: {fit.forward_choice['chosen']} ({fit.forward_choice['reason']})")
    if fit.absorbers:
        console.print(f"absorbers: {fit.absorbers['reason']}")
    if fit.uncertainty and fit.uncertainty.get("crosstalk_measured"):
        rho = ", ".join(f"{n} {v:.2f}" for n, v in fit.uncertainty["crosstalk_ratio"].items())
        console.print(f"sigma: the noise's share widened by each map's own-pixel response (cross-talk ratio {rho}), the nodes' "
                      "by the residual's correlation in space and the spread between them")
    for note in fit.checks.notes:
        console.print(f"note: {note}")
    for what, source in (("camera angle", fit.view_angle_source), ("filter widths", fit.band_fwhm_source)):
        if source.startswith("not in"):
            console.print(f"note: {what} {source} (set view_angle_deg / band_fwhm_nm in --config if your rig differs)")
    for name, share in fit.maps_at_bound.items():
        console.print(f"note: {name} (on nodes) rests at a bound over {share:.0%} of the pixels (the data do not hold it there)")
    if flags:
        console.print("flagged pixels: " + ", ".join(f"{k} {v}" for k, v in flags.items()))


@contextmanager
def fit_progress(settings, bands: int):
    """A progress bar with an ETA over the fit's levels; yields the ``fit_cube`` progress callback."""
    from rich.console import Console  # noqa: PLC0415
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn  # noqa: PLC0415

    from .mapfit.fit import FitEvent  # noqa: PLC0415

    expected = _EXPECTED_ITERATIONS.get(settings.method, 20) * (1 + settings.robust_passes)
    with Progress(
        TextColumn("{task.description}"), BarColumn(), TextColumn("{task.percentage:>3.0f}%"),
        TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn(), console=Console(stderr=True), transient=False,
    ) as bar:
        task = bar.add_task("preparing", total=1.0)

        def on_event(event: FitEvent) -> None:
            if event.stage == "tables":
                bar.update(task, description=f"tables {event.level}/{event.levels} wavelengths (once, cached)")
                return
            if not event.pixels:
                return
            work = [p * expected for p in event.pixels]
            total = float(sum(work))
            base = float(sum(work[: event.level]))
            if event.stage == "fit":
                within = min(event.iteration, expected - 1) * event.pixels[event.level]
                rms = (2 * event.loss / max(event.pixels[event.level] * bands, 1)) ** 0.5
                bar.update(task, total=total, completed=base + within,
                           description=f"level {event.level + 1}/{event.levels} it {event.iteration} RMS {rms:.4f}")
            elif event.stage == "level":
                bar.update(task, total=total, completed=base + work[event.level])
            elif event.stage == "start":
                bar.update(task, total=total, completed=0.0, description=f"start: {settings.start}")
            elif event.stage == "final":
                bar.update(task, total=total, completed=total, description="residuals, flags, uncertainties")

        yield on_event


def _flag_counts(fit) -> dict[str, int]:
    from .diagnosis.checks import FLAG_BITS  # noqa: PLC0415

    return {name: int(((fit.flags >> bit) & 1).sum()) for name, bit in FLAG_BITS.items()}


def _visible_rms(fit) -> float:
    from .diagnosis.checks import FLAG_BITS  # noqa: PLC0415

    visible = ((fit.flags >> FLAG_BITS["masked"]) & 1) == 0
    used = fit.checks.bands_used
    return float(fit.residual[used][:, visible].pow(2).mean().sqrt())


def register(app: typer.Typer) -> None:
    app.command("fit-spectrum")(fit_spectrum)
    app.command("reconstruct")(reconstruct)

