"""Commands the model contributes to ``skinlayers``: spectrum, skin-types, tables."""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Optional

import torch
import typer
import yaml

from ..formats.errors import InputError
from ..formats.outputs import write_file
from .optics.colour import ColourConverter, ita_degrees
from .column.layered import SkinModel
from .optics.params import PARAMETER_NAMES, TABLE2, SkinParams
from .settings import ModelSettings, load_model_settings
from .transport import check_physics_options
from ..formats.threads import THREADS_HELP, command_threads

__all__ = ["COLOUR_WAVELENGTHS_NM", "parse_wavelengths", "register"]

#: Colour is always computed from the model's spectrum at these wavelengths, whatever is printed.
COLOUR_WAVELENGTHS_NM = torch.arange(380.0, 782.0, 2.0, dtype=torch.float64)
DEFAULT_PRESET = "III interior"
#: The most wavelengths a command renders or tabulates (380–800 nm every 0.2 nm).
MAX_WAVELENGTHS = 2101


def parse_wavelengths(text: str) -> torch.Tensor:
    """``start:stop:step`` (nm, stop included) or a comma list, e.g. ``400:700:5`` or ``450,550,650``."""
    text = text.strip()
    try:
        if ":" in text:
            parts = [float(p) for p in text.split(":")]
            if len(parts) != 3:
                raise ValueError
            start, stop, step = parts
            if not all(map(math.isfinite, parts)) or step <= 0 or stop < start:
                raise ValueError
            n = int(math.floor((stop - start) / step + 1e-9)) + 1
            values = [start + i * step for i in range(min(n, MAX_WAVELENGTHS + 1))]
        else:
            values = [float(p) for p in text.split(",") if p.strip()]
    except ValueError:
        raise InputError(
            f"--wavelengths {text!r}: expected start:stop:step (stop included, step > 0) or a comma list in nm"
        ) from None
    if not values:
        raise InputError("--wavelengths: no wavelengths given")
    if len(values) > MAX_WAVELENGTHS:
        raise InputError(f"--wavelengths {text!r}: more than {MAX_WAVELENGTHS} wavelengths (380–800 nm every 0.2 nm is the most)")
    if any(not math.isfinite(v) for v in values):
        raise InputError("--wavelengths: values must be finite numbers")
    if sorted(set(values)) != values:
        raise InputError("--wavelengths: values must increase")
    return torch.tensor(values, dtype=torch.float64)


def _params_from(preset: str, params_file: Optional[Path], overrides: dict[str, Optional[float]]) -> SkinParams:
    if preset not in TABLE2:
        raise InputError(f"--preset {preset!r}: unknown; choose one of: {', '.join(TABLE2)}")
    values: dict[str, object] = dict(TABLE2[preset])
    if params_file is not None:
        try:
            loaded = yaml.safe_load(Path(params_file).read_text())
        except OSError as exc:
            raise InputError(f"{params_file}: cannot read ({exc.strerror or exc})") from None
        except yaml.YAMLError as exc:
            raise InputError(f"{params_file}: not valid YAML/JSON ({exc})") from None
        if not isinstance(loaded, dict):
            raise InputError(f"{params_file}: expected a mapping of parameter names to values")
        unknown = sorted(set(loaded) - set(PARAMETER_NAMES))
        if unknown:
            raise InputError(f"{params_file}: unknown key(s) {', '.join(unknown)} (expected {', '.join(PARAMETER_NAMES)})")
        for k, v in loaded.items():
            if not isinstance(v, (int, float)) or isinstance(v, bool):
                raise InputError(f"{params_file}: {k} must be a number, got {v!r}")
        values.update(loaded)
    values.update({k: v for k, v in overrides.items() if v is not None})
    return SkinParams.from_mapping(values).validate()


