"""``skinlayers stability``: where each method breaks, how badly, and whether the user is told.

A matrix of conditions × methods on simulated sessions with a known truth. Each condition is swept in
strength (``CONDITIONS``); each cell is one fit, measured against the truth the session was simulated
from (``skinlayers.analyses.tradeoff``'s sessions: the demo's scene through the rig and the calibration):

- where the condition lives decides what is simulated anew: on the calibrated cube (``"cube"``: the
  camera's noise scaled, bands misregistered, a band blurred by the subject's motion, a dead band;
  seconds a cell), in the calibration (``"calibration"``: the Spectralon's certified value wrong at one
  band or at all, the base session calibrated anew), in the capture (``"capture"``: the skin type, hairs,
  the flash drifting between frames; a new session each), in the physics (``"physics"``: the shipped
  transport sessions of ``skinlayers.analyses.truths``, the skin rendered by Monte Carlo);
- a cell **meets the targets** when each map's median error is within ``TARGETS`` (the demo's) over the
  scored pixels (``demo.scored_pixels``: visible, not flagged for a high residual or a hair), the
  residual is at the camera's noise (``RESIDUAL_AT_NOISE``) and σ covers ``SIGMA_COVER`` of the truth
  within 2σ for every targeted map, on the scored pixels and on those flagged for a hair;
- a cell is **detected** when the calibration or the fit warned (a flag of ``CALIBRATION_WARNINGS`` in
  ``calibration.json``; a warning in ``fit.json``'s ``data_checks`` and on the command line) or refused
  the data with an error. A cell that misses a
  target and is not detected is a **silent failure**; one detected whose words do not name its condition
  (``Condition.cause``) is **told, not named**; one that meets the targets and still warns is a **false
  alarm** (counted: a check that cries on good data teaches users to ignore it).

The table (``stability.csv``) is written row by row and resumed; ``stability.json`` holds per method
the first strength of each condition that misses a target (its breaking point) and the silent cells;
``stability_<method>.png`` the heat maps.
"""

from __future__ import annotations

import json
import math
import re
import time
from dataclasses import dataclass
from pathlib import Path
import torch
import typer

from .sweep import AnalysisResult, SweepTable, analysis_device, cell_text, echo_outputs
from .tradeoff import TARGETS, SessionSpec, make_session
from ..formats.threads import THREADS_HELP, command_threads

__all__ = ["COLUMNS", "CONDITIONS", "METHODS", "StabilityPlan", "StabilityResult", "cell_verdict", "make_plan", "run_stability"]

MAPS = ("C_m", "beta_m", "C_he", "C_bc", "C_hd")
#: The residual's RMS over the camera's noise RMS (same pixels and bands) at or below which the residual is
#: "at the noise": above what clean sessions give with the default fit (docs/stability.md, "From
#: skinlayers/analyses/stability.py").
RESIDUAL_AT_NOISE = 1.2
#: The share of scored pixels whose truth each targeted map's σ must cover within 2σ.
SIGMA_COVER = 0.85


@dataclass(frozen=True)
class Condition:
    """A fault and its strengths (``clean``: the strength that leaves the data as simulated)."""

    where: str  # "cube", "calibration", "capture" or "physics"
    strengths: tuple
    quick: tuple
    unit: str
    clean: object = None
    #: Words a warning must hold to name this condition as a cause (any of them).
    cause: tuple[str, ...] = ()


