"""Fit a reflectance cube: chromophore maps by inverse rendering (DWRR08 §6.3, made fast).

``fit_cube(cube, settings)`` screens the cube (``checks.py``), builds the coarse-to-fine pyramid
(``unknowns.pyramid``), starts on the coarsest level (``start.py``), runs the chosen optimiser
(``optimizers.METHODS``) on every level, upsampling the unknowns between levels — or, where the forward
setting allows, takes the homogeneous detour (``detour.py``) — and returns the maps, the scale, the fitted
image, residuals, per-pixel flags and uncertainties (``finish.py``).

Uncertainty (``finish.py``). At the end point the noise's share of each pixel's covariance is the Gauss–Newton
sandwich Aₚ⁻¹ (Jₚᵀ Σ Jₚ) Aₚ⁻¹ (every map per pixel) or the inverse Fisher information of the whole fit
with the nodes' cluster-robust variance (maps on nodes, ``schur.marginal_variance``), Jₚ each pixel's
homogeneous Jacobian × light factor × scale and Σ = diag(σ_λ²) each band's residual variance
(``sigma_noise``). ``sigma`` widens it by what that leaves out, measured on the cube where it can be
(the cross-talk, the variation finer than the nodes) and on simulated sessions where it cannot (the
model's own error): ``uncertainty.py``.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Callable

import torch
import torch.nn.functional as F

from ...formats.cube import Cube
from ...formats.errors import InputError
from ...model import N_PARAMS
from ...model.patch.maps import SkinMaps
from ...formats.resources import require_memory
from ...formats.threads import library_threads
from ...model.render.renderer import SkinRenderer, render_bytes
from ..diagnosis.absorbers import AbsorberFit, candidate_rows, fit_grey_absorbance
from ..diagnosis.checks import DataChecks, check_cube
from .detour import homogeneous_fit
from .finish import cube_hairs, cube_noise, finish_fit, pixel_rms
from ..choice.fidelity import ForwardChoice
from ..choice.grid_choice import choose_map_grids
from .optimizers import METHODS, OptimResult
from ..levels.problem import HomogeneousProblem, LevelProblem, RenderCounter
from ..settings import FitSettings
from .start import STARTS, mean_spectrum_start
from ..levels.unknowns import extend, pyramid, upsample

#: band_weights: noise: the largest weight a band gets, in multiples of the typical band's (the root mean
#: square noise over the used bands): a band whose measured noise is near zero (a synthetic cube, a band the
#: camera clips) is not let to carry the fit alone
NOISE_WEIGHT_MAX = 4.0

log = logging.getLogger(__name__)

__all__ = ["DEFAULT_BAND_FWHM_NM", "DEFAULT_VIEW_ANGLE_DEG", "FitEvent", "MapFit", "band_fwhm_of", "fit_cube", "view_angle_of"]

#: Where neither the settings nor the cube's header say: DWRR08 §6.1's camera, 30° off the flash axis,
#: and its 10-nm band-pass filters.
DEFAULT_VIEW_ANGLE_DEG = 30.0
DEFAULT_BAND_FWHM_NM = 10.0


@dataclass(frozen=True)
class FitEvent:
    """What a progress callback hears. ``stage``: "tables" (``level`` of ``levels`` wavelengths built),
    "start", "fit" (``iteration`` done on ``level``, loss after it), "level" (``level`` finished) or
    "final"; ``pixels``: pixels of every level, coarsest first."""

    stage: str
    level: int
    levels: int
    iteration: int = 0
    loss: float = math.nan
    pixels: tuple[int, ...] = ()


Progress = Callable[[FitEvent], None]


@dataclass
class MapFit:
    """The result on the cube's grid. Maps ``(1, H, W)``; ``image`` and ``residual`` ``(L, H, W)``
    (scaled prediction and prediction − measurement, all bands); ``residual_rms`` ``(H, W)`` over the
    used bands; ``flags`` ``(H, W)`` int bit field (``checks.FLAG_BITS``); ``sigma`` ``(N_PARAMS, H, W)`` the
    uncertainty (``uncertainty.py``: the noise's share widened by the cross-talk and the variation finer
    than the nodes), ``sigma_noise`` the noise's share alone; ``uncertainty`` what the widening measured;
    ``absorbers`` what the absorber step found (``absorbers.py``);
    ``band_fwhm_nm`` ``(L,)`` each band's filter width as fitted, ``band_fwhm_source`` where it came from;
    ``band_weight`` ``(L,)`` each band's weight in the loss (0: unused; ``settings.band_weights``);
    ``history``: (CPU s, loss, level) after every accepted step of every pass (a robust pass lowers its
    own, weighted loss); ``maps_at_bound``: each map on nodes that rests at a bound somewhere, with the
    share of the loss pixels where it does (such a map flags no pixel: ``at_bound`` is a pixel's own maps);
    ``grid_choice``: with ``map_grids: auto``, what was considered and chosen (``grid_choice.GridChoice``);
    ``forward_choice``: with ``forward`` other than heterogeneous, the forward model used and why
    (``fidelity.ForwardChoice``); ``hairs``, ``structure``: what ``hairs.py`` found in the cube and
    ``structure.py`` in the residual (flagged pixels, regions, bands)."""

    maps: SkinMaps
    scale: float
    image: torch.Tensor
    residual: torch.Tensor
    residual_rms: torch.Tensor
    flags: torch.Tensor
    sigma: torch.Tensor
    sigma_noise: torch.Tensor
    checks: DataChecks
    wavelength_nm: torch.Tensor
    view_angle_deg: float
    view_angle_source: str
    band_fwhm_nm: torch.Tensor
    band_fwhm_source: str
    band_weight: torch.Tensor | None = None
    levels: list[dict] = field(default_factory=list)
    counter: RenderCounter = field(default_factory=RenderCounter)
    cpu_s: float = 0.0
    wall_s: float = 0.0
    history: list[tuple[float, float, int]] = field(default_factory=list)
    maps_at_bound: dict[str, float] = field(default_factory=dict)
    grid_choice: dict | None = None
    forward_choice: dict | None = None
    absorbers: dict | None = None
    uncertainty: dict | None = None
    band_bias: dict[str, float] = field(default_factory=dict)
    residual_over_noise: float = math.nan
    sigma_median: dict[str, float] = field(default_factory=dict)
    hairs: dict | None = None
    structure: dict | None = None

    @property
    def kept_levels(self) -> list[dict]:
        """The level records of the forward model whose maps were kept (``levels`` also holds the
        homogeneous detour's where ``forward: auto`` fell back to the renderer)."""
        kept = self.forward_choice["chosen"] if self.forward_choice else "heterogeneous"
        return [level for level in self.levels if level.get("forward", kept) == kept]


def view_angle_of(cube: Cube, settings: FitSettings) -> tuple[float, str]:
    """The camera angle: the settings', else the cube header's (the rig's), else DWRR08's 30°; and where it came from."""
    if settings.view_angle_deg is not None:
        return float(settings.view_angle_deg), "fit settings"
    if cube.header.camera_angle_deg is not None:
        return float(cube.header.camera_angle_deg), "cube header"
    return DEFAULT_VIEW_ANGLE_DEG, f"not in the cube header: DWRR08's {DEFAULT_VIEW_ANGLE_DEG:g}°"


def band_fwhm_of(cube: Cube, settings: FitSettings) -> tuple[torch.Tensor, str]:
    """Each band's filter width ``(L,)`` nm: the settings' (one for all), else the cube header's (the
    rig's, per band), else DWRR08's 10 nm; and where it came from."""
    bands = len(cube.header.wavelengths_nm)
    if settings.band_fwhm_nm is not None:
        return torch.full((bands,), float(settings.band_fwhm_nm), dtype=torch.float64), "fit settings"
    if cube.header.band_fwhm_nm is not None:
        return torch.tensor(cube.header.band_fwhm_nm, dtype=torch.float64), "cube header"
    return torch.full((bands,), DEFAULT_BAND_FWHM_NM, dtype=torch.float64), f"not in the cube header: DWRR08's {DEFAULT_BAND_FWHM_NM:g} nm"


def _resolve_device(device: str | torch.device | None) -> torch.device:
    if device in (None, "auto"):
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise InputError("--device cuda: no CUDA device is available here (use cpu or auto)")
    return dev


def fit_cube(
    cube: Cube,
    settings: FitSettings | None = None,
    *,
    device: str | torch.device | None = "cpu",
    renderer: SkinRenderer | None = None,
    progress: Progress | None = None,
    cache_dir: str | None = None,
) -> MapFit:
    """Fit the five maps and the scale to ``cube``; see the module docstring."""
    library_threads()  # SKINLAYERS_THREADS, where set (formats/threads.py)
    run = CubeFit(cube, settings or FitSettings(), device=device, renderer=renderer, progress=progress, cache_dir=cache_dir)
    problem, x, choice = run.start()
    result, forward, problem, x = run.fit_levels(problem, x)
    absorber, result, x = run.fit_absorbers(problem, result, forward, x)
    return run.finish(problem, result, x, forward, choice, absorber)


class CubeFit:
    """One map fit's state and its steps (``fit_cube`` runs them in order): the cube's checks and
    pyramid, the renderer and its render count, the records of every level fitted, the loss history and
    the robust weights carried from one level to the next, and the map grids in use (``cells``)."""

    def __init__(self, cube: Cube, settings: FitSettings, *, device=None, renderer: SkinRenderer | None = None,
                 progress: Progress | None = None, cache_dir: str | None = None) -> None:
        self.cube, self.settings = cube, settings
        self.device = _resolve_device(device)
        self.dtype = torch.float64 if settings.dtype == "float64" else torch.float32
        self.cpu0, self.wall0 = time.process_time(), time.perf_counter()
        self.checks = check_cube(cube, settings.saturated_reflectance, settings.dead_band_reflectance)
        _require_memory(cube, settings, self.dtype, self.device)
        self.view, self.view_source = view_angle_of(cube, settings)
        self.fwhm, self.fwhm_source = band_fwhm_of(cube, settings)
        self.renderer = renderer or SkinRenderer(settings.model, cache_dir)
        self.wl = cube.wavelength_nm.to(torch.float64)
        self.say = progress or (lambda event: None)
        self.renderer.model.tables(self.wl, progress=lambda j, n: self.say(FitEvent("tables", j, n)))
        self.target = cube.reflectance.to(device=self.device, dtype=self.dtype)
        self.noise = cube_noise(self.target, self.checks.fit_mask.to(self.device))  # (L,) or None: too few pixels
        self.hairs = cube_hairs(cube, self.checks, self.noise)
        self.levels = pyramid(self.target, self.checks.fit_mask.to(self.device), cube.mm_per_pixel, settings.coarsest_px)
        self.pixels = tuple(lv.shape[0] * lv.shape[1] for lv in self.levels)
        self.band_weight = band_weights(self.noise, self.checks.bands_used, settings.band_weighting)
        self.counter = RenderCounter()
        self.records: list[dict] = []
        self.history: list[tuple[float, float, int]] = []
        self.cells = settings.cells
        self.carried: dict = {}  # forward model → the last level's (shape, loss pixels, robust weights)

    # -- the steps -------------------------------------------------------------------------------
    def start(self) -> tuple[LevelProblem, torch.Tensor | None, object]:
        """The start, on the coarsest level, where it is first needed (with map_grids: auto, the grids
        from this cube's information; forward: auto's homogeneous detour starts from the cube's mean
        spectrum and, on skin the renderer is not needed for, never needs the per-pixel start)."""
        problem = self.problem(self.levels[0])
        self.say(FitEvent("start", 0, len(self.levels), pixels=self.pixels))
        x, choice = None, None
        if self.settings.map_grids == "auto":
            x = STARTS[self.settings.start](problem, dtype=self.dtype, device=self.device)
            choice = choose_map_grids(problem, x, self.noise_at(self.levels[0]), self.cells, self.cube.mm_per_pixel)
            self.cells = choice.cells_mm
            problem = self.problem(self.levels[0])
            x = _on_nodes(problem, x)
        return problem, x, choice

    def fit_levels(self, problem: LevelProblem, x) -> tuple[OptimResult, ForwardChoice | None, LevelProblem, torch.Tensor]:
        """Coarse to fine: the homogeneous detour where the settings allow and it holds, else the renderer's
        fit from the start. Returns the finest level's result, the forward choice, its problem and the maps
        ``(N_PARAMS, H, W)`` (the renderer's with masked pixels following the nearest visible one)."""
        log_scale = torch.zeros((), dtype=self.dtype, device=self.device)
        result, forward = None, None
        if self.settings.forward != "heterogeneous":
            x_start = x if x is not None else mean_spectrum_start(problem, dtype=self.dtype, device=self.device)
            result, forward, fitted_cells = homogeneous_fit(self, problem, x_start, log_scale, self.settings.forward)
            if result is not None:
                self.cells = fitted_cells
        if result is not None:
            return result, forward, self.problem(self.levels[-1]), result.x
        if x is None:
            x = _on_nodes(problem, STARTS[self.settings.start](problem, dtype=self.dtype, device=self.device))
        for i, level in enumerate(self.levels):
            if i:
                problem = self.problem(level)
                x = upsample(x, level.shape)
            result = self.fit_level(i, problem, x, log_scale, "heterogeneous")
            x, log_scale = extend(result.x, problem.index), result.log_scale
        return result, forward, problem, x

    def fit_absorbers(self, problem: LevelProblem, result: OptimResult, forward: ForwardChoice | None,
                      x: torch.Tensor) -> tuple[AbsorberFit | None, OptimResult, torch.Tensor]:
        """The grey absorbance where the settings ask for it (``_absorber_fit``), with the maps after it."""
        if self.settings.absorbers != "auto":
            return None, result, x
        absorber, result = _absorber_fit(self, problem, result, len(self.levels) - 1, forward)
        return absorber, result, extend(result.x, problem.index)

    def finish(self, problem: LevelProblem, result: OptimResult, x: torch.Tensor, forward: ForwardChoice | None, choice,
               absorber: AbsorberFit | None) -> MapFit:
        """The maps, their σ, flags and notes (``finish.finish_fit``), with this fit's records."""
        log_scale = result.log_scale
        self.say(FitEvent("final", len(self.levels) - 1, len(self.levels), pixels=self.pixels))
        renderer_fit = forward is None or forward.chosen == "heterogeneous"
        if forward is not None:
            self.checks.warn(forward.model_notes())
        out = finish_fit(problem, result, x, log_scale, self.checks, self.settings, self.cube.mm_per_pixel, renderer_fit, self.hairs)
        return MapFit(
            **out, checks=self.checks, wavelength_nm=self.wl, view_angle_deg=self.view, view_angle_source=self.view_source,
            band_fwhm_nm=self.fwhm, band_fwhm_source=self.fwhm_source, band_weight=self.band_weight.cpu(), levels=self.records,
            counter=self.counter, cpu_s=time.process_time() - self.cpu0, wall_s=time.perf_counter() - self.wall0,
            history=self.history, grid_choice=choice.as_dict() if choice else None,
            forward_choice=forward.as_dict() if forward else None,
            absorbers=absorber.as_dict() if absorber else None,
        )

    # -- what the steps share ----------------------------------------------------------------------
    def problem(self, level, light_factor: torch.Tensor | None = None, cells: dict[str, float] | None = None) -> LevelProblem:
        """The level's problem on the map grids in use (or ``cells``); with a light factor, the
        homogeneous model's."""
        kw = dict(view_angle_deg=self.view, border_mm=self.settings.border_mm, band_fwhm_nm=self.fwhm,
                  map_cell_mm=self.cells if cells is None else cells, counter=self.counter)
        if light_factor is None:
            return LevelProblem(self.renderer, level, self.wl, self.band_weight, **kw)
        return HomogeneousProblem(self.renderer, level, self.wl, self.band_weight, light_factor=light_factor, **kw)

    def noise_at(self, level) -> torch.Tensor:
        """The cube's own noise per band ``(L,)`` at a level: each 2×2 mean halves white noise's σ. Raises
        ValueError where the cube has too few pixels to tell it."""
        if self.noise is None:
            raise ValueError("fewer than 16 pixels with their 3×3 neighbourhood in the mask")
        return self.noise * (self.cube.mm_per_pixel / level.mm_per_pixel)

    def fit_level(self, i: int, problem: LevelProblem, x, log_scale, forward: str, method=None) -> OptimResult:
        """One level's fit and its robust refits, recorded (``records``, ``history``)."""
        c0, f0, b0 = time.process_time(), self.counter.forward, self.counter.backward
        passes: list[int] = []
        result = None
        n_pass = 1 + self.settings.robust_passes
        prev = self.carried.get(forward)
        if (self.settings.robust_finest == "carry" and i == len(self.levels) - 1 and prev is not None
                and prev[0] != problem.level.shape and problem.pixel_weight is None):
            # the finest level weighted from the start by the level above's robust weights: one pass instead of two
            problem.pixel_weight = _carry_weights(prev, problem)
            n_pass = 1
        for k in range(n_pass):  # the fit, then its robust refits
            if k:
                problem.pixel_weight = robust_weights(pixel_rms(problem, result.evaluation), self.settings.robust_scale)
                x, log_scale = result.x, result.log_scale
            result = (method or METHODS[self.settings.method])(
                problem, x, log_scale, self.settings,
                lambda it, loss, i=i, done=sum(passes): self.say(FitEvent("fit", i, len(self.levels), done + it, loss, self.pixels)),
            )
            passes.append(result.iterations)
            self.history.extend((t - self.cpu0, loss, i) for t, loss in result.history[1 if k else 0:])
        if problem.pixel_weight is not None:
            self.carried[forward] = (problem.level.shape, problem.pixels, problem.pixel_weight)
        self.records.append({"forward": forward, **_level_record(problem, result, passes, time.process_time() - c0,
                                                                 self.counter.forward - f0, self.counter.backward - b0)})
        self.say(FitEvent("level", i, len(self.levels), sum(passes), result.evaluation.loss, self.pixels))
        log.info("level %d of %d (%d×%d px, %s): %d iteration(s) in %d pass(es), loss %.4g, %.1f s of CPU", i + 1,
                 len(self.levels), *problem.level.shape, forward, sum(passes), len(passes), result.evaluation.loss,
                 time.process_time() - c0)
        return result


def _on_nodes(problem: LevelProblem, x: torch.Tensor) -> torch.Tensor:
    """The per-pixel start ``x`` with the maps on nodes made from its interquartile range: its noisy fits
    put many values at the start's bounds, from which the first steps are rejected (docs/reconstruct.md)."""
    if problem.layout.per_pixel:
        return x
    return problem.layout.assemble(x, problem.layout.project(x, clip_quantile=0.25))


def _absorber_fit(run: CubeFit, problem: LevelProblem, result: OptimResult, i: int,
                  forward: ForwardChoice | None) -> tuple[AbsorberFit | None, OptimResult]:
    """The grey absorbance where the finest level's residual asks for it (``absorbers.py``), and the finest
    level refitted with it held; ``result`` unchanged where nothing was kept."""
    shape = problem.level.shape
    nothing = lambda why: AbsorberFit(torch.zeros(shape), 0, 0, math.nan, math.nan, math.nan, 0, why)  # noqa: E731
    if forward is not None and forward.chosen != "heterogeneous":
        return nothing("not considered: the homogeneous model was kept (no neighbour's shading stood out)"), result
    try:
        noise = run.noise_at(problem.level)
    except ValueError as err:
        return nothing(f"not considered: the cube's noise cannot be measured ({err})"), result
    candidates = candidate_rows(problem, pixel_rms(problem, result.evaluation), run.settings.high_residual_factor)
    found, x = fit_grey_absorbance(problem, result.x, result.log_scale, noise, candidates)
    if not found.kept:
        return found, result
    return found, run.fit_level(i, problem, x, result.log_scale, "heterogeneous")


def _carry_weights(prev, problem: LevelProblem) -> torch.Tensor:
    """A coarser level's robust weights ``(N_coarse,)`` on this level's loss pixels ``(N,)`` (nearest)."""
    shape, pixels, weight = prev
    image = torch.ones(shape[0] * shape[1], dtype=weight.dtype, device=weight.device)
    image[pixels] = weight
    up = F.interpolate(image.reshape(1, 1, *shape), size=problem.level.shape, mode="nearest")[0, 0].reshape(-1)
    return up[problem.pixels]


def band_weights(noise: torch.Tensor | None, used: torch.Tensor, mode: str) -> torch.Tensor:
    """Each band's weight in the loss ``(L,)`` float64 (zero for an unused band) from the cube's own ``noise``
    ``(L,)`` (``finish.cube_noise``): with ``mode`` noise, the typical band's noise over the band's own (the
    least-squares fit of unequal noise, the estimate σ describes), at most ``NOISE_WEIGHT_MAX``; equal (or
    no noise: a cube too small to tell it): one for every used band."""
    weight = used.to(torch.float64).cpu()
    if mode == "equal" or noise is None or int(used.sum()) < 2:
        return weight
    noise = noise.double().cpu()
    typical = noise[used.cpu()].pow(2).mean().sqrt()
    return weight * (typical / noise).clamp(max=NOISE_WEIGHT_MAX)


def _require_memory(cube: Cube, settings: FitSettings, dtype: torch.dtype, device: torch.device) -> None:
    """Refuse, before any work, a cube whose finest level cannot be rendered and fitted in the memory
    available: its render (with a backward pass for the exact-gradient methods) and the per-pixel
    Jacobians, residuals and curvature blocks in float64."""
    bands, h, w = cube.shape
    border = math.ceil(settings.border_mm / cube.mm_per_pixel)
    render = render_bytes(1, bands, h, w, border, itemsize=dtype.itemsize, weight_cache_mb=settings.model.render.weight_cache_mb,
                          backward=settings.method in ("gn", "adam"))
    per_pixel = h * w * (bands + 1) * (N_PARAMS + 1) * 8 * 4
    require_memory(render + per_pixel, f"fitting a {h}×{w} cube at {bands} bands",
                   "Fit a coarser cube (calibrate with a smaller geometry.cube_px), fewer bands, or a smaller border_mm.", device)


def robust_weights(rms: torch.Tensor, scale: float) -> torch.Tensor:
    """Cauchy weights 1/(1 + (rms/c)²), c = ``scale`` × the median pixel's RMS (Holland & Welsch 1977):
    a pixel the model cannot explain (a hair, a vein) pulls the shared unknowns less."""
    c = scale * rms.median().clamp_min(1e-12)
    return 1.0 / (1.0 + (rms / c) ** 2)


def _level_record(problem: LevelProblem, result: OptimResult, passes: list[int], cpu_s: float, forward: int, backward: int) -> dict:
    return {
        "shape": list(problem.level.shape),
        "map_grids": problem.layout.describe(),
        "mm_per_pixel": problem.level.mm_per_pixel,
        "iterations": sum(passes),
        "iterations_per_pass": passes,
        "nodes_step_chi2": round(result.shared_decrement, 3),
        "converged": result.converged,
        "rms_residual": float(pixel_rms(problem, result.evaluation).pow(2).mean().sqrt()),
        "scale": float(torch.exp(result.log_scale)),
        "forward_renders": forward,
        "backward_renders": backward,
        "cpu_s": round(cpu_s, 3),
    }