def _spectrum_report(model: SkinModel, params: SkinParams, wavelengths: torch.Tensor, method: str, illuminant: str) -> dict:
    refl = model.diffuse_reflectance(params, wavelengths, method=method)
    colour = ColourConverter(COLOUR_WAVELENGTHS_NM, illuminant)
    dense = model.diffuse_reflectance(params, COLOUR_WAVELENGTHS_NM, method="exact")
    lab = colour.lab(dense)
    return {
        "wavelength_nm": [round(float(w), 6) for w in wavelengths],
        "reflectance": [float(r) for r in refl],
        "srgb": [float(c) for c in colour.srgb(dense)],
        "lab": [float(c) for c in lab],
        "ita_deg": float(ita_degrees(lab)),
        "params": {n: float(getattr(params, n)) for n in PARAMETER_NAMES},
        "illuminant": illuminant,
        "method": method,
    }


def _transport_spectrum_report(settings: ModelSettings, params: SkinParams, wavelengths: torch.Tensor, illuminant: str,
                               photons: Optional[int], seed: int) -> dict:
    """The spectrum by the Monte Carlo reference, its standard errors, and the colour of its samples."""
    from rich.progress import Progress  # noqa: PLC0415

    from .transport import TransportRenderer  # noqa: PLC0415

    with Progress(transient=True) as bar:
        task = bar.add_task("transport (Monte Carlo)", total=wavelengths.numel())
        totals = TransportRenderer(settings).totals(params, wavelengths, photons=photons, seed=seed,
                                                    progress=lambda done, total: bar.update(task, completed=done))
    refl = totals.reflectance
    report = {
        "wavelength_nm": [round(float(w), 6) for w in wavelengths], "reflectance": refl.tolist(), "std_error": totals.std_error.tolist(),
        "params": {n: float(getattr(params, n)) for n in PARAMETER_NAMES}, "illuminant": illuminant,
        "physics": "transport", "photons": totals.photons, "anisotropy": settings.transport.anisotropy,
    }
    if wavelengths.numel() >= 2:
        colour = ColourConverter(wavelengths, illuminant)
        lab = colour.lab(refl)
        report.update(srgb=[float(c) for c in colour.srgb(refl)], lab=[float(c) for c in lab], ita_deg=float(ita_degrees(lab)))
    return report


def _hex(rgb) -> str:
    return "#" + "".join(f"{int(round(255 * min(max(c, 0.0), 1.0))):02x}" for c in rgb)


def spectrum(
    C_m: Optional[float] = typer.Option(None, "--C_m", help="Melanin volume fraction (0–0.5)."),
    beta_m: Optional[float] = typer.Option(None, "--beta_m", help="Eumelanin share of the melanin (0–1)."),
    C_he: Optional[float] = typer.Option(None, "--C_he", help="Epidermal blood fraction (0–0.05)."),
    C_bc: Optional[float] = typer.Option(None, "--C_bc", help="β-carotene fraction (0–0.05)."),
    C_hd: Optional[float] = typer.Option(None, "--C_hd", help="Dermal blood fraction (0–0.1)."),
    preset: str = typer.Option(DEFAULT_PRESET, "--preset", help="Table 2 row giving the parameters not set."),
    params_file: Optional[Path] = typer.Option(None, "--params", help="YAML/JSON file of parameters."),
    wavelengths: str = typer.Option("400:700:5", "--wavelengths", help="start:stop:step (nm, stop included) or a comma list."),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON object."),
    plot: Optional[Path] = typer.Option(None, "--plot", help="Write a figure of the spectrum and its colour."),
    force: bool = typer.Option(False, "--force", help="Replace the --plot file if it exists."),
    illuminant: str = typer.Option("D65", "--illuminant", help="CIE illuminant for sRGB and L*a*b*."),
    method: str = typer.Option("exact", "--method", help="exact (closed-form profiles) or tables (Gaussian tables)."),
    physics: str = typer.Option("diffusion", "--physics", help="diffusion (the model) or transport (the Monte Carlo reference)."),
    photons: Optional[int] = typer.Option(None, "--photons", help="--physics transport: photons per wavelength (default: the settings')."),
    seed: int = typer.Option(0, "--seed", help="--physics transport: seed of the photons."),
    config: Optional[Path] = typer.Option(None, "--config", help="Model settings YAML (configs/model.yaml)."),
) -> None:
    """Diffuse reflectance spectrum of homogeneous skin, with its sRGB and L*a*b* colour.

    Example: skinlayers spectrum --C_m 0.02 --beta_m 0.5 --C_he 0.002 --C_bc 0.001 --C_hd 0.005 --json
    """
    settings = load_model_settings(config)
    params = _params_from(preset, params_file, dict(C_m=C_m, beta_m=beta_m, C_he=C_he, C_bc=C_bc, C_hd=C_hd))
    model = SkinModel(settings)
    wl = parse_wavelengths(wavelengths)
    check_physics_options(physics, photons)
    if physics == "transport":
        if plot is not None and wl.numel() < 2:
            raise InputError("--plot needs at least two wavelengths")
        report = _transport_spectrum_report(settings, params, wl, illuminant, photons, seed)
    else:
        report = _spectrum_report(model, params, wl, method, illuminant)
    if plot is not None:
        _plot_spectra([("skin", report)], plot, title="Diffuse reflectance (normal incidence, specular excluded)", force=force)
    if as_json:
        typer.echo(json.dumps(report))
        return
    _print_spectrum(report, illuminant, plot)