CERTIFICATE_UNIT = "relative error of the Spectralon's certified value the calibration uses"
#: The conditions. Cube conditions act on the calibrated cube (``_perturb_cube``); calibration conditions
#: calibrate the base session anew with the rig's record changed (``_recorded_rig``: the Spectralon's
#: certified value wrong, its true value what the simulator photographed); capture conditions change the
#: simulated scene or bench (``_capture_changes``); physics uses the shipped transport sessions.
CONDITIONS: dict[str, Condition] = {
    "noise": Condition("cube", (0.25, 0.5, 1.0, 2.0, 4.0, 8.0), (0.25, 2.0, 8.0), "× the camera's noise", 1.0, cause=("noise-limited",)),
    "certificate 430 nm": Condition("calibration", (-0.10, -0.08, -0.05, -0.03, -0.02, 0.01), (-0.08, -0.03), CERTIFICATE_UNIT, cause=("certified value",)),
    "certificate 550 nm": Condition("calibration", (-0.10, -0.08, -0.05, -0.03, -0.02, 0.01), (-0.08,), CERTIFICATE_UNIT, cause=("certified value",)),
    "certificate all bands": Condition("calibration", (-0.10, -0.05, 0.01), (-0.10,), CERTIFICATE_UNIT, cause=("certified value",)),
    "misregistration": Condition("cube", (0.5, 1.0, 2.0, 3.0), (1.0, 3.0), "cube px between neighbouring bands", cause=("misregistration",)),
    "motion blur": Condition("cube", (3, 5, 9), (5,), "px, one band (550 nm)", cause=("motion",)),
    "dead band": Condition("cube", (550,), (550,), "nm", cause=("left out",)),
    "skin type": Condition("capture", ("I interior", "IV exterior", "V exterior"), ("V exterior",), "DWRR08 Table 2 row", cause=("noise-limited",)),
    "hairs": Condition("capture", (5, 20), (5,), "hairs in the view", cause=("hair",)),
    "flash drift": Condition("capture", (0.1, 0.2), (0.2,), "frame-to-frame flash jitter (relative)", cause=("flash",)),
    "physics": Condition("physics", (41, 42, 43), (41,), "transport session (Monte Carlo) seed", cause=("physics",)),
}
#: The methods: fit settings over the defaults (``skinlayers.analyses.tradeoff.INVERSE_CONFIGS``' names where shared).
METHODS: dict[str, dict] = {
    "auto": {},
    "gn-hom": {"forward": "heterogeneous"},
    "homogeneous": {"forward": "homogeneous"},
    "gn": {"method": "gn", "forward": "heterogeneous"},
    "adam": {"method": "adam", "forward": "heterogeneous"},
    "transport": {"model": {"profiles": "transport"}},
}
QUICK_METHODS = ("auto", "homogeneous", "transport")
#: The calibration's flags that say the cube may be wrong (the others say which pixels it masked).
CALIBRATION_WARNINGS = ("many_invalid", "gray_card_drift", "card_spectrum", "misaligned", "alignment_failed")
#: The cube band a one-band condition acts on.
BAND_OF = {"motion blur": 550.0}
#: The base session: a diffusion session (the model at twice the fit's resolution) at this seed, not one
#: the defaults were tuned on (the demo uses 0–2, the tradeoff 61–63).
BASE_SEED = 71
COLUMNS = ("condition", "strength", "method", "seed", "size_px", "unit", *(f"error_{m}" for m in MAPS), "residual_over_noise", "sigma_cover",
           "hair_flagged", "sigma_cover_flagged",
           "iterations", "capped", "meets_targets", "missed", "detected", "message", "wall_s")
KEY = ("condition", "strength", "method", "seed", "size_px")


@dataclass
class StabilityPlan:
    """What one run measures: conditions with their strengths, methods, the sessions' side (px)."""

    conditions: dict[str, tuple]
    methods: list[str]
    size_px: int = 32
    seed: int = BASE_SEED
    quick: bool = False


#: The files written and the summary (``stability.json``'s content).
StabilityResult = AnalysisResult


def make_plan(quick: bool = False, seed: int = 0) -> StabilityPlan:
    """--quick: the strengths marked quick and three methods at 32²; the full run: everything."""
    conditions = {name: (c.quick if quick else c.strengths) for name, c in CONDITIONS.items()}
    return StabilityPlan(conditions, list(QUICK_METHODS if quick else METHODS), 32, BASE_SEED + seed, quick)


def run_stability(out: Path, *, quick: bool = False, seed: int = 0, device: str = "cpu", say=None,
                  plan: StabilityPlan | None = None) -> StabilityResult:
    """Measure ``plan`` into ``out`` (a rerun measures only the missing cells), then the summary and charts."""
    from .stability_charts import CellTargets, draw_heat_maps  # noqa: PLC0415

    start = time.perf_counter()
    plan = plan or make_plan(quick, seed)
    out.mkdir(parents=True, exist_ok=True)
    table = SweepTable(out / "stability.csv", COLUMNS, KEY)
    runner = _Runner(out, plan, device)
    table.run(_cases(plan), runner.measure, say=say, estimate_s=_estimate_s)
    summary = summarise(table.rows, plan)
    summary.update(plan={"quick": plan.quick, "seed": plan.seed, "size_px": plan.size_px, "device": device},
                   seconds=round(time.perf_counter() - start, 1))
    summary_path = out / "stability.json"
    summary_path.write_text(json.dumps(summary, indent=1) + "\n")
    charts = draw_heat_maps(table.rows, plan, out, CellTargets(TARGETS, RESIDUAL_AT_NOISE, SIGMA_COVER, names_cause))
    return StabilityResult(table.path, summary_path, charts, summary, time.perf_counter() - start)


