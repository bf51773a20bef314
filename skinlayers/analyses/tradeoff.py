"""``skinlayers tradeoff``: what each choice of the model and the fit costs in time and buys in accuracy.

Three sweeps into one table (``tradeoff.csv``, one row per configuration and scene, written as each is
measured and resumed on a rerun), then the Pareto fronts, a summary (``tradeoff.json``) and charts:

- **forward**: the renderer's choices (``FORWARD_CONFIGS``: physics, coupling, Gaussians, series
  tolerance, blur, border, precision) on five heterogeneous scenes, each render's error per pixel against
  the shipped Monte Carlo (``skinlayers.analyses.truths``; its own noise taken out) and against the same physics
  rendered at full fidelity (``OWN_REFERENCE``: the numerical error alone);
- **inverse**: the fit's choices (``INVERSE_CONFIGS``: method, start, ``--model``, physics, levels,
  tolerance, map grids, precision, cube binning) on simulated sessions through the rig and the
  calibration, some rendered by the model at higher fidelity than the fit's, some by the transport
  reference; each map's median error against the truth, how often its σ covers the truth
  (``sigma_coverage_<map>``) and the residual against the cube's noise;
- **scale**: the default and the paper's fit against the cube's size, with the fitted exponent
  (time ∝ pixels^k).

A configuration's accuracy in one number (``score``): the mean over C_m, β_m, C_he and C_hd of its
median error over the demo's target for that map (``TARGETS``): 1 is every map at its target.
"""

from __future__ import annotations

import json
import math
import statistics
import time
from pathlib import Path
from typing import Optional

import torch
import typer

from .tradeoff_plan import (COLUMNS, FAITHFUL, FORWARD_CONFIGS, INVERSE_CONFIGS, KEY, MAPS, OWN_REFERENCE, SESSION_KEYS, TARGETS, SessionSpec,
                            TradeoffPlan, forward_cases, inverse_cases, make_plan, scale_cases)
from .sweep import AnalysisResult, PeakMemory, SweepTable, analysis_device, echo_outputs, pareto_front, time_to_front
from ..formats.threads import THREADS_HELP, command_threads

__all__ = ["COLUMNS", "FORWARD_CONFIGS", "INVERSE_CONFIGS", "TARGETS", "SessionSpec", "TradeoffPlan", "TradeoffResult",
           "make_plan", "run_tradeoff"]

#: The files written and the summary (``tradeoff.json``'s content).
TradeoffResult = AnalysisResult


def run_tradeoff(out: Path, *, quick: bool = False, cube: Path | None = None, device: str = "cpu", seed: int = 0,
                 say=None, plan: TradeoffPlan | None = None) -> TradeoffResult:
    """Measure ``plan`` (default ``make_plan(quick, seed, cube)``) into ``out``: the table, the summary and
    the charts. A rerun into the same folder measures only the rows that are missing."""
    from .tradeoff_charts import draw_charts  # noqa: PLC0415

    start = time.perf_counter()
    plan = plan or make_plan(quick, seed, cube)
    out.mkdir(parents=True, exist_ok=True)
    table = SweepTable(out / "tradeoff.csv", COLUMNS, KEY)
    runner = _Runner(out, device, say, plan)
    table.run(forward_cases(plan), runner.forward, say=say, estimate_s=lambda c: 2.0)
    table.run(inverse_cases(plan), runner.inverse, say=say, estimate_s=_estimate_s)
    _copy_twins(table, scale_cases(plan))
    table.run(scale_cases(plan), runner.inverse, say=say, estimate_s=_estimate_s)
    summary = summarise(table.rows)
    _rewrite_with_front(table, summary)
    summary.update(plan={"quick": plan.quick, "seed": seed, "device": device, "cube": str(cube) if cube else None,
                         "threads": torch.get_num_threads()}, seconds=round(time.perf_counter() - start, 1))
    summary_path = out / "tradeoff.json"
    summary_path.write_text(json.dumps(summary, indent=1) + "\n")
    charts = draw_charts(table.rows, summary, out)
    return TradeoffResult(table.path, summary_path, charts, summary, time.perf_counter() - start)


# -- the cases ------------------------------------------------------------------------------------------------


def _copy_twins(table: SweepTable, cases: list[dict]) -> None:
    """A scale case that is an inverse case already measured (the same configuration on the same session)
    takes that row instead of fitting again."""
    measured = {(r["config"], r["scene"]): r for r in table.rows if r["part"] == "inverse"}
    done = table.done()
    for case in cases:
        twin = measured.get((case["config"], case["scene"]))
        if twin is not None and table.key_of(case) not in done:
            table.append({**twin, "part": "scale", "pareto": ""})