def _print_spectrum(report: dict, illuminant: str, plot: Path | None) -> None:
    """``spectrum``'s table of reflectance per wavelength, its parameters and colour."""
    from rich.console import Console  # noqa: PLC0415
    from rich.table import Table  # noqa: PLC0415

    console = Console()
    table = Table(title="Diffuse reflectance", show_header=True)
    table.add_column("λ (nm)", justify="right")
    table.add_column("R_d", justify="right")
    errors = report.get("std_error") or [None] * len(report["reflectance"])
    if report.get("std_error"):
        table.add_column("± (MC)", justify="right")
    for w, r, e in zip(report["wavelength_nm"], report["reflectance"], errors):
        table.add_row(f"{w:g}", f"{r:.4f}", *([] if e is None else [f"{e:.4f}"]))
    console.print(table)
    p = report["params"]
    console.print("params: " + ", ".join(f"{k}={v:g}" for k, v in p.items()))
    if "lab" in report:
        L, a, b = report["lab"]
        console.print(
            f"sRGB ({illuminant}): {_hex(report['srgb'])} = ({', '.join(f'{c:.3f}' for c in report['srgb'])});"
            f" L*a*b* = ({L:.1f}, {a:.1f}, {b:.1f}); ITA = {report['ita_deg']:.1f}°"
        )
    if report.get("physics") == "transport":
        console.print(f"Monte Carlo: {report['photons']:,} photons per wavelength, g = {report['anisotropy']:g}; ± one standard error")
    if plot is not None:
        console.print(f"figure: {plot}")