def _cases(plan: StabilityPlan) -> list[dict]:
    """Each method's clean cell first, then the conditions."""
    base = {"seed": plan.seed, "size_px": plan.size_px}
    cases = [{"condition": "clean", "strength": "", "method": m, **base, "unit": ""} for m in plan.methods]
    for name, strengths in plan.conditions.items():
        cases += [{"condition": name, "strength": s, "method": m, **base, "unit": CONDITIONS[name].unit}
                  for s in strengths for m in plan.methods]
    return cases


def _estimate_s(case: dict) -> float:
    per_method = {"homogeneous": 2.0, "transport": 12.0, "adam": 15.0, "gn": 8.0}
    fresh = 20.0 if CONDITIONS.get(case["condition"], Condition("cube", (), (), "")).where == "capture" else 0.0
    return per_method.get(case["method"], 6.0) + fresh


# -- the conditions ----------------------------------------------------------------------------------------------


def _band(cube, nm: float) -> int:
    wl = cube.wavelength_nm.tolist()
    return min(range(len(wl)), key=lambda j: abs(wl[j] - nm))


def _shift_x(image: torch.Tensor, px: float) -> torch.Tensor:
    """``image`` ``(H, W)`` moved ``px`` pixels along x (bilinear, edges repeated): kornia's translate."""
    from kornia.geometry.transform import translate  # noqa: PLC0415

    t = torch.tensor([[float(px), 0.0]], dtype=image.dtype)
    return translate(image[None, None], t, mode="bilinear", padding_mode="border", align_corners=True)[0, 0]


def _perturb_cube(cube, truth_r: torch.Tensor, condition: str, strength):
    """The calibrated ``cube`` under a cube condition: a new ``Cube`` (``truth_r`` ``(L, H, W)``: the skin's
    true reflectance on the cube's grid, whose difference from the cube is the camera's noise)."""
    from kornia.filters import motion_blur  # noqa: PLC0415

    from ..formats.cube import Cube  # noqa: PLC0415

    r = cube.reflectance.clone().float()
    if condition == "noise":
        r = truth_r.float() + float(strength) * (r - truth_r.float())
    elif condition == "misregistration":
        for j in range(r.shape[0]):  # neighbouring bands `strength` apart: every other band moved
            r[j] = _shift_x(r[j], float(strength) * (0.5 if j % 2 else -0.5))
    elif condition == "motion blur":
        j = _band(cube, BAND_OF[condition])
        r[j] = motion_blur(r[j][None, None], int(strength), 0.0, 0.0, border_type="replicate")[0, 0]
    elif condition == "dead band":
        r[_band(cube, float(strength))] = 1e-4
    else:
        raise ValueError(f"{condition!r} is not a cube condition")
    return Cube(r, cube.mask.clone(), cube.header)


def _recorded_rig(manifest: dict, condition: str, strength) -> dict:
    """The session's ``manifest`` with the rig's certified Spectralon value off by ``strength`` (relative) at
    the condition's band, or at every band."""
    import copy  # noqa: PLC0415

    from ..formats.rig import rig_from_dict  # noqa: PLC0415

    out = copy.deepcopy(manifest)
    rig = rig_from_dict(out["rig"], "manifest rig")
    every = condition == "certificate all bands"
    wrong = None if every else float(condition.split()[1])
    out["rig"]["targets"]["spectralon_reflectance"] = {
        b.wavelength_nm: rig.targets.spectralon_at(b.wavelength_nm) * (1.0 + float(strength) if every or b.wavelength_nm == wrong else 1.0)
        for b in rig.bands}
    return out


def _capture_changes(condition: str, strength) -> tuple[dict, dict]:
    """A capture condition's changes to the demo's scene and to the simulation's settings."""
    if condition == "skin type":
        return {"base": {"preset": str(strength)}}, {}
    if condition == "hairs":
        return {"hairs": {"count": int(strength)}}, {}
    if condition == "flash drift":
        return {}, {"flash": {"jitter": float(strength)}}
    raise ValueError(f"{condition!r} is not a capture condition")


# -- measuring ----------------------------------------------------------------------------------------------------


