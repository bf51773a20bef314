"""``skinlayers design-bands``: choose the rig's filters from a catalogue by the Cramér–Rao bound of the fit.

DWRR08 §5 chose its filters "based on simulations using our skin model … an exhaustive search for filter
combinations that provided an optimal signal-to-noise ratio with respect to the intrinsic model
parameters". Here the same search, stated:

- **What is photographed** (``Radiometry``): the simulator's own chain (``acquire/simulator/simulated.py``): the
  flash (the simulation settings' blackbody; the simulator has no xenon spectrum, so no ragged
  region near 420 nm), the filter (a Gaussian of the catalogue's FWHM, the simulator's quadrature), the
  Spectralon and the polarizers' factors, the sensor's Bayer sensitivities, each band's ISO chosen as the
  rig file's are (the largest that keeps the Spectralon within ``reference_fill`` of the range), shot
  and read noise and the DN step, and the calibration's ratio of skin to Spectralon superpixels
  (R + 2G + B), averaged over the superpixels of a cube pixel. The flash's power is the current rig's,
  so every design is photographed with the same flash.
- **What is fitted** (``band_jacobian``): the fit's band model, homogeneous skin per pixel
  (``reconstruct/levels/problem.py``: the multipole reflectance at each band's three nodes, weights 2/3, 1/6,
  1/6, times the camera's exit factor), differentiated in log C_m, β_m, log C_he, log C_bc, log C_hd.
- **The model's error** (``band_discrepancy``, on by default): what the fit's renderer misses of the
  skin it fits (variation within a pixel, the simulator's finer grid and quadrature), measured per filter
  by rendering the demo's scene both ways over the rig's window. Its spread from pixel to
  pixel counts as noise in quadrature (shared maps average it as they average noise); its mean is the
  same in every pixel, and no sharing averages it: it enters as the bias of the fit's own estimator
  (unweighted least squares, every map free, ``FilterTerms``).
- **The criterion** (``Criterion``): per skin of the prior, the Cramér–Rao bound of each map in the
  fit's layout (``bound_variance``: C_m and C_he per pixel; C_hd, β_m and C_bc on their default grids,
  each value shared by the pixels of its cell, ``shared_pixels``) plus the model's bias squared; per
  scored map (``MAP_TARGETS``: C_m, C_he, C_hd relative, β_m absolute; C_bc has no target) its expected
  log(1 + variance/target²) over the prior. ``rig`` (the default): the worst map's expected error over
  the same for the rig's own bands — below 1, every map improves on the rig (a minimax relative
  efficiency); ``targets``: the maps' expected errors summed (A-optimal, target-weighted).
- **The prior** (``prior_skins``): each row of DWRR08's Table 2, each chromophore spread as the demo
  scene spreads it (log-normal, ``SPREAD``), ``PRIOR_SAMPLES`` skins a row, from a fixed seed.
- **The search** (``search``): every combination where there are at most ``EXHAUSTIVE_LIMIT``; beyond,
  Fedorov's exchange from ``EXCHANGE_STARTS`` random sets (swap a chosen filter for one not chosen while
  the score falls) and, counting up (``search_counts``), from the best set one smaller with its best
  further filter.
"""

from __future__ import annotations

import itertools
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch
import typer

from .band_discrepancy import Discrepancy
from .band_information import (CATALOGUE_DEFAULT, CRITERIA, CRITERION_WORDS, SCORE_BATCH_BYTES, UNDETERMINED_SD, Criterion, Filter,
                               FilterTerms, Radiometry, band_jacobian, bound_variance, default_catalogue, filter_information,
                               filter_terms, joined_terms, prior_skins, read_catalogue, rgb_terms, shared_pixels)
from ..formats.errors import InputError

__all__ = ["CATALOGUE_DEFAULT", "CRITERIA", "BandDesign", "Criterion", "Filter", "FilterTerms", "Radiometry", "band_jacobian",
           "bound_variance", "default_catalogue", "design_bands", "exchange_search", "exhaustive_search", "filter_information",
           "filter_terms", "prior_skins",
           "read_catalogue", "search", "shared_pixels", "write_design"]

#: Combinations above which the exchange algorithm replaces the exhaustive search.
EXHAUSTIVE_LIMIT = 200_000
EXCHANGE_STARTS = 12
#: Counts the chart of the bound against N spans: one band per parameter and the scale, to a full wheel.
CHART_COUNTS = range(6, 12)
#: Evenly spaced comparison: the catalogue's span in ``count`` equal steps.
COMPARISONS = ("chosen", "current rig", "evenly spaced", "RGB camera")
#: Exchange passes from one start at most (each lowers the score; the searches here end in a few).
MAX_EXCHANGES = 200