def skin_types(
    plot: Optional[Path] = typer.Option(None, "--plot", help="Write the figure of spectra and colours (PNG)."),
    force: bool = typer.Option(False, "--force", help="Replace the --plot file if it exists."),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON object."),
    illuminant: str = typer.Option("D65", "--illuminant", help="CIE illuminant for sRGB and L*a*b*."),
    config: Optional[Path] = typer.Option(None, "--config", help="Model settings YAML."),
) -> None:
    """The paper's Table 2 skin types: spectra, sRGB, L*a*b* and ITA°, lighter to darker.

    Example: skinlayers skin-types --plot skin_types.png
    """
    settings = load_model_settings(config)
    model = SkinModel(settings)
    wl = parse_wavelengths("400:700:5")
    rows = [(name, _spectrum_report(model, SkinParams.from_mapping(p), wl, "exact", illuminant)) for name, p in TABLE2.items()]
    if plot is not None:
        _plot_spectra(rows, plot, title="DWRR08 Table 2 skin types (lower arm), homogeneous model", force=force)
    if as_json:
        typer.echo(json.dumps({"skin_types": [{"name": n, **r} for n, r in rows]}))
        return
    from rich.console import Console  # noqa: PLC0415
    from rich.table import Table  # noqa: PLC0415

    table = Table(title=f"Table 2 skin types ({illuminant})")
    for col in ("type", "sRGB", "L*", "a*", "b*", "ITA°", "R(450)", "R(550)", "R(650)"):
        table.add_column(col, justify="right")
    for name, r in rows:
        refl = dict(zip(r["wavelength_nm"], r["reflectance"]))
        hexcode = _hex(r["srgb"])
        table.add_row(
            name, f"[on {hexcode}]      [/] {hexcode}", *(f"{v:.1f}" for v in r["lab"]), f"{r['ita_deg']:.1f}",
            *(f"{refl[w]:.3f}" for w in (450.0, 550.0, 650.0)),
        )
    Console().print(table)
    if plot is not None:
        typer.echo(f"figure: {plot}")


def tables(
    wavelengths: Optional[str] = typer.Option(None, "--wavelengths", help="Default: the render wavelengths of the settings."),
    rebuild: bool = typer.Option(False, "--rebuild", help="Rebuild even if a cached copy exists."),
    config: Optional[Path] = typer.Option(None, "--config", help="Model settings YAML."),
) -> None:
    """Build (or find in the cache) the Gaussian lookup tables for a set of wavelengths.

    Example: skinlayers tables --wavelengths 400:700:10
    """
    from rich.progress import Progress  # noqa: PLC0415

    from .column.tables import default_cache_dir, load_profile_tables  # noqa: PLC0415

    settings: ModelSettings = load_model_settings(config)
    wl = parse_wavelengths(wavelengths) if wavelengths else torch.tensor(settings.render_wavelengths_nm, dtype=torch.float64)
    start = time.perf_counter()
    with Progress(transient=True) as bar:
        task = bar.add_task("fitting Gaussians", total=wl.numel())
        load_profile_tables(wl, settings, rebuild=rebuild, progress=lambda done, total: bar.update(task, completed=done))
    typer.echo(
        f"tables for {wl.numel()} wavelengths ready in {time.perf_counter() - start:.1f} s "
        f"({settings.tables.n_gaussians} Gaussians × {settings.tables.n_sigma_a} σa; cache {default_cache_dir()})"
    )


def _plot_spectra(rows: list[tuple[str, dict]], path: Path, title: str, force: bool) -> None:
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    fig, (ax, sw) = plt.subplots(1, 2, figsize=(10, 4.6), gridspec_kw={"width_ratios": [3, 1]})
    for i, (name, r) in enumerate(rows):
        rgb = [min(max(c, 0.0), 1.0) for c in r["srgb"]]
        ax.plot(r["wavelength_nm"], r["reflectance"], color=rgb, lw=2.2, label=name)
        sw.add_patch(plt.Rectangle((0, len(rows) - 1 - i), 1, 0.9, color=rgb))
        sw.text(1.08, len(rows) - 1 - i + 0.45, f"{name}  ITA {r['ita_deg']:.0f}°", va="center", fontsize=8)
    ax.set_xlabel("wavelength (nm)")
    ax.set_ylabel("diffuse reflectance")
    ax.set_ylim(0, None)
    ax.grid(alpha=0.3)
    ax.set_facecolor("#f4f4f4")
    if len(rows) > 1:
        ax.legend(fontsize=7, ncol=2)
    ax.set_title(title, fontsize=10)
    sw.set_xlim(0, 2.6)
    sw.set_ylim(0, len(rows))
    sw.axis("off")
    sw.set_title("sRGB (" + rows[0][1]["illuminant"] + ")", fontsize=9)
    fig.tight_layout()
    try:
        write_file(path, lambda p: fig.savefig(p, dpi=130, format="png"), force=force, what="figure")
    finally:
        plt.close(fig)