def _estimate_s(case: dict) -> float:
    """A rough cost for the time-left estimate: pixels, and the paper's forward differences."""
    px = float(case.get("size_px") or 32) ** 2
    return px / 1024.0 * (20.0 if case.get("method") == "paper-fd" else 4.0)


# -- measuring -------------------------------------------------------------------------------------------------


class _Runner:
    """Measures one case at a time; keeps the sessions, truths and reference renders it has made."""

    def __init__(self, out: Path, device: str, say, plan: TradeoffPlan) -> None:
        self.out, self.device, self.say, self.cube, self.configs = out, device, say, plan.cube, plan.configs
        self._own: dict = {}
        self._faithful = None

    # forward
    def forward(self, case: dict) -> dict:
        from .truths import forward_scene, forward_truth, scene_profile  # noqa: PLC0415

        over = FORWARD_CONFIGS[case["config"]]
        scene = forward_scene(case["scene"])
        _render(scene, over, self.device)  # the tables built, the caches warm: the render's own time follows
        seconds, cpu_s, peak, image = _timed(lambda: _render(scene, over, self.device), self.device)
        profile = scene_profile(scene, image)
        mc, mc_se = forward_truth(case["scene"])
        keep = scene.keep
        rel = ((profile - mc) / mc)[:, keep]
        noise = (mc_se / mc)[:, keep]
        excess = float(rel.pow(2).mean() - noise.pow(2).mean())
        own = scene_profile(scene, self._own_render(scene, over))
        return {"wall_s": seconds, "cpu_s": cpu_s, "peak_mb": peak,
                "error_vs_mc": math.sqrt(max(excess, 0.0)), "mc_std_error": float(noise.pow(2).mean().sqrt()),
                "error_vs_own": float(((profile - own) / own)[:, keep].pow(2).mean().sqrt())}

    def _own_render(self, scene, over: dict) -> torch.Tensor:
        physics = {k: over[k] for k in ("profiles",) if k in over}
        coupling = over.get("render", {}).get("coupling")
        key = (scene.name, physics.get("profiles"), coupling)
        if key not in self._own:
            ref = {**OWN_REFERENCE, **physics, "render": {**OWN_REFERENCE["render"], **({"coupling": coupling} if coupling else {})}}
            self._own[key] = _render(scene, ref, self.device)
        return self._own[key]

    # inverse and scale
    def inverse(self, case: dict) -> dict:
        from ..formats.cube import read_cube  # noqa: PLC0415
        from ..reconstruct import fit_cube, load_fit_settings  # noqa: PLC0415

        over = self.configs[case["config"]]
        k = int(over.get("bin", 1))
        settings = load_fit_settings(None, **{key: v for key, v in over.items() if key not in SESSION_KEYS})
        if case["truth"] == "none":
            cube_path, session = self.cube, None
        else:
            spec = _spec_of(case)
            cube_path, session = self._session(spec)
        cube = _binned(read_cube(cube_path), k)
        _warm_up(settings, cube, self.device)
        seconds, cpu_s, peak, fit = _timed(lambda: fit_cube(cube, settings, device=self.device), self.device)
        row = {"wall_s": seconds, "cpu_s": cpu_s, "peak_mb": peak, "converged": all(lv["converged"] for lv in fit.kept_levels),
               "band_bias_max": max((abs(b) for b in fit.band_bias.values()), default=math.nan),
               "iterations": sum(lv["iterations"] for lv in fit.kept_levels)}
        if session is None:
            row.update(self._against_faithful(case, fit))
        else:
            row.update(_against_truth(fit, cube, session, k))
        return row

    def _session(self, spec: SessionSpec) -> tuple[Path, Path]:
        """The session's calibrated cube and folder, simulated and calibrated once into ``out/sessions``."""
        from ..formats.cube import CUBE_NAME  # noqa: PLC0415

        folder = self.out / "sessions" / spec.name
        cube = folder / "calibrated" / CUBE_NAME
        if not (cube.exists() and (folder / "session" / "truth" / "maps.exr").exists()):
            make_session(spec, folder)
        return cube, folder / "session"

    def _against_faithful(self, case: dict, fit) -> dict:
        if case["config"] == FAITHFUL:
            self._faithful = fit.maps
        ref = self._faithful
        if ref is None or ref.shape != fit.maps.shape:
            return {}
        from ..demo import map_errors  # noqa: PLC0415
        from ..reconstruct.diagnosis.checks import FLAG_BITS  # noqa: PLC0415

        visible = ((fit.flags.cpu() >> FLAG_BITS["masked"]) & 1) == 0
        errors = map_errors(ref, fit.maps, visible)
        return _error_columns(errors)


