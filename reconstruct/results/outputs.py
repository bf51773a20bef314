"""What a fit leaves on disk: ``maps.exr``, ``fit.json``, ``report.png`` and ``fit_settings.yaml``.

``maps.exr`` is the renderer's map format (``model/maps_io.write_maps``: C_m, β_m, C_he, C_bc, C_hd and
``mm_per_pixel``) plus ``residual_rms``, one ``res_<nm>`` per band (fitted − measured reflectance
factor), ``flags`` (bit field, meanings in the header attribute ``flag_bits`` and in ``fit.json``) and
``sigma_<param>`` (one standard deviation per parameter, NaN where the pixel was not in the loss).
``fit_settings.yaml`` is the resolved settings: ``skinlayers reconstruct --config`` on it re-makes the fit.

``reconstruct_cube`` is the whole job the command runs: the output folder claimed before the fit
(``formats.outputs``: never inside a session, nothing replaced without ``force``, one run at a time),
the fit, the four files written into its staging area and moved into place, ``fit.json`` last.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Callable

import torch
import yaml

from ...formats.foreign.cubes import read_cube_file
from ...formats.files import atomic_write
from ...formats.outputs import claim_outputs
from ...formats.version import software_version
from ...model import PARAMETER_NAMES
from ...model.patch.maps_io import write_maps
from ..diagnosis.checks import FLAG_BITS
from ..mapfit.fit import MapFit, fit_cube
from ..settings import FitSettings
from .stats import correlations, pca_explained, residual_stats, trimmed_stats
from ..levels.unknowns import near_bound

__all__ = ["MARKER", "OUTPUT_NAMES", "fit_summary", "reconstruct_cube", "write_outputs"]

#: A map resting at a bound of its range (``at_bound_fraction``) on at least this share of the visible
#: pixels is reported undetermined in ``fit.json``: its value is the bound's, and its σ (the noise's
#: share of a free parameter's error) says nothing of its error (the demo's carotene, at its lower bound
#: on every pixel: docs/reconstruct.md, "From reconstruct/results/outputs.py").
UNDETERMINED_AT_BOUND_SHARE = 0.5
#: What a fit writes; ``fit.json`` last: its presence marks a complete reconstruction.
MARKER = "fit.json"
OUTPUT_NAMES = ("maps.exr", "fit_settings.yaml", "report.png", MARKER)


def fit_summary(fit: MapFit, settings: FitSettings, source: str = "") -> dict:
    """Everything ``fit.json`` holds, as a JSON-able dict."""
    visible = (fit.flags & (1 << FLAG_BITS["masked"])) == 0
    params = torch.stack([getattr(fit.maps, n)[0] for n in PARAMETER_NAMES])[:, visible]
    sigma = fit.sigma[:, visible]
    wl = [float(w) for w in fit.wavelength_nm.tolist()]
    used = [bool(u) for u in fit.checks.bands_used.tolist()]
    flags = {name: int(((fit.flags >> bit) & 1).sum()) for name, bit in FLAG_BITS.items()}
    per_param = _parameter_stats(params, sigma, settings.at_bound_fraction)
    return {
        "software_version": software_version(),
        "input": source,
        "shape": list(fit.residual_rms.shape),
        "wavelengths_nm": wl,
        "mm_per_pixel": fit.maps.mm_per_pixel,
        "view_angle_deg": fit.view_angle_deg,
        "view_angle_source": fit.view_angle_source,
        "band_fwhm_nm": [float(w) for w in fit.band_fwhm_nm.tolist()],
        "band_fwhm_source": fit.band_fwhm_source,
        "band_weight": None if fit.band_weight is None else [round(float(w), 4) for w in fit.band_weight.tolist()],
        "method": settings.method,
        "start": settings.start,
        "scale": fit.scale,
        "map_grids": fit.levels[-1]["map_grids"] if fit.levels else None,
        "maps_at_bound": fit.maps_at_bound,
        "grid_choice": fit.grid_choice,
        "forward_choice": fit.forward_choice,
        "absorbers": fit.absorbers,
        "uncertainty": fit.uncertainty,
        "converged": all(level["converged"] for level in fit.kept_levels),
        "iterations": sum(level["iterations"] for level in fit.kept_levels),
        "levels": fit.levels,
        "time": {"cpu_s": round(fit.cpu_s, 3), "wall_s": round(fit.wall_s, 3), "renders": fit.counter.as_dict()},
        "data_checks": {
            "notes": fit.checks.notes,
            "warnings": fit.checks.warnings,
            "excluded_bands": fit.checks.excluded_bands,
            "saturated_pixels": int(fit.checks.saturated.sum()),
            "cube_masked_pixels": int(fit.checks.cube_masked.sum()),
            "band_bias": fit.band_bias,
            "residual_over_noise": fit.residual_over_noise if math.isfinite(fit.residual_over_noise) else None,
            "sigma_median": fit.sigma_median,
            "hairs": fit.hairs,
            "structure": fit.structure,
        },
        "flags": {"bits": FLAG_BITS, "counts": flags},
        "residual": residual_stats(fit.residual[:, visible], fit.residual_rms[visible], wl, used),
        "parameters": per_param,
        "correlations": correlations(params),
        "pca": pca_explained(params),
        "history": [[round(t, 3), loss, level] for t, loss, level in fit.history],
        "settings": settings.model_dump(mode="json"),
    }


def _parameter_stats(params: torch.Tensor, sigma: torch.Tensor, at_bound_fraction: float) -> dict[str, dict]:
    """Per map: trimmed statistics of ``params`` ``(N_PARAMS, pixels)``, the median σ, and whether the
    data determine it (not resting at a bound of its range)."""
    per_param = {}
    at_bound = near_bound(params, at_bound_fraction)  # (N_PARAMS, visible pixels)
    for i, n in enumerate(PARAMETER_NAMES):
        entry = trimmed_stats(params[i])
        entry["sigma_median"] = float(sigma[i].median())
        share = float(at_bound[i].double().mean()) if at_bound.shape[1] else 0.0
        entry["determined"] = share < UNDETERMINED_AT_BOUND_SHARE
        if not entry["determined"]:
            entry["undetermined_because"] = (
                f"it rests at a bound of its range on {share:.0%} of the pixels: the data push it past the model's range, "
                "so the value is the bound's and sigma does not describe its error")
        per_param[n] = entry
    return per_param


def reconstruct_cube(
    cube_path: str | Path, out_dir: str | Path, settings: FitSettings, *, device: str = "auto", force: bool = False,
    progress: Callable | None = None, mm_per_pixel: float | None = None,
) -> tuple[MapFit, dict[str, Path]]:
    """Fit the cube at ``cube_path`` (``cube.exr`` or any format of ``formats.foreign.cubes``; ``mm_per_pixel``
    where that file does not say it) and write the outputs into ``out_dir``; the fit and the files' final
    paths by kind. ``progress``: ``fit_cube``'s callback."""
    out = Path(out_dir)
    with claim_outputs(out, OUTPUT_NAMES, force=force, marker=MARKER, what="reconstruction") as staging:
        cube = read_cube_file(cube_path, mm_per_pixel)
        fit = fit_cube(cube, settings, device=device, progress=progress)
        written = write_outputs(fit, settings, staging.staging, source=str(cube_path))
    return fit, {kind: out / path.name for kind, path in written.items()}