def _device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise InputError("--device cuda: no CUDA device is available")
    if name not in ("cpu", "cuda"):
        raise InputError(f"--device {name!r}: expected auto, cpu or cuda")
    return torch.device(name)


def render(
    maps_file: Path = typer.Argument(..., help="Parameter maps (OpenEXR: C_m, beta_m, C_he, C_bc, C_hd[, rho_s], mm_per_pixel)."),
    out: Path = typer.Option(..., "-o", "--out", help="Output path; writes OUT.exr (one channel per band) and OUT.png (sRGB)."),
    light: str = typer.Option("uniform", "--light", help="uniform | window[:mm] | stripes[:period_mm[:duty]] | point."),
    bands: Optional[str] = typer.Option(None, "--bands", help="Wavelengths (start:stop:step or a list); default: the render bands."),
    edit: list[str] = typer.Option([], "--edit", help="Scale a chromophore, e.g. hemoglobin*1.5, melanin*2 (repeatable)."),
    swap: list[str] = typer.Option([], "--swap", help="Take a chromophore from other maps: NAME=FILE.exr (repeatable)."),
    tattoo: Optional[Path] = typer.Option(None, "--tattoo", help="Interface absorbance (OpenEXR channels P_<nm>): ink, veins."),
    gel: bool = typer.Option(False, "--gel/--no-gel", help="Skin under gel with crossed polarizers: no surface term."),
    light_angle: float = typer.Option(0.0, "--light-angle", help="Angle of the light from the normal (degrees)."),
    view_angle: float = typer.Option(0.0, "--view-angle", help="Angle of the view from the normal (degrees)."),
    blur: Optional[str] = typer.Option(None, "--blur", help="Blur strategy: pyramid, fft or chain (default from settings)."),
    device: str = typer.Option("auto", "--device", help="auto, cpu or cuda."),
    config: Optional[Path] = typer.Option(None, "--config", help="Model settings YAML."),
    force: bool = typer.Option(False, "--force", help="Replace OUT.exr and OUT.png if they exist."),
    physics: str = typer.Option("diffusion", "--physics", help="diffusion (the model's renderer) or transport (the Monte Carlo reference)."),
    photons: Optional[int] = typer.Option(None, "--photons", help="--physics transport: photons per band (default: the settings')."),
    seed: int = typer.Option(0, "--seed", help="--physics transport: seed of the photons."),
    tile: int = typer.Option(0, "--tile", help="Render in square tiles of this many pixels (uniform light; 0: only when the maps do not fit in memory whole)."),
    threads: Optional[str] = typer.Option(None, "--threads", help=THREADS_HELP),
) -> None:
    """Render parameter maps with the heterogeneous layered model: a spectral EXR and an sRGB PNG.

    Example: skinlayers render maps.exr --light window:7.5 --edit hemoglobin*1.5 -o out/render
    """
    from .render.illumination import parse_light  # noqa: PLC0415
    from ..formats.exr import write_spectral  # noqa: PLC0415
    from ..formats.outputs import claim_outputs  # noqa: PLC0415

    settings = load_model_settings(config)
    dev = _device(device)
    lit = parse_light(light)
    wl = parse_wavelengths(bands) if bands else torch.tensor(settings.render_wavelengths_nm, dtype=torch.float64)
    check_physics_options(physics, photons)
    plan = _memory_plan(maps_file, lit, wl, settings, dev, tile, physics)  # from the header, before any pixel is read
    maps = _edited_maps(maps_file, swap, edit, tattoo)
    base = out.with_suffix("") if out.suffix.lower() in (".exr", ".png") else out
    names = [base.with_suffix(".exr").name] + ([base.with_suffix(".png").name] if wl.numel() >= 2 else [])
    command_threads(threads)
    with claim_outputs(base.parent, names, force=force, lock_name=f".{base.name}.lock", what="rendering") as staging:
        start = time.perf_counter()
        angles = dict(under_gel=gel, light_angle_deg=light_angle, view_angle_deg=view_angle)
        if physics == "transport":
            image, se, extra, how = _render_transport(maps.to(dev), lit, wl, settings, photons, seed, angles)
        elif plan is not None and plan.tile_px is not None:
            (image, extra, how), se = _render_tiles(maps.to(dev), lit, wl, settings, blur, angles, plan), None
        else:
            passes = plan.bands_per_pass if plan is not None else None
            (image, extra, how), se = _render_diffusion(maps.to(dev), lit, wl, settings, blur, angles, passes), None
        seconds = time.perf_counter() - start
        write_spectral(staging.path(names[0]), image, wl, maps.mm_per_pixel,
                       attributes={"light": light, "software": "skinlayers", "physics": physics, **extra},
                       extra=None if se is None else {"SE": se})
        if wl.numel() >= 2:
            _write_png(staging.path(names[1]), _srgb_rows(ColourConverter(wl, settings.illuminant), image))
    typer.echo(
        f"rendered {image.shape[1]}×{image.shape[2]} px at {wl.numel()} bands on {dev.type} in {seconds:.1f} s "
        f"({how}): " + ", ".join(str(base.parent / n) for n in names)
    )