def make_session(spec: SessionSpec, folder: Path, scene_over: dict | None = None, simulation_over: dict | None = None) -> None:
    """Simulate and calibrate ``spec`` into ``folder`` (``session/`` with ``truth/``, ``calibrated/``): the
    demo's scene and rig at the session's size; a transport session photographs the shipped Monte Carlo.
    ``scene_over``, ``simulation_over``: changes to the demo's scene and to the simulation's settings (a
    diffusion session only: the transport truths were rendered for the demo's scene)."""
    import shutil  # noqa: PLC0415

    import yaml  # noqa: PLC0415

    from ..acquire.simulator.simulation_settings import default_simulation_path  # noqa: PLC0415
    from ..calibration import calibrate_session  # noqa: PLC0415
    from ..demo import simulate_session  # noqa: PLC0415
    from .truths import demo_scene, session_rig  # noqa: PLC0415
    from ..formats.settings import merge  # noqa: PLC0415

    if folder.exists():
        shutil.rmtree(folder)  # an incomplete session from an interrupted run
    folder.mkdir(parents=True)
    scene = folder / "scene.yaml"
    truth, kept = {}, None
    if spec.physics == "transport":
        from .truths import session_renders  # noqa: PLC0415

        record, kept = session_renders(spec.seed)
        scene.write_text(yaml.safe_dump(record["scene"], sort_keys=False))
        truth = {"physics": "transport", "photons": record["photons_per_node"]}
    else:
        scene.write_text(yaml.safe_dump(merge(demo_scene(), scene_over or {}), sort_keys=False))
    simulation = None
    if simulation_over:
        simulation = folder / "simulation.yaml"
        simulation.write_text(yaml.safe_dump(merge(yaml.safe_load(default_simulation_path().read_text()), simulation_over), sort_keys=False))
    simulate_session(folder / "session", session_rig(spec.size_px, spec.bands), scene, spec.seed, "cpu", truth, kept_renders=kept,
                     simulation=simulation)
    calibrate_session(folder / "session", folder / "calibrated")


def _spec_of(case: dict) -> SessionSpec:
    physics, seed, size, *bands = case["scene"].split("-")
    return SessionSpec(physics, int(seed[1:]), int(size[:-2]), *(int(b[:-1]) for b in bands))


def _render(scene, over: dict, device: str) -> torch.Tensor:
    """``scene``'s exitance ``(L, H, W)`` by the renderer with ``over`` (``ForwardScene.render_maps``)."""
    from ..model import ModelSettings  # noqa: PLC0415
    from ..model.render.renderer import SkinRenderer  # noqa: PLC0415
    from .truths import FORWARD_WAVELENGTHS_NM  # noqa: PLC0415

    dtype = torch.float64 if over.get("dtype") == "float64" else torch.float32
    settings = ModelSettings.model_validate({k: v for k, v in over.items() if k != "dtype"})
    wl = torch.tensor(FORWARD_WAVELENGTHS_NM, dtype=dtype, device=device)
    with torch.no_grad():
        return SkinRenderer(settings).render(scene.render_maps().to(device=device, dtype=dtype), scene.light, wl).exitance[0].double().cpu()


#: Work shorter than this (s) is timed REPEATS times and the fastest kept: a short step's time is
#: at the mercy of whatever else the machine does for a moment.
REPEAT_BELOW_S = 2.0
REPEATS = 3


def _timed(work, device: str):
    """Wall and CPU seconds, peak memory (MB) and the result of ``work()`` (short work: the fastest of
    ``REPEATS``, the largest peak)."""
    best, peak, result = None, 0.0, None
    for _ in range(REPEATS):
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        with PeakMemory(device) as memory:
            wall0, cpu0 = time.perf_counter(), time.process_time()
            result = work()
            if device.startswith("cuda"):
                torch.cuda.synchronize()
            wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
        peak = max(peak, memory.device_mb if memory.device_mb is not None else memory.peak_mb)
        best = (wall, cpu) if best is None or wall < best[0] else best
        if wall >= REPEAT_BELOW_S:
            break
    return best[0], best[1], peak, result


#: The warm-up fit's crop of the cube (px) and iterations.
WARM_UP_PX = 16