class _Runner:
    """Measures one cell at a time; keeps the sessions it simulated and each method's clean notes."""

    def __init__(self, out: Path, plan: StabilityPlan, device: str) -> None:
        self.out, self.plan, self.device = out, plan, device

    def measure(self, case: dict) -> dict:
        from ..formats.cube import read_cube  # noqa: PLC0415
        from ..formats.errors import InputError  # noqa: PLC0415
        from ..formats.resources import ResourceError  # noqa: PLC0415
        from ..reconstruct import fit_cube, load_fit_settings  # noqa: PLC0415

        condition, strength, method = case["condition"], case["strength"], case["method"]
        spec, changes = self._session_of(condition, strength)
        where = CONDITIONS[condition].where if condition in CONDITIONS else "clean"
        folder = self._session(spec, changes, (condition, strength) if where == "calibration" else None)
        # the camera's noise: the cube the session's frames calibrate into with a right record, against its truth
        clean_cube = (self._session(spec, changes) if where == "calibration" else folder) / "calibrated" / "cube.exr"
        cube = read_cube(folder / "calibrated" / "cube.exr")
        truth_r = _truth_reflectance(folder / "session")
        calibration_notes = _calibration_flags(folder / "calibrated")
        noise_scale = float(strength) if condition == "noise" else 1.0
        if where == "cube":
            cube = _perturb_cube(cube, truth_r, condition, strength)
        settings = load_fit_settings(None, **METHODS[method])
        start = time.perf_counter()
        try:
            fit = fit_cube(cube, settings, device=self.device)
        except ResourceError:
            raise  # the machine's limit, not the data's: nothing to record
        except InputError as error:  # the data refused, with its reason: the user is told
            return {"detected": True, "message": f"refused: {error}", "meets_targets": False, "missed": "refused",
                    "wall_s": time.perf_counter() - start}
        wall = time.perf_counter() - start
        row = _against_truth(fit, folder / "session", truth_r, clean_cube, noise_scale)
        notes = [*calibration_notes, *fit.checks.warnings]
        verdict = cell_verdict(row)
        row.update(iterations=sum(lv["iterations"] for lv in fit.kept_levels),
                   capped=not all(lv["converged"] for lv in fit.kept_levels), meets_targets=not verdict, missed=" ".join(verdict),
                   detected=bool(notes), message=" | ".join(notes), wall_s=wall)
        return row

    def _session_of(self, condition: str, strength) -> tuple[SessionSpec, tuple[dict, dict]]:
        where = CONDITIONS[condition].where if condition in CONDITIONS else "clean"
        if where == "physics":
            return SessionSpec("transport", int(strength), 32), ({}, {})
        if where == "capture":
            return SessionSpec("diffusion", self.plan.seed, self.plan.size_px), _capture_changes(condition, strength)
        return SessionSpec("diffusion", self.plan.seed, self.plan.size_px), ({}, {})

    def _session(self, spec: SessionSpec, changes: tuple[dict, dict], recalibrate: tuple | None = None) -> Path:
        """The session's folder (``session/``, ``calibrated/``), simulated and calibrated once; with
        ``recalibrate`` (a calibration condition and strength) the base session calibrated anew under it."""
        scene_over, simulation_over = changes
        label = _slug(json.dumps([scene_over, simulation_over], sort_keys=True)) if (scene_over or simulation_over) else "base"
        folder = self.out / "sessions" / f"{spec.name}-{label}"
        if not ((folder / "calibrated" / "cube.exr").exists() and (folder / "session" / "truth" / "maps.exr").exists()):
            make_session(spec, folder, scene_over, simulation_over)
        if recalibrate is None:
            return folder
        condition, strength = recalibrate
        variant = self.out / "sessions" / f"{spec.name}-{_slug(condition)}-{cell_text(strength)}"
        if not (variant / "calibrated" / "cube.exr").exists():
            _recalibrated(folder, variant, condition, strength)
        return variant


def _recalibrated(base: Path, variant: Path, condition: str, strength) -> None:
    """``base``'s session copied to ``variant`` with the rig's record changed (``_recorded_rig``; its frames
    and truth as they were), and calibrated."""
    import shutil  # noqa: PLC0415

    from ..calibration import calibrate_session  # noqa: PLC0415

    if variant.exists():
        shutil.rmtree(variant)  # an incomplete one from an interrupted run
    shutil.copytree(base / "session", variant / "session")
    manifest = variant / "session" / "manifest.json"
    manifest.write_text(json.dumps(_recorded_rig(json.loads(manifest.read_text()), condition, strength), indent=1))
    calibrate_session(variant / "session", variant / "calibrated")


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9.]+", "-", text).strip("-")[:60]