def _edited_maps(maps_file: Path, swap: list[str], edit: list[str], tattoo: Path | None):
    """The maps to render: read, then each ``--swap`` (NAME=FILE.exr), each ``--edit``, and the ``--tattoo``'s ink."""
    from ..formats.maps import read_absorbance  # noqa: PLC0415
    from .patch.edits import add_absorbance, apply_edit, swap_chromophore  # noqa: PLC0415
    from .patch.maps_io import read_maps  # noqa: PLC0415

    maps = read_maps(maps_file)
    for item in swap:
        name, _, path = item.partition("=")
        if not path:
            raise InputError(f"--swap {item!r}: expected NAME=FILE.exr")
        maps = swap_chromophore(maps, read_maps(path), name.strip())
    for item in edit:
        maps = apply_edit(maps, item)
    if tattoo is not None:
        ink, ink_wl, ink_mm = read_absorbance(tattoo)
        if abs(ink_mm - maps.mm_per_pixel) > 1e-6 * maps.mm_per_pixel:
            raise InputError(f"{tattoo}: mm_per_pixel {ink_mm:g} differs from the maps' {maps.mm_per_pixel:g}")
        maps = add_absorbance(maps, ink, ink_wl)
    return maps


def _render_diffusion(maps, light, wl: torch.Tensor, settings: ModelSettings, blur, angles: dict, bands_per_pass):
    """The diffusion renderer, whole, ``bands_per_pass`` bands at a time (None: all; the memory plan's):
    the image ``(L, H, W)``, header extras, a note."""
    from .render.renderer import SkinRenderer  # noqa: PLC0415

    renderer = SkinRenderer(settings)
    step = bands_per_pass or wl.numel()
    groups = [slice(k, k + step) for k in range(0, wl.numel(), step)]
    # every group takes the terms all bands at once would: grouping changes nothing in the image
    series = renderer.series_terms_for(maps, wl) if len(groups) > 1 else None
    image, terms = None, []
    for group in groups:  # each group's bands go straight into the one output image: no list to concatenate
        result = renderer.render(maps, light, wl[group], blur=blur, series_terms=series, **angles)
        if image is None:
            image = torch.empty(wl.numel(), *result.image.shape[-2:], dtype=torch.float32)
        image[group] = result.image[0].detach().cpu()
        terms += result.terms
        del result
    return image, {}, f"{max(terms)} inter-scattering terms"