def _warm_up(settings, cube, device: str) -> None:
    """Before the clock starts: the fit's tables built or loaded (a one-off cost, kept on disk) and one
    short fit of the cube's centre with the same settings (the point tables, the first calls of
    each kernel: costs a process pays once, not a fit)."""
    from ..formats.cube import Cube  # noqa: PLC0415
    from ..reconstruct import fit_cube  # noqa: PLC0415

    n = min(WARM_UP_PX, cube.shape[1], cube.shape[2])
    c = cube.shape[1] // 2 - n // 2
    centre = Cube(cube.reflectance[:, c:c + n, c:c + n].clone(), torch.ones(n, n, dtype=torch.bool), cube.header)
    short = {"max_iterations": 1, "coarsest_px": 0}
    if settings.method in ("paper-fd", "adam"):  # their first-order loops have no first-call costs of their own
        short.update(method="gn-hom", free_scale=False)
    fit_cube(centre, settings.model_copy(update=short), device=device)


def _binned(cube, k: int):
    """``cube`` with k×k pixels averaged into one (a pixel kept where all k² were), its pixel k times wider."""
    if k == 1:
        return cube
    import torch.nn.functional as F  # noqa: PLC0415

    from ..formats.cube import Cube  # noqa: PLC0415

    h, w = (cube.shape[1] // k) * k, (cube.shape[2] // k) * k
    r = F.avg_pool2d(cube.reflectance[None, :, :h, :w].float(), k)[0]
    m = F.avg_pool2d(cube.mask[None, None, :h, :w].float(), k)[0, 0] > 0.999
    header = cube.header.model_copy(update={"mm_per_pixel": cube.header.mm_per_pixel * k})
    return Cube(r, m, header)


def _against_truth(fit, cube, session: Path, k: int) -> dict:
    """Each map's median error against the session's truth (pixels not masked nor flagged for a high
    residual), and the residual's RMS over the cube's noise against its true reflectance."""
    import torch.nn.functional as F  # noqa: PLC0415

    from ..demo import map_errors, scored_pixels, sigma_coverage  # noqa: PLC0415
    from ..formats.exr import read_spectral  # noqa: PLC0415
    from ..model.patch.maps_io import read_maps  # noqa: PLC0415

    keep = scored_pixels(fit.flags.cpu())
    truth = read_maps(session / "truth" / "maps.exr")
    errors = map_errors(truth, fit.maps, keep)
    cover = sigma_coverage(truth, fit.maps, fit.sigma, keep, TARGETS)
    truth_r = read_spectral(session / "truth" / "reflectance.exr")[0].double()
    if k > 1:
        truth_r = F.avg_pool2d(truth_r[None], k)[0]
    used = fit.checks.bands_used.cpu()
    noise = (cube.reflectance.double() - truth_r)[used][:, keep]
    residual = fit.residual.detach().double().cpu()[used][:, keep]
    return {**_error_columns(errors), **{f"sigma_coverage_{m}": v for m, v in cover.items()},
            "residual_over_noise": float(residual.pow(2).mean().sqrt() / noise.pow(2).mean().sqrt())}


def _error_columns(errors: dict) -> dict:
    row = {f"error_{m}": errors[m]["median_error"] for m in MAPS}
    row["score"] = score(row)
    return row


def score(row: dict) -> float:
    """The mean over the targeted maps of the median error over its target (1: every map at its target)."""
    values = [float(row[f"error_{m}"]) / t for m, t in TARGETS.items() if row.get(f"error_{m}") not in (None, "")]
    return sum(values) / len(values) if values else math.nan


# -- the fronts and the summary ------------------------------------------------------------------------------


def _float(value) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan


def summarise(rows: list[dict]) -> dict:
    """Per group (forward; inverse on each truth's sessions), each configuration's mean time and error over
    its scenes, whether it is on the Pareto front, and how much slower than the front at its error; the
    default's standing, the paper's against it; the scale's exponents."""
    groups: dict[str, dict] = {}
    for part, truth, error_key in (("forward", "transport", "error_vs_mc"), ("forward", "own", "error_vs_own"),
                                   ("inverse", "diffusion", "score"), ("inverse", "transport", "score"), ("inverse", "none", "score")):
        chosen = [r for r in rows if r["part"] == part and (part == "forward" or r["truth"] == truth)]
        if not chosen:
            continue
        configs = list(dict.fromkeys(r["config"] for r in chosen))
        time_s = [statistics.fmean(_float(r["wall_s"]) for r in chosen if r["config"] == c) for c in configs]
        error = [statistics.fmean(_float(r[error_key]) for r in chosen if r["config"] == c) for c in configs]
        front = pareto_front(time_s, error)
        entries = {c: {"wall_s": round(t, 4), "error": float(f"{e:.4g}") if math.isfinite(e) else None, "pareto": f,
                       "time_to_front": round(time_to_front(time_s, error, i), 3) if math.isfinite(e) else None}
                   for i, (c, t, e, f) in enumerate(zip(configs, time_s, error, front))}
        name = f"{part} vs {'Monte Carlo' if truth == 'transport' and part == 'forward' else truth}"
        group = {"part": part, "truth": truth, "error": error_key, "scenes": sorted({r["scene"] for r in chosen}), "configs": entries}
        if "default" in entries:
            d = entries["default"]
            group["default_on_front"] = d["pareto"]
            group["default_within_10pct_of_front"] = d["time_to_front"] is not None and d["time_to_front"] <= 1.10
        if "paper" in entries and "default" in entries:
            p, d = entries["paper"], entries["default"]
            group["paper_over_default_time"] = round(p["wall_s"] / d["wall_s"], 2)
            group["default_error_at_most_paper"] = d["error"] is not None and p["error"] is not None and d["error"] <= p["error"]
        groups[name] = group
    return {"groups": groups, "scale": _scale_summary(rows), "targets": TARGETS}


def _scale_summary(rows: list[dict]) -> dict:
    out = {}
    for config in dict.fromkeys(r["config"] for r in rows if r["part"] == "scale"):
        chosen = sorted((r for r in rows if r["part"] == "scale" and r["config"] == config), key=lambda r: int(r["size_px"]))
        px = [int(r["size_px"]) ** 2 for r in chosen]
        t = [_float(r["wall_s"]) for r in chosen]
        entry = {"pixels": px, "wall_s": [round(v, 2) for v in t], "peak_mb": [round(_float(r["peak_mb"]), 1) for r in chosen]}
        if len(px) >= 2:
            entry["exponent"] = round(_slope([math.log(p) for p in px], [math.log(v) for v in t]), 3)
        out[config] = entry
    return out


def _slope(x: list[float], y: list[float]) -> float:
    mx, my = statistics.fmean(x), statistics.fmean(y)
    return sum((a - mx) * (b - my) for a, b in zip(x, y)) / sum((a - mx) ** 2 for a in x)


def _rewrite_with_front(table: SweepTable, summary: dict) -> None:
    """Each row's ``pareto``: its configuration on its group's front (forward: against the Monte Carlo)."""
    groups = summary["groups"]
    for row in table.rows:
        name = "forward vs Monte Carlo" if row["part"] == "forward" else f"inverse vs {row['truth']}"
        entry = groups.get(name, {}).get("configs", {}).get(row["config"])
        row["pareto"] = "" if entry is None else str(entry["pareto"])
    table.rewrite()


# -- the command ----------------------------------------------------------------------------------------------


def tradeoff(
    quick: bool = typer.Option(False, "--quick", help="The main choices on one session of each physics, scale to 64² (about 10 min on 2 cores)."),
    out: Path = typer.Option(Path("tradeoff"), "-o", "--out", help="Folder for tradeoff.csv, tradeoff.json and the charts; a rerun continues in it."),
    cube: Optional[Path] = typer.Option(None, "--cube", help="Your own cube.exr (no truth): each configuration against the most faithful one's maps."),
    device: str = typer.Option("cpu", "--device", help="cpu, cuda or auto (CUDA when available)."),
    seed: int = typer.Option(0, "--seed", help="Shifts the simulated (diffusion) sessions' seeds; the transport sessions are the shipped ones."),
    threads: Optional[str] = typer.Option(None, "--threads", help=THREADS_HELP),
) -> None:
    """Chart speed against accuracy: the renderer's and the fit's choices, each timed and measured against
    a truth (Monte Carlo, simulated sessions), with the Pareto front.

    Example: skinlayers tradeoff --quick -o tradeoff   (then open tradeoff/tradeoff_inverse.png)
    """
    from ..formats.errors import InputError  # noqa: PLC0415

    device = analysis_device(device)
    command_threads(threads)
    if cube is not None and not cube.is_file():
        raise InputError(f"--cube {cube}: no such file")
    result = run_tradeoff(out, quick=quick, cube=cube, device=device, seed=seed)
    for name, group in result.summary["groups"].items():
        if "default_on_front" in group:
            d = group["configs"]["default"]
            typer.echo(f"{name}: default {d['wall_s']:.3g} s, error {d['error']}, on the front: {group['default_on_front']}, "
                       f"{d['time_to_front']:.2f}× the front's time at its error"
                       + (f"; the paper's scheme {group['paper_over_default_time']:.1f}× the default's time" if "paper_over_default_time" in group else ""))
    echo_outputs(result.table, result.summary_path, result.charts, result.seconds)


def register(app: typer.Typer) -> None:
    app.command("tradeoff")(tradeoff)