def _truth_reflectance(session: Path) -> torch.Tensor:
    from ..formats.exr import read_spectral  # noqa: PLC0415

    return read_spectral(session / "truth" / "reflectance.exr")[0].double()


def _calibration_flags(calibrated: Path) -> list[str]:
    """The calibration's flags that say the cube may be wrong (``CALIBRATION_WARNINGS``)."""
    report = json.loads((calibrated / "calibration.json").read_text())
    return [f"calibration: {f.get('code', '')} {f.get('message', '')}".strip() for f in report.get("flags", [])
            if f.get("code") in CALIBRATION_WARNINGS]


def _against_truth(fit, session: Path, truth_r: torch.Tensor, clean_cube: Path, noise_scale: float) -> dict:
    """Each map's median error and σ coverage against the truth over the scored pixels, and the residual
    over the camera's noise (``clean_cube``'s difference from the truth, times ``noise_scale``)."""
    from ..demo import map_errors, scored_pixels, sigma_coverage  # noqa: PLC0415
    from ..formats.cube import read_cube  # noqa: PLC0415
    from ..model.patch.maps_io import read_maps  # noqa: PLC0415
    from ..reconstruct.diagnosis.checks import FLAG_BITS  # noqa: PLC0415

    truth = read_maps(session / "truth" / "maps.exr")
    keep = scored_pixels(fit.flags.cpu())
    hair = (((fit.flags.cpu().long() >> FLAG_BITS["hair"]) & 1) == 1) & (((fit.flags.cpu().long() >> FLAG_BITS["masked"]) & 1) == 0)
    errors = map_errors(truth, fit.maps, keep)
    row = {f"error_{m}": errors[m]["median_error"] for m in MAPS}
    cover = sigma_coverage(truth, fit.maps, fit.sigma, keep, TARGETS)
    cover_hair = sigma_coverage(truth, fit.maps, fit.sigma, hair, TARGETS) if bool(hair.any()) else {}
    row.update(sigma_cover=min(cover.values()), hair_flagged=int(hair.sum()),
               sigma_cover_flagged=min(cover_hair.values()) if cover_hair else math.nan)
    clean = read_cube(clean_cube).reflectance.double()
    used = fit.checks.bands_used.cpu()
    noise = noise_scale * (clean - truth_r)[used][:, keep]
    residual = fit.residual.detach().double().cpu()[used][:, keep]
    row["residual_over_noise"] = float(residual.pow(2).mean().sqrt() / noise.pow(2).mean().sqrt())
    return row


def cell_verdict(row: dict) -> list[str]:
    """The targets a cell misses (empty: it meets them all): maps over ``TARGETS``, the residual over
    ``RESIDUAL_AT_NOISE`` × the noise, σ covering less than ``SIGMA_COVER``."""
    missed = [m for m, t in TARGETS.items() if not float(row[f"error_{m}"]) <= t]
    if not float(row["residual_over_noise"]) <= RESIDUAL_AT_NOISE:
        missed.append("residual")
    if not float(row["sigma_cover"]) >= SIGMA_COVER:
        missed.append("sigma")
    flagged = row.get("sigma_cover_flagged")
    if flagged not in (None, "") and math.isfinite(float(flagged)) and not float(flagged) >= SIGMA_COVER:
        missed.append("sigma_flagged")
    return missed


# -- the summary -------------------------------------------------------------------------------------------------


def _truthy(value) -> bool:
    return str(value) in ("True", "true", "1")