def _render_transport(maps, light, wl: torch.Tensor, settings: ModelSettings, photons, seed: int, angles: dict):
    """The Monte Carlo reference: the image ``(L, H, W)``, its standard error ``(L, H, W)`` (written as
    channels ``SE_<nm>``), the photons and seed for the header, a note."""
    from rich.progress import Progress  # noqa: PLC0415

    from .transport import TransportRenderer  # noqa: PLC0415

    with Progress(transient=True) as bar:
        task = bar.add_task("transport (Monte Carlo)", total=wl.numel())
        result = TransportRenderer(settings).render(maps, light, wl, photons=photons, seed=seed, progress=lambda done, total: bar.update(task, completed=done), **angles)
    se = result.image_std_error[0].cpu()
    extra = {"photons_per_band": str(result.photons), "seed": str(seed), "anisotropy": str(settings.transport.anisotropy),
             "std_error_median": [float(v) for v in se.reshape(se.shape[0], -1).median(1).values]}
    return result.image[0].cpu(), se, extra, f"Monte Carlo, {result.photons:,} photons a band, median standard error {float(se.median()):.2g}"


def _memory_plan(maps_file: Path, light, wl: torch.Tensor, settings: ModelSettings, device, tile: int, physics: str):
    """Whole or in tiles, from the maps' header alone (``model/render/tiles.py``); refused here, before any large
    allocation, when not even tiles fit the memory budget. None for the Monte Carlo (it renders pixels
    in batches of its own)."""
    from ..formats.exr import float_attribute, read_exr_header  # noqa: PLC0415
    from ..formats.maps import MapsError  # noqa: PLC0415
    from .render.renderer import SkinRenderer  # noqa: PLC0415
    from ..formats.resources import plan_budget_bytes  # noqa: PLC0415
    from .render.tiles import plan_render  # noqa: PLC0415

    if tile < 0 or 0 < tile < 16:
        raise InputError(f"--tile {tile}: 0 (automatic) or a tile side of at least 16 px")
    if physics == "transport":
        return None
    height, width, header = read_exr_header(maps_file, MapsError)
    mm = float_attribute(header, "mm_per_pixel", maps_file, MapsError)
    if not mm > 0:
        return None  # the maps' reader refuses it, naming the attribute
    renderer = SkinRenderer(settings)
    return plan_render((1, height, width), mm, wl.numel(), light, renderer, plan_budget_bytes(device), tile or None)


def _render_tiles(maps, light, wl: torch.Tensor, settings: ModelSettings, blur, angles: dict, plan):
    """The diffusion renderer tile by tile, with a progress bar: the image ``(L, H, W)``, header extras, a note."""
    from rich.progress import Progress  # noqa: PLC0415

    from .render.renderer import SkinRenderer  # noqa: PLC0415
    from .render.tiles import render_tiled  # noqa: PLC0415

    with Progress(transient=True) as bar:
        task = bar.add_task(f"tiles of {plan.tile_px} px", total=None)
        image = render_tiled(SkinRenderer(settings), maps, light, wl, plan.tile_px, plan.halo_px,
                             lambda done, total: bar.update(task, completed=done, total=total),
                             bands_per_pass=plan.bands_per_pass, blur=blur, **angles)
    extra = {"tile_px": str(plan.tile_px), "tile_halo_px": str(plan.halo_px)}
    return image[0], extra, plan.describe()


def _srgb_rows(converter: ColourConverter, image: torch.Tensor, rows: int = 256) -> torch.Tensor:
    """sRGB ``(H, W, 3)`` (float32) of ``(L, H, W)``, ``rows`` rows at a time (a camera's frame whole
    would take its size many times over in the colour conversion's intermediates)."""
    out = torch.empty(image.shape[1], image.shape[2], 3, dtype=torch.float32)
    for y in range(0, image.shape[1], rows):
        out[y:y + rows] = converter.srgb(image[:, y:y + rows].permute(1, 2, 0).double()).float()
    return out


def _write_png(path: Path, rgb: torch.Tensor) -> None:
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    plt.imsave(path, rgb.clamp(0, 1).numpy(), format="png")


def register(app: typer.Typer) -> None:
    app.command("spectrum")(spectrum)
    app.command("skin-types")(skin_types)
    app.command("tables")(tables)
    app.command("render")(render)
