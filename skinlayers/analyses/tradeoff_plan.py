"""The tradeoff's plan (``skinlayers tradeoff``, ``tradeoff.py`` measures it): every configuration of the
renderer and the fit it can sweep, the sessions it fits, the table's columns, and the cases of a run —
the forward scenes, the inverse sessions and the scale sizes — with the knobs each case's row records."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path


from ..reconstruct.diagnosis.checks import MAP_TARGETS
from ..reconstruct.mapfit.first_order import FIRST_ORDER_CAP

__all__ = ["COLUMNS", "FAITHFUL", "FORWARD_CONFIGS", "INVERSE_CONFIGS", "KEY", "KNOBS", "MAPS", "OWN_REFERENCE", "TARGETS",
           "SessionSpec", "TradeoffPlan", "all_configs", "forward_cases", "inverse_cases", "make_plan", "scale_cases"]

#: The demo's targets per map (relative median error; β_m absolute), the same the fit's precision check and
#: the stability analysis use.
TARGETS = MAP_TARGETS
MAPS = ("C_m", "beta_m", "C_he", "C_bc", "C_hd")
#: DWRR08's renderer: its 18 Gaussians from 0.01 mm, the series cut after six terms with no closure,
#: Gaussians under half a pixel taken as the identity (§4.3–4.5).
PAPER_RENDER = {"tables": {"n_gaussians": 18, "gaussian_std_min_mm": 0.01},
                "render": {"series_closure": False, "max_series_terms": 6, "series_tolerance": 1e-3, "identity_below_px": 0.5}}
#: The forward configurations: model settings over the defaults (``dtype``: the render's precision).
FORWARD_CONFIGS: dict[str, dict] = {
    "default": {},
    "paper": PAPER_RENDER,
    "transport": {"profiles": "transport"},
    "transport, segment": {"profiles": "transport", "render": {"coupling": "segment"}},
    "segment": {"render": {"coupling": "segment"}},
    "15 Gaussians": {"tables": {"n_gaussians": 15, "gaussian_std_min_mm": 0.02}},
    "series 0.1": {"render": {"series_tolerance": 0.1}},
    "series 1e-3": {"render": {"series_tolerance": 1e-3}},
    "blur fft": {"render": {"blur": "fft"}},
    "blur chain": {"render": {"blur": "chain"}},
    "border 1 mm": {"render": {"border_mm": 1.0}},
    "float64": {"dtype": "float64"},
}
#: The numerical reference of each physics: the same model with every approximation tightened.
OWN_REFERENCE = {"render": {"blur": "fft", "series_tolerance": 1e-5, "max_series_terms": 40, "identity_below_px": 0.0,
                            "border_mm": 8.0}, "dtype": "float64"}
_ALL_PER_PIXEL = dict.fromkeys(MAPS, 0.0)
#: DWRR08's fit ran 200–500 gradient steps (§6.3); first-order methods take up to FIRST_ORDER_CAP ×
#: max_iterations steps (reconstruct/mapfit/first_order.py), so the paper's scheme is capped at 300.
PAPER_STEPS = 300
#: --quick: the paper's scheme at its fewest steps (§6.3: 200), on the transport sessions only (each
#: step costs 1 + N_PARAMS renders, so 300 steps are minutes a session: docs/tradeoff.md, "What is
#: swept, and against which truth").
QUICK_PAPER_STEPS = 200
#: On the 32² diffusion session: the Monte Carlo's is 64², where each step costs four times the pixels.
QUICK_PAPER_TRUTHS = ("diffusion",)
#: The scale sweep's paper: its time per step is what grows with the cube (the steps do not), so it runs
#: SCALE_PAPER_STEPS steps (no convergence test) and its time is per that many steps.
SCALE_PAPER_STEPS = 10
#: The fit configurations: fit settings over the defaults (``bin``: the cube binned k×k before the fit).
INVERSE_CONFIGS: dict[str, dict] = {
    "default": {},
    "fixed": {"forward": "heterogeneous"},
    "homogeneous": {"forward": "homogeneous"},
    "paper": {"method": "paper-fd", "start": "paper", "forward": "heterogeneous", "map_cell_mm": _ALL_PER_PIXEL,
              "free_scale": True, "robust_passes": 0, "max_iterations": PAPER_STEPS // FIRST_ORDER_CAP},
    "paper model, gn-hom": {"forward": "heterogeneous", "map_cell_mm": _ALL_PER_PIXEL, "free_scale": True},
    # each physics by name, whatever the default is (today "diffusion" is the default's)
    "diffusion": {"model": {"profiles": "diffusion"}},
    "transport": {"model": {"profiles": "transport"}},
    "transport, diffusion's grids": {"model": {"profiles": "transport"}, "map_cell_mm": {"C_he": 0.0, "C_hd": 0.375}},
    # under transport a dermal-blood change spreads its light wider than diffusion draws it
    # (docs/transport.md): C_hd on nodes the light can tell apart, and the coupling that draws that spread
    "transport, C_hd 0.75 mm": {"model": {"profiles": "transport"}, "map_cell_mm": {"C_hd": 0.75}},
    "transport, segment": {"model": {"profiles": "transport", "render": {"coupling": "segment"}}},
    "transport, segment, C_hd 0.75 mm": {"model": {"profiles": "transport", "render": {"coupling": "segment"}},
                                         "map_cell_mm": {"C_hd": 0.75}},
    "transport, grids auto": {"model": {"profiles": "transport"}, "map_grids": "auto", "forward": "heterogeneous"},
    # the loss's band weights, each physics with the other's (by default noise with transport, equal with diffusion)
    "transport, equal weights": {"model": {"profiles": "transport"}, "band_weights": "equal"},
    "diffusion, noise weights": {"model": {"profiles": "diffusion"}, "band_weights": "noise"},
    "gn": {"method": "gn", "forward": "heterogeneous"},
    "adam": {"method": "adam", "forward": "heterogeneous"},
    "start paper": {"start": "paper"},
    "one level": {"coarsest_px": 0},
    "levels to 8 px": {"coarsest_px": 8},
    "ftol 1e-2": {"ftol": 1e-2},
    "ftol 1e-4": {"ftol": 1e-4},
    "grids auto": {"map_grids": "auto", "forward": "heterogeneous"},
    "per-pixel maps": {"forward": "heterogeneous", "map_cell_mm": _ALL_PER_PIXEL},
    "float64": {"dtype": "float64"},
    "binned 2x2": {"bin": 2},
    # the session through the hyperspectral rig (31 bands of 10 nm, 400–700 nm): its own scene, with "-31b"
    # in its name; diffusion truths only (the Monte Carlo sessions were rendered at the nine bands)
    "31 bands": {"bands": 31},
    "31 bands, noise weights": {"bands": 31, "band_weights": "noise"},
}
#: Keys of a configuration that choose its session or cube, not the fit's settings.
SESSION_KEYS = ("bin", "bands")
#: --quick runs these (the full run all of them).
QUICK_FORWARD = ("default", "paper", "transport", "transport, segment", "series 0.1", "series 1e-3", "blur fft", "float64")
#: The scale sweep's configurations.
SCALE_CONFIGS: dict[str, dict] = {
    "default": {},
    "fixed": {"forward": "heterogeneous"},
    f"paper, {SCALE_PAPER_STEPS} steps": {**{k: v for k, v in INVERSE_CONFIGS["paper"].items() if k != "max_iterations"},
                                          "max_iterations": SCALE_PAPER_STEPS // FIRST_ORDER_CAP, "ftol": 1e-12},
}
QUICK_INVERSE = ("default", "fixed", "homogeneous", "paper", "transport", "transport, C_hd 0.75 mm", "transport, segment",
                 "transport, equal weights", "ftol 1e-2", "binned 2x2", "31 bands")
#: Configurations measured only on sessions of these truths, in every run.
ONLY_ON = {"31 bands": ("diffusion",), "31 bands, noise weights": ("diffusion",)}
QUICK_SCALE_PX = (32, 64)
#: Marked on the charts.
MARKED = {"default": "default (--model auto)", "fixed": "--model fixed", "paper": "DWRR08's scheme"}
#: With --cube (no truth): the configuration whose maps the others are measured against.
FAITHFUL = "faithful"
FAITHFUL_CONFIG = {"forward": "heterogeneous", "dtype": "float64", "ftol": 1e-4, "model": {"profiles": "transport"}}
#: The diffusion sessions' seeds are these plus --seed (none of them tuned a diffusion default; with --seed 0
#: they share their skin with the Monte Carlo sessions, whose seeds chose transport's grids and floor).
DIFFUSION_SEED_BASE = 61
#: Knob columns: what each row's configuration set (empty: the default).
KNOBS = ("physics", "coupling", "gaussians", "series_tolerance", "blur", "border_mm", "dtype", "method", "start", "model",
         "coarsest_px", "ftol", "map_grids", "map_cells", "band_weights", "free_scale", "robust_passes", "max_iterations", "bin")
COLUMNS = ("part", "config", "scene", "truth", "size_px", *KNOBS, "wall_s", "cpu_s", "peak_mb",
           *(f"error_{m}" for m in MAPS), "score", *(f"sigma_coverage_{m}" for m in TARGETS), "error_vs_mc", "mc_std_error", "error_vs_own", "residual_over_noise", "band_bias_max",
           "converged", "iterations", "pareto")
KEY = ("part", "config", "scene")


@dataclass(frozen=True)
class SessionSpec:
    """A simulated session: its truth's physics, seed, cube side (px) and the rig's bands (the default
    rig's nine, or the hyperspectral rig's 31: ``skinlayers.analyses.truths.session_rig``)."""

    physics: str
    seed: int
    size_px: int
    bands: int = 9

    @property
    def name(self) -> str:
        return f"{self.physics}-s{self.seed}-{self.size_px}px" + ("" if self.bands == 9 else f"-{self.bands}b")


def all_configs() -> dict[str, dict]:
    """Every fit configuration a plan can name: the faithful one, the inverse sweep's, the scale sweep's."""
    return {FAITHFUL: FAITHFUL_CONFIG, **INVERSE_CONFIGS, **SCALE_CONFIGS}


@dataclass
class TradeoffPlan:
    """What one run measures."""

    forward: list[str]
    inverse: list[str]
    sessions: list[SessionSpec]
    scale_sizes: list[int]
    scale_configs: list[str]
    scale_seed: int
    cube: Path | None = None
    quick: bool = False
    #: The inverse configurations by name (``INVERSE_CONFIGS`` with the run's own changes).
    configs: dict[str, dict] = field(default_factory=lambda: all_configs())
    #: Configurations measured only on sessions of these truths.
    only_on: dict[str, tuple[str, ...]] = field(default_factory=dict)


def make_plan(quick: bool = False, seed: int = 0, cube: Path | None = None) -> TradeoffPlan:
    """The quick run: the main choices, one session of each physics (diffusion at 32², the Monte Carlo at
    64², the size a user fits), scale to 64²; the full run: every choice, three sessions each, scale to 512²."""
    from .truths import SESSION_PX, SESSION_PX_64, SESSION_SEEDS_64  # noqa: PLC0415

    n = 1 if quick else 3
    configs = all_configs()
    if quick:
        configs["paper"] = {**configs["paper"], "max_iterations": QUICK_PAPER_STEPS // FIRST_ORDER_CAP}
    sessions = [SessionSpec("diffusion", DIFFUSION_SEED_BASE + seed + i, SESSION_PX) for i in range(n)]
    sessions += [SessionSpec("transport", s, SESSION_PX_64) for s in SESSION_SEEDS_64[:n]]
    return TradeoffPlan(
        forward=list(QUICK_FORWARD if quick else FORWARD_CONFIGS),
        inverse=list(QUICK_INVERSE if quick else INVERSE_CONFIGS) if cube is None else
        [FAITHFUL, *(c for c in (QUICK_INVERSE if quick else INVERSE_CONFIGS) if "bands" not in configs[c])],
        sessions=[] if cube is not None else sessions,
        scale_sizes=[] if cube is not None else (list(QUICK_SCALE_PX) if quick else [64, 128, 256, 512]),
        scale_configs=["default", "fixed"] if quick else list(SCALE_CONFIGS), scale_seed=DIFFUSION_SEED_BASE + seed, cube=cube,
        quick=quick, configs=configs, only_on={**ONLY_ON, **({"paper": QUICK_PAPER_TRUTHS} if quick else {})})


def forward_cases(plan: TradeoffPlan) -> list[dict]:
    from .truths import FORWARD_SCENES  # noqa: PLC0415

    return [{"part": "forward", "config": c, "scene": s, "truth": "transport", **_forward_knobs(FORWARD_CONFIGS[c])}
            for c in plan.forward for s in FORWARD_SCENES]


def inverse_cases(plan: TradeoffPlan) -> list[dict]:
    if plan.cube is not None:
        return [{"part": "inverse", "config": c, "scene": plan.cube.name, "truth": "none", **_inverse_knobs(plan.configs[c])}
                for c in plan.inverse]
    return [{"part": "inverse", "config": c, "scene": replace(s, bands=plan.configs[c].get("bands", s.bands)).name,
             "truth": s.physics, "size_px": s.size_px, **_inverse_knobs(plan.configs[c])}
            for s in plan.sessions for c in plan.inverse if s.physics in plan.only_on.get(c, (s.physics,))]


def scale_cases(plan: TradeoffPlan) -> list[dict]:
    return [{"part": "scale", "config": c, "scene": SessionSpec("diffusion", plan.scale_seed, n).name, "truth": "diffusion",
             "size_px": n, **_inverse_knobs(plan.configs[c])} for n in plan.scale_sizes for c in plan.scale_configs]


def _forward_knobs(over: dict) -> dict:
    from ..model import ModelSettings  # noqa: PLC0415

    s = ModelSettings.model_validate({k: v for k, v in over.items() if k != "dtype"})
    return {"physics": s.profiles, "coupling": s.render.coupling, "gaussians": s.tables.n_gaussians,
            "series_tolerance": s.render.series_tolerance, "blur": s.render.blur, "border_mm": s.render.border_mm,
            "dtype": over.get("dtype", "float32")}


def _inverse_knobs(over: dict) -> dict:
    from ..reconstruct import load_fit_settings  # noqa: PLC0415

    s = load_fit_settings(None, **{k: v for k, v in over.items() if k not in SESSION_KEYS})
    cells = s.cells
    return {"physics": s.model.profiles, "coupling": s.model.render.coupling, "dtype": s.dtype, "method": s.method,
            "start": s.start, "model": s.forward, "coarsest_px": s.coarsest_px, "ftol": s.ftol, "map_grids": s.map_grids,
            "map_cells": " ".join(f"{k}:{v:g}" for k, v in cells.items()), "band_weights": s.band_weighting, "free_scale": s.free_scale, "robust_passes": s.robust_passes,
            "max_iterations": s.max_iterations, "bin": over.get("bin", 1)}


