"""Commands reconstruction contributes to ``skinlayers``: fit-spectrum."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Optional

import torch
import typer

from ..model import PARAMETER_NAMES, SkinModel, load_model_settings
from ..model.cli import parse_wavelengths
from .spectra_io import read_spectra_csv
from .spectrum_fit import fit_spectra

__all__ = ["register"]


def fit_spectrum(
    file: Path = typer.Argument(..., help="CSV: wavelength_nm, then one column of reflectance (0–1) per spectrum."),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON object."),
    wavelength_range: str = typer.Option("400:700", "--range", help="lo:hi in nm, the samples used (within 380–800)."),
    free_scale: bool = typer.Option(False, "--free-scale", help="Fit a radiometric scale per spectrum too."),
    specular_included: bool = typer.Option(
        False, "--specular-included", help="The data include the surface's specular reflection (sphere, SCI)."
    ),
    plot: Optional[Path] = typer.Option(None, "--plot", help="Write a figure of measured against fitted spectra."),
    config: Optional[Path] = typer.Option(None, "--config", help="Model settings YAML."),
) -> None:
    """Fit C_m, β_m, C_he, C_bc, C_hd to measured reflectance spectra (homogeneous model, one batched fit).

    Example: skinlayers fit-spectrum tests/data/nist_skin_reflectance_forearm_avg_370-830nm.csv --json
    """
    settings = load_model_settings(config)
    lo_hi = wavelength_range.split(":")
    try:
        lo, hi = (float(v) for v in lo_hi)
    except ValueError:
        raise ValueError(f"--range {wavelength_range!r}: expected lo:hi in nm, e.g. 400:700") from None
    if not (380.0 <= lo < hi <= 800.0):
        raise ValueError(f"--range {wavelength_range!r}: must lie within 380–800 nm with lo < hi")
    data = read_spectra_csv(file).select(lo, hi)
    start = time.perf_counter()
    fit = fit_spectra(
        data.reflectance, data.wavelength_nm, SkinModel(settings), free_scale=free_scale, specular_included=specular_included
    )
    seconds = time.perf_counter() - start
    rms = fit.rms_residual
    spectra = []
    for b, name in enumerate(data.names):
        entry = {
            "name": name,
            "params": {n: float(getattr(fit.params, n)[b]) for n in PARAMETER_NAMES},
            "rms_residual": float(rms[b]),
            "at_bound": fit.at_bound[b],
            "converged": bool(fit.converged[b]),
        }
        if free_scale:
            entry["scale"] = float(fit.scale[b])
        spectra.append(entry)
    summary = {
        "count": len(spectra),
        "median_rms_residual": float(rms.median()),
        "worst_rms_residual": float(rms.max()),
        "worst": data.names[int(rms.argmax())],
        "wavelength_range_nm": [float(data.wavelength_nm[0]), float(data.wavelength_nm[-1])],
        "samples": int(data.wavelength_nm.numel()),
        "free_scale": free_scale,
        "specular_included": specular_included,
        "seconds": round(seconds, 3),
    }
    if plot is not None:
        _plot_fits(data.names, data.wavelength_nm, data.reflectance, fit.fitted, rms, plot)
    if as_json:
        typer.echo(json.dumps({"spectra": spectra, "summary": summary}))
        return
    from rich.console import Console  # noqa: PLC0415
    from rich.table import Table  # noqa: PLC0415

    table = Table(title=f"fit-spectrum: {file}")
    table.add_column("spectrum")
    for n in PARAMETER_NAMES:
        table.add_column(n, justify="right")
    if free_scale:
        table.add_column("scale", justify="right")
    table.add_column("RMS", justify="right")
    table.add_column("at bound")
    for s in spectra:
        row = [s["name"], *(f"{s['params'][n]:.4g}" for n in PARAMETER_NAMES)]
        if free_scale:
            row.append(f"{s['scale']:.3f}")
        row += [f"{s['rms_residual']:.4f}", ", ".join(s["at_bound"])]
        table.add_row(*row)
    console = Console()
    console.print(table)
    console.print(
        f"{summary['count']} spectra, {summary['samples']} samples each ({lo:g}–{hi:g} nm): RMS residual median "
        f"{summary['median_rms_residual']:.4f}, worst {summary['worst_rms_residual']:.4f} ({summary['worst']}); "
        f"{seconds:.2f} s"
    )
    if plot is not None:
        console.print(f"figure: {plot}")


def _plot_fits(names, wavelength_nm, measured, fitted, rms, path: Path) -> None:
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
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def register(app: typer.Typer) -> None:
    app.command("fit-spectrum")(fit_spectrum)