def write_outputs(fit: MapFit, settings: FitSettings, out_dir: str | Path, source: str = "", measured: torch.Tensor | None = None) -> dict[str, Path]:
    """Write the four files into ``out_dir`` (created); returns their paths by kind."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    extra: dict[str, torch.Tensor] = {"residual_rms": fit.residual_rms, "flags": fit.flags.to(torch.float32)}
    for j, w in enumerate(fit.wavelength_nm.tolist()):
        extra[f"res_{w:g}"] = fit.residual[j]
    for i, n in enumerate(PARAMETER_NAMES):
        extra[f"sigma_{n}"] = fit.sigma[i]
        extra[f"sigma_noise_{n}"] = fit.sigma_noise[i]
    maps_path = write_maps(
        out / "maps.exr", fit.maps.to(device="cpu"), {k: v.detach().cpu() for k, v in extra.items()},
        {"wavelengths_nm": [float(w) for w in fit.wavelength_nm], "scale": float(fit.scale), "method": settings.method,
         "software_version": software_version(), "flag_bits": json.dumps(FLAG_BITS)},
    )
    settings_path = out / "fit_settings.yaml"
    settings_path.write_text(
        "# Resolved fit settings of this run: `skinlayers reconstruct CUBE --config fit_settings.yaml` re-makes it.\n"
        + yaml.safe_dump(settings.model_dump(mode="json"), sort_keys=False)
    )
    report_path = out / "report.png"
    from .report import plot_report  # noqa: PLC0415 (matplotlib only when a report is written)

    summary = fit_summary(fit, settings, source)
    undetermined = {n: "at its bound" for n, entry in summary["parameters"].items() if not entry.get("determined", True)}
    plot_report(fit, measured if measured is not None else fit.image - fit.residual, report_path, undetermined)
    # fit.json last and atomically: its presence says the outputs are complete (the CLI keys on it)
    json_path = atomic_write(out / "fit.json", json.dumps(summary, indent=1, allow_nan=True).encode())
    return {"maps": maps_path, "fit": json_path, "settings": settings_path, "report": report_path}