def summarise(rows: list[dict], plan: StabilityPlan) -> dict:
    """Per method: the targets it misses on the clean session; each condition's breaking point (the
    strength nearest the clean data that misses a target the clean session meets); the silent cells (a
    target missed, nothing said), those told in words that do not name their condition, the false alarms."""
    methods = {}
    rows = [r for r in rows if (str(r["seed"]), str(r["size_px"])) == (cell_text(plan.seed), cell_text(plan.size_px))]
    for method in plan.methods:
        mine = [r for r in rows if r["method"] == method]
        breaking = {}
        clean = next((r for r in mine if r["condition"] == "clean"), None)
        missed_clean = set(str(clean["missed"]).split()) if clean is not None else set()
        for name, strengths in plan.conditions.items():
            cells = {str(r["strength"]): r for r in mine if r["condition"] == name}
            # a strength breaks the method where it misses a target the clean session meets
            failing = [s for s in strengths if cell_text(s) in cells and set(str(cells[cell_text(s)]["missed"]).split()) - missed_clean]
            breaking[name] = {"first_miss": _nearest_to_clean(failing, CONDITIONS[name]),
                              "missed": {cell_text(s): cells[cell_text(s)]["missed"] for s in failing}}
        silent = [{"condition": r["condition"], "strength": r["strength"], "missed": r["missed"]}
                  for r in mine if not _truthy(r["meets_targets"]) and not _truthy(r["detected"])]
        false_alarms = [{"condition": r["condition"], "strength": r["strength"], "message": r["message"]}
                        for r in mine if _truthy(r["meets_targets"]) and _truthy(r["detected"])]
        # a cell missing only what the clean session misses fails for the method's own reason (told on the clean
        # session); one missing more must name its condition
        unnamed = [{"condition": r["condition"], "strength": r["strength"], "missed": r["missed"], "message": r["message"]}
                   for r in mine if not _truthy(r["meets_targets"]) and _truthy(r["detected"]) and not names_cause(r)
                   and set(str(r["missed"]).split()) - missed_clean]
        methods[method] = {"missed_clean": sorted(missed_clean), "breaking_points": breaking, "silent": silent, "told_not_named": unnamed, "false_alarms": false_alarms,
                           "cells": len(mine), "meeting_targets": sum(_truthy(r["meets_targets"]) for r in mine)}
    return {"methods": methods, "silent_cells": sum(len(m["silent"]) for m in methods.values()),
            "told_not_named_cells": sum(len(m["told_not_named"]) for m in methods.values()),
            "targets": {**TARGETS, "residual_over_noise": RESIDUAL_AT_NOISE, "sigma_cover": SIGMA_COVER}}


def names_cause(row: dict) -> bool:
    """Whether the cell's warnings name its condition (``Condition.cause``; a clean cell has none to name)."""
    condition = CONDITIONS.get(row["condition"])
    if condition is None:
        return True
    return any(word in str(row["message"]) for word in condition.cause)


def _nearest_to_clean(failing: list, condition: Condition):
    """Of the failing strengths, the one nearest the clean data (numbers: nearest ``clean``, or 0)."""
    if not failing:
        return None
    numeric = [s for s in failing if isinstance(s, (int, float))]
    if len(numeric) == len(failing):
        ref = condition.clean if isinstance(condition.clean, (int, float)) else 0.0
        return min(numeric, key=lambda s: abs(math.log(s / ref)) if condition.clean else abs(s - ref))
    return failing[0]


# -- the command ------------------------------------------------------------------------------------------------


def stability(
    quick: bool = typer.Option(False, "--quick", help="Three methods and the marked strengths at 32² (under 15 min on 2 cores)."),
    out: Path = typer.Option(Path("stability"), "-o", "--out", help="Folder for stability.csv, stability.json and the heat maps; a rerun continues in it."),
    device: str = typer.Option("cpu", "--device", help="cpu, cuda or auto (CUDA when available)."),
    seed: int = typer.Option(0, "--seed", help="Shifts the base session's seed."),
    threads: "str | None" = typer.Option(None, "--threads", help=THREADS_HELP),
) -> None:
    """Map where each method fails: conditions × methods on simulated sessions with known truth; per cell
    whether the maps meet the targets and whether the calibration or the fit said so.

    Example: skinlayers stability --quick -o stability   (then open stability/stability_auto.png)
    """
    device = analysis_device(device)
    command_threads(threads)
    result = run_stability(out, quick=quick, seed=seed, device=device)
    for method, entry in result.summary["methods"].items():
        points = ", ".join(f"{c} {b['first_miss']}" for c, b in entry["breaking_points"].items() if b["first_miss"] is not None)
        clean = f" (clean: misses {', '.join(entry['missed_clean'])})" if entry["missed_clean"] else ""
        typer.echo(f"{method}: {entry['meeting_targets']}/{entry['cells']} cells meet the targets{clean}; breaks at: {points or 'nothing tried'}; "
                   f"silent failures: {len(entry['silent'])}, told but not named: {len(entry['told_not_named'])}")
    echo_outputs(result.table, result.summary_path, result.charts, result.seconds)


def register(app: typer.Typer) -> None:
    app.command("stability")(stability)