@dataclass(frozen=True)
class SearchResult:
    """The best set found (indices, ascending), its score, how it was found and in what time."""

    chosen: tuple[int, ...]
    score: float
    method: str
    evaluated: int
    seconds: float


def exhaustive_search(criterion: Criterion, count: int) -> SearchResult:
    """Every combination of ``count`` filters, scored in batches of ``SCORE_BATCH_BYTES``; the best."""
    start = time.perf_counter()
    per_filter = criterion.information[0].numel() * (1 if criterion.terms.normal is None else 2.2)  # the bias: J Jᵀ and J b too
    batch = max(1, int(SCORE_BATCH_BYTES // (count * per_filter * 8)))
    best, best_score, evaluated = None, math.inf, 0
    combos = itertools.combinations(range(criterion.candidates), count)
    while chunk := list(itertools.islice(combos, batch)):
        scores = criterion(torch.tensor(chunk))
        i = int(torch.argmin(scores))
        evaluated += len(chunk)
        if float(scores[i]) < best_score:
            best, best_score = chunk[i], float(scores[i])
    return SearchResult(tuple(best), best_score, "exhaustive", evaluated, time.perf_counter() - start)


def exchange_search(criterion: Criterion, count: int, starts: int = EXCHANGE_STARTS, seed: int = 0,
                    initial: Sequence[Sequence[int]] = ()) -> SearchResult:
    """Fedorov's exchange: from each start (the ``initial`` sets, then ``starts`` random ones), the best
    single swap (a chosen filter for one not chosen) while it lowers the score; the best end point."""
    start_time = time.perf_counter()
    generator = torch.Generator().manual_seed(seed)
    size = criterion.candidates
    best, best_score, evaluated = None, math.inf, 0
    randoms = (sorted(torch.randperm(size, generator=generator)[:count].tolist()) for _ in range(starts))
    for chosen in itertools.chain((sorted(c) for c in initial), randoms):
        score = float(criterion(chosen))
        for _ in range(MAX_EXCHANGES):
            swaps = [sorted([*chosen[:i], c, *chosen[i + 1:]]) for i in range(count) for c in range(size) if c not in chosen]
            scores = criterion(torch.tensor(swaps))
            evaluated += len(swaps)
            i = int(torch.argmin(scores))
            if float(scores[i]) >= score * (1 - 1e-12):
                break
            chosen, score = swaps[i], float(scores[i])
        if score < best_score:
            best, best_score = chosen, score
    return SearchResult(tuple(best), best_score, "exchange", evaluated, time.perf_counter() - start_time)


def search(criterion: Criterion, count: int, initial: Sequence[Sequence[int]] = ()) -> SearchResult:
    """Exhaustive where the combinations are at most ``EXHAUSTIVE_LIMIT``, else the exchange algorithm
    (from ``initial`` sets too)."""
    size = criterion.candidates
    if not 1 <= count <= size:
        raise InputError(f"--count {count}: choose between 1 and the catalogue's {size} filters")
    if math.comb(size, count) <= EXHAUSTIVE_LIMIT:
        return exhaustive_search(criterion, count)
    return exchange_search(criterion, count, initial=initial)


def search_counts(criterion: Criterion, counts: Sequence[int]) -> dict[int, SearchResult]:
    """The best set of each count, ascending: each exchange starts also from the best set one smaller with
    the filter that lowers its score most (the model's bias makes the score rugged: random starts alone
    ended far from the best at 11 filters)."""
    found: dict[int, SearchResult] = {}
    for count in sorted(set(counts)):
        smaller = found.get(count - 1)
        initial = [] if smaller is None else [_best_extension(criterion, smaller.chosen)]
        found[count] = search(criterion, count, initial)
    return found


def _best_extension(criterion: Criterion, chosen: Sequence[int]) -> list[int]:
    """``chosen`` with the one further filter that gives the lowest score."""
    others = [c for c in range(criterion.candidates) if c not in chosen]
    sets = [sorted([*chosen, c]) for c in others]
    return sets[int(torch.argmin(criterion(torch.tensor(sets))))]


@dataclass
class BandDesign:
    """What ``design-bands`` found: the chosen filters and their ISOs, the search, the bound of each
    compared set per parameter, and the best score at each count of the chart."""

    chosen: list[Filter]
    isos: list[int]
    criterion: str
    search: SearchResult
    bounds: dict[str, dict[str, float]]
    scores: dict[str, float]
    by_count: dict[int, float]
    seconds: float
    model_error: Discrepancy | None = None  # the model's error the criterion used; None: the noise alone


def design_bands(catalogue: Sequence[Filter], count: int, rig=None, kind: str = "rig", *, model_error: bool = True,
                 say=None) -> BandDesign:
    """Search the catalogue for ``count`` filters by the criterion ``kind`` (the module docstring), compare
    with the rig's own bands and evenly spaced ones, and chart the best score against the count.
    ``model_error``: the fit's model error beside the noise (``band_discrepancy``; each filter measured once
    per rig window, a minute or two for a catalogue, then cached; ``say`` announces it)."""
    from .band_discrepancy import discrepancy  # noqa: PLC0415

    start = time.perf_counter()
    radiometry = Radiometry(rig)
    lo, hi = min(f.centre_nm for f in catalogue), max(f.centre_nm for f in catalogue)
    compared = {"current rig": [Filter(b.wavelength_nm, b.fwhm_nm) for b in radiometry.rig.bands],
                "evenly spaced": [Filter(float(c), catalogue[0].fwhm_nm) for c in np.linspace(lo, hi, count)]}
    every = [*catalogue, *compared["current rig"], *compared["evenly spaced"]]
    error = discrepancy(radiometry.rig, list(dict.fromkeys(every)), simulation=radiometry.settings, say=say) if model_error else None
    skins = prior_skins()
    terms = joined_terms(filter_terms(radiometry, skins, every, error), rgb_terms(radiometry, skins, model_error))
    n, r = len(catalogue), len(compared["current rig"])
    sets = {"current rig": list(range(n, n + r)), "evenly spaced": list(range(n + r, len(every))),
            "RGB camera": list(range(len(every), len(every) + 3))}
    criterion = Criterion(terms, shared_pixels(radiometry.rig), kind, sets["current rig"], candidates=n)
    searched = search_counts(criterion, [k for k in CHART_COUNTS if k <= n] + [count])
    found = searched[count]
    sets = {"chosen": list(found.chosen), **sets}
    bounds = {name: criterion.median_sd(chosen) for name, chosen in sets.items()}
    scores = {name: float(criterion(chosen)) for name, chosen in sets.items()}
    by_count = {k: searched[k].score for k in CHART_COUNTS if k <= n}
    chosen = [catalogue[i] for i in found.chosen]
    return BandDesign(chosen, [radiometry.iso(f) for f in chosen], kind, found, bounds, scores, by_count, time.perf_counter() - start,
                      error)


#: What ``design-bands`` writes; ``design.json`` last (its presence says the rest is there).
PRODUCTS = ("rig.yaml", "bound_vs_count.png", "design.json")


def write_design(design: BandDesign, out: Path, rig=None, *, force: bool = False) -> dict[str, Path]:
    """``design.json``, ``rig.yaml`` (the rig with the chosen bands and their ISOs at f/10, the ISOs' rule)
    and ``bound_vs_count.png`` into ``out``, under the outputs' promises (``formats/outputs.py``: never in
    a session, nothing replaced without ``force``, whole or absent); their paths by kind."""
    import json  # noqa: PLC0415

    import yaml  # noqa: PLC0415

    from ..acquire.hardware.rig import load_rig  # noqa: PLC0415
    from ..formats.files import atomic_write  # noqa: PLC0415
    from ..formats.outputs import claim_outputs  # noqa: PLC0415

    rig = rig or load_rig()
    positions = [p for p in range(1, rig.wheel.position_count + 1) if p != rig.wheel.dark_position]
    if len(design.chosen) > len(positions):
        raise InputError(f"{len(design.chosen)} filters: the wheel holds {len(positions)} beside its dark slot")
    bands = [{"wavelength_nm": f.centre_nm, "fwhm_nm": f.fwhm_nm, "filter_position": position, "iso": iso, "aperture_f": 10.0}
             for f, iso, position in zip(design.chosen, design.isos, positions)]
    rig_text = yaml.safe_dump({**rig.model_dump(mode="json"), "bands": bands}, sort_keys=False)
    record = {
        "criterion": {"kind": design.criterion, "meaning": CRITERION_WORDS[design.criterion]},
        "chosen": [{"centre_nm": f.centre_nm, "fwhm_nm": f.fwhm_nm, "iso": iso} for f, iso in zip(design.chosen, design.isos)],
        "search": {"method": design.search.method, "sets_scored": design.search.evaluated, "seconds": round(design.search.seconds, 2)},
        "score": design.scores, "median_expected_sd": design.bounds,
        "best_score_by_count": {str(n): s for n, s in design.by_count.items()}, "seconds": round(design.seconds, 1),
        "model_error": None if design.model_error is None else {
            k: getattr(design.model_error, k) for k in ("cube_px", "mm_per_pixel", "seed", "seconds")},
    }
    with claim_outputs(out, PRODUCTS, force=force, marker="design.json", what="band design") as staging:
        atomic_write(staging.path("rig.yaml"), ("# skinlayers design-bands: the rig with the chosen bands\n" + rig_text).encode())
        _chart(design, len(rig.bands), staging.path("bound_vs_count.png"))
        atomic_write(staging.path("design.json"), (json.dumps(record, indent=1) + "\n").encode())
    return {"rig": out / "rig.yaml", "chart": out / "bound_vs_count.png", "record": out / "design.json"}


def _chart(design: BandDesign, rig_bands: int, path: Path) -> Path:
    import io  # noqa: PLC0415

    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    from ..formats.files import atomic_write  # noqa: PLC0415

    fig, ax = plt.subplots(figsize=(6, 4))
    counts = list(design.by_count)
    ax.plot(counts, [design.by_count[n] for n in counts], "o-", label="best set of N from the catalogue")
    n = len(design.chosen)
    for name, marker, bands in (("chosen", "*", n), ("current rig", "s", rig_bands), ("evenly spaced", "^", n)):
        ax.plot([bands], [design.scores[name]], marker, ms=9, label=f"{name} ({bands} bands)")
    ax.set_xlabel("bands (N)")
    ax.set_ylabel("worst map's expected error / the rig's" if design.criterion == "rig" else "Σ maps' expected error")
    ax.set_title("The fit's expected error (noise bound" + (" + model error)" if design.model_error is not None else ")")
                 + " against N", fontsize=10)
    ax.legend(fontsize=8)
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=110)
    plt.close(fig)
    return atomic_write(path, buffer.getvalue())


def design_bands_cli(
    catalog: Optional[Path] = typer.Option(None, "--catalog", help="CSV of filters (centre_nm, fwhm_nm); default: 10-nm "
                                                                   "filters every 10 nm over 400–720 nm."),
    count: int = typer.Option(9, "--count", help="Filters to choose."),
    rig_path: Optional[Path] = typer.Option(None, "--rig", help="Rig YAML (its flash, camera, exposures' rule, wheel)."),
    criterion: str = typer.Option("rig", "--criterion", help="rig: improve every map most on the rig's own bands; "
                                                             "targets: A-optimal, each map over its target."),
    out: Path = typer.Option(Path("design-bands"), "-o", "--out", help="Folder for design.json, rig.yaml and the chart."),
    force: bool = typer.Option(False, "--force", help="Replace an earlier design in the output folder."),
    model_error: bool = typer.Option(True, "--model-error/--noise-only", help="Weigh the fit's model error beside the "
                                     "camera's noise (each filter rendered once per rig window, a minute or two a catalogue; cached)."),
) -> None:
    """Choose the rig's filters from a catalogue by the fit's expected error: its Cramér–Rao bound and its model's error (DWRR08 §5).

    Example: skinlayers design-bands                 (9 of the default catalogue: 10-nm filters, 400–720 nm)
             skinlayers design-bands --catalog my_filters.csv --count 8 -o my_design
    """
    from ..acquire.hardware.rig import load_rig  # noqa: PLC0415

    if criterion not in CRITERIA:
        raise InputError(f"--criterion {criterion!r}: choose one of {', '.join(CRITERIA)}")
    from ..formats.outputs import check_outputs  # noqa: PLC0415

    catalogue = read_catalogue(catalog) if catalog is not None else default_catalogue()
    rig = load_rig(rig_path)
    most = min(rig.wheel.position_count - 1, len(catalogue))
    if not 1 <= count <= most:
        raise InputError(f"--count {count}: choose 1 to {most} (the wheel's filters beside its dark slot, the catalogue's filters)")
    check_outputs(out, PRODUCTS, force=force, what="band design")  # refused before the search
    design = design_bands(catalogue, count, rig, criterion, model_error=model_error, say=typer.echo)
    paths = write_design(design, out, rig, force=force)
    typer.echo("chosen: " + ", ".join(f"{f.centre_nm:g} nm (ISO {iso})" for f, iso in zip(design.chosen, design.isos)))
    typer.echo(f"search: {design.search.method}, {design.search.evaluated} sets in {design.search.seconds:.1f} s; "
               f"all of it {design.seconds:.0f} s")
    for name in COMPARISONS:
        sd = ", ".join(f"{k} {100 * v:.1f}%" if v <= UNDETERMINED_SD else f"{k} undetermined" for k, v in design.bounds[name].items())
        typer.echo(f"{name:>14}: score {design.scores[name]:.3g}; median expected error {sd}")
    for kind, path in paths.items():
        typer.echo(f"{kind}: {path}")
    typer.echo("before buying filters, photograph simulated sessions with rig.yaml and with your rig's bands and compare "
               "the maps (docs/band_design.md: the bound and the model's error do not yet predict every rig)")


def register(app: typer.Typer) -> None:
    app.command("design-bands")(design_bands_cli)
