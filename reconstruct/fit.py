"""Fit a reflectance cube: chromophore maps by inverse rendering (DWRR08 §6.3, made fast).

``fit_cube(cube, settings)`` screens the cube (``checks.py``), builds the coarse-to-fine pyramid
(``unknowns.pyramid``), starts on the coarsest level (``start.py``), runs the chosen optimiser
(``optimizers.METHODS``) on every level, upsampling the unknowns between levels, and returns the maps,
the scale, the fitted image, residuals, per-pixel flags and uncertainties.

Uncertainty. At the end point the noise's share of each pixel's covariance is the Gauss–Newton
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

from ..formats.cube import Cube
from ..formats.errors import InputError
from ..model import N_PARAMS, PARAMETER_NAMES
from ..model.maps import SkinMaps
from ..formats.resources import require_memory
from ..formats.threads import library_threads
from ..model.renderer import SkinRenderer, render_bytes
from .absorbers import AbsorberFit, candidate_rows, fit_grey_absorbance
from .checks import (DataChecks, band_bias, band_bias_notes, check_cube, flag_value, precision_notes, residual_notes,
                     smooth_band_notes)
from .fidelity import PATCH_MM, ForwardChoice, crosstalk_check, spatial_structure, uniform_light_factor, window_light_factor
from .gauss_newton import curvature_and_columns, level_step
from .grid_choice import band_noise, choose_map_grids
from .hairs import HairFinding, find_hairs, hair_notes, hair_widening
from .optimizers import METHODS, OptimResult
from .problem import HomogeneousProblem, LevelProblem, RenderCounter
from .schur import marginal_variance
from .settings import FitSettings
from .start import STARTS, mean_spectrum_start
from .uniform import fit_uniform
from .uncertainty import MODEL_FLOOR_ABSOLUTE, MODEL_FLOORS, crosstalk_ratio, model_floor, subnode_sd
from .unknowns import dparams_dx, extend, near_bound, pyramid, to_params, upsample

#: band_weights: noise: the largest weight a band gets, in multiples of the typical band's (the root mean
#: square noise over the used bands): a band whose measured noise is near zero (a synthetic cube, a band the
#: camera clips) is not let to carry the fit alone
NOISE_WEIGHT_MAX = 4.0

log = logging.getLogger(__name__)

__all__ = ["DEFAULT_BAND_FWHM_NM", "DEFAULT_VIEW_ANGLE_DEG", "FitEvent", "MapFit", "band_fwhm_of", "fit_cube", "view_angle_of"]

#: The homogeneous fit makes the window's light factor on its coarsest level this many times: at the
#: skin of a point fit of the level's mean spectrum (which ignores the window's edges), then at the skin
#: of a uniform fit of the level (its light-weighted mean spectrum) under the factor before. The factors
#: toward the skin are the Fourier-domain combination, the last a render; every pixel is fitted once,
#: under the last, from the uniform skin. Three passes: β_m's error falls with the second and the third factor
#: and no further with a fourth (with one ``auto``'s check fails and the renderer fits); re-making the
#: factor after each of three per-pixel fits instead (the scheme before) ends about as well at several
#: times the cost (docs/reconstruct.md, "From reconstruct/fit.py").
LIGHT_FACTOR_PASSES = 3
#: Where neither the settings nor the cube's header say: DWRR08 §6.1's camera, 30° off the flash axis,
#: and its 10-nm band-pass filters.
DEFAULT_VIEW_ANGLE_DEG = 30.0
#: The nodes' cluster-robust variance (``schur.marginal_variance``) sums the residual's pull over squares
#: of this side: about the light's spread in red, the scale on which the model's error is correlated.
CLUSTER_MM = 1.0
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
    (``fidelity.ForwardChoice``)."""

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
        self.hairs = _hairs(cube, self.checks)
        self.levels = pyramid(self.target, self.checks.fit_mask.to(self.device), cube.mm_per_pixel, settings.coarsest_px)
        self.pixels = tuple(lv.shape[0] * lv.shape[1] for lv in self.levels)
        self.band_weight = band_weights(self.target, self.checks.fit_mask.to(self.device), self.checks.bands_used,
                                        settings.band_weighting)
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
            result, forward, fitted_cells = _homogeneous_fit(self, problem, x_start, log_scale, self.settings.forward)
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
        """The maps, their σ, flags and notes (``_finish``), with this fit's records."""
        log_scale = result.log_scale
        self.say(FitEvent("final", len(self.levels) - 1, len(self.levels), pixels=self.pixels))
        renderer_fit = forward is None or forward.chosen == "heterogeneous"
        if forward is not None:
            self.checks.warn(forward.model_notes())
        out = _finish(problem, result, x, log_scale, self.checks, self.settings, self.cube.mm_per_pixel, renderer_fit, self.hairs)
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
        """The cube's own noise per band ``(L,)`` at a level: each 2×2 mean halves white noise's σ."""
        return band_noise(self.target, self.checks.fit_mask.to(self.device)) * (self.cube.mm_per_pixel / level.mm_per_pixel)

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


def _homogeneous_fit(run: CubeFit, problem: LevelProblem, x, log_scale, setting: str):
    """Every level fitted with each pixel's homogeneous model under the window's light (``fidelity``).
    The coarsest level's light factor is re-made from the skin it finds (``LIGHT_FACTOR_PASSES``), the
    finest level's by the Fourier-domain combination (``uniform_light_factor``: no render). With
    ``setting == "auto"`` the fit is checked against the renderer on the coarsest level at its maps;
    maps whose values there show no spatial structure (``spatial_structure``) become one value for the
    patch, and where every map is one value (uniform skin) the homogeneous model is the renderer's own
    answer: the finest level is fitted at once, as five unknowns, without a render. (Tested earlier, after
    the first or second pass, the maps still carry the start's light factor as a smooth bowl.) Otherwise
    the finest is checked at the coarse maps upsampled (smooth: the check measures the scene's
    cross-talk, not that of the maps' own pixel noise, which the renderer blurs and the homogeneous
    model does not). Both: docs/reconstruct.md, "From reconstruct/fit.py".
    Returns the finest level's result (its evaluation the renderer's unless the skin is uniform), the
    choice and the map grids it fitted, or ``(None, choice, cells)`` where a check fails and the
    renderer's fit must run."""
    detour = _HomogeneousDetour(run, setting)
    try:
        return detour.fit(problem, x, log_scale), detour.choice, detour.cells
    except _RendererNeeded as why:  # a check failed: the renderer's fit runs, from its own start
        detour.choice.chosen = "heterogeneous"
        if why.note:
            detour.choice.note = why.note
        detour.choice.homogeneous_wall_s = time.perf_counter() - detour.wall0
        return None, detour.choice, detour.cells


class _RendererNeeded(Exception):
    """The homogeneous model failed a check (or cannot be checked): the renderer's fit must run."""

    def __init__(self, note: str | None = None) -> None:
        super().__init__(note)
        self.note = note


class _HomogeneousDetour:
    """The homogeneous fit's state: the run it belongs to, the map grids (which it may coarsen to one
    value per map), the choice it records and when it started."""

    def __init__(self, run: CubeFit, setting: str) -> None:
        self.run, self.setting, self.levels, self.cells = run, setting, run.levels, run.cells
        self.wall0 = time.perf_counter()
        self.choice = ForwardChoice(setting, "homogeneous")
        self.last = len(self.levels) - 1

    def fit(self, problem: LevelProblem, x, log_scale) -> OptimResult:
        """The steps: noise known (auto), the coarsest level, then the finest at once (uniform skin) or
        every level in turn; the answer evaluated with the renderer."""
        if self.setting == "auto":
            try:
                self.run.noise_at(self.levels[self.last])
            except ValueError as err:  # too few pixels to tell the noise: nothing to weigh the cross-talk against
                raise _RendererNeeded(f"the cube's noise cannot be measured ({err})") from err
        x, log_scale, factor, coarse = self._coarsest(problem, x, log_scale)
        if self.choice.uniform:
            return self._uniform(x, log_scale)
        factor = self._finest_factor(x, log_scale, factor)
        x, log_scale, result, hom = self._climb(x, log_scale, factor, coarse)
        evaluation = self._evaluate(x, log_scale, hom)
        self.choice.homogeneous_wall_s = time.perf_counter() - self.wall0
        return OptimResult(x, log_scale, evaluation, result.iterations, result.converged, result.history)

    def _check(self, i: int, x_at, scale_at, factor_at) -> None:
        """The cross-talk check on level ``i``; raises ``_RendererNeeded`` where it fails."""
        run = self.run
        rendered = run.problem(self.levels[i], cells=self.cells)
        found, _ = crosstalk_check(i, rendered, run.problem(self.levels[i], factor_at, cells=self.cells), x_at, scale_at,
                                   run.noise_at(self.levels[i]))
        self.choice.checks.append(found)
        if not found.passed:
            raise _RendererNeeded

    def _coarsest(self, problem: LevelProblem, x, log_scale):
        """The coarsest level's light factor from the skin found, its fit, and (auto) its check and the
        maps with no structure made one value. Returns the maps, scale, light factor and the level's
        (result, problem)."""
        run, level, cells = self.run, self.levels[0], self.cells
        skin = x  # the light factor's skin: the start's, then the level's uniform fits (its mean spectrum)
        # the factors toward it need no render (close to one here: docs/reconstruct.md, "From reconstruct/fit.py")
        for _ in range(LIGHT_FACTOR_PASSES - 1):
            hom = run.problem(level, uniform_light_factor(problem, skin), cells=cells)
            uniform_fit = run.fit_level(0, hom, skin, log_scale, "homogeneous", fit_uniform)
            skin, log_scale = uniform_fit.x, uniform_fit.log_scale
        factor = window_light_factor(problem, skin)
        hom = run.problem(level, factor, cells=cells)
        result = run.fit_level(0, hom, skin, log_scale, "homogeneous")  # every pixel, from the uniform skin
        x, log_scale = extend(result.x, hom.index), result.log_scale
        if self.setting != "auto":
            return x, log_scale, factor, (result, hom)
        self._check(0, x, log_scale, factor)
        self.choice.structure = spatial_structure(hom.layout, x, hom.mask, level.mm_per_pixel)
        self.cells = {**cells, **dict.fromkeys(self.choice.constant_maps, PATCH_MM)}  # no structure: one value
        if self.choice.constant_maps and not self.choice.uniform:  # refitted so on this level
            hom = run.problem(level, factor, cells=self.cells)
            x = hom.layout.assemble(x, hom.layout.project(x))
            result = run.fit_level(0, hom, x, log_scale, "homogeneous")
            x, log_scale = extend(result.x, hom.index), result.log_scale
        return x, log_scale, factor, (result, hom)

    def _uniform(self, x, log_scale) -> OptimResult:
        """Five values, which every level determines alike: the finest fitted at once as five unknowns,
        its light factor made from the skin found (the Fourier-domain combination: no render); the
        homogeneous model of uniform skin under the window's light is the render (Eq. 3), so the fit's
        own evaluation is the renderer's."""
        run, last, cells = self.run, self.last, self.cells
        x = upsample(x, self.levels[last].shape)
        fine = run.problem(self.levels[last], cells=cells)
        factor = uniform_light_factor(fine, x) if last > 0 else window_light_factor(fine, x)
        result = run.fit_level(last, run.problem(self.levels[last], factor, cells=cells), x, log_scale, "homogeneous",
                               fit_uniform)
        self.choice.homogeneous_wall_s = time.perf_counter() - self.wall0
        return result

    def _finest_factor(self, x, log_scale, factor):
        """The window's edges fall off within a fraction of a millimetre: the finest level's factor is its
        own (an upsampled coarse one is off at the edge pixels: docs/reconstruct.md, "From
        reconstruct/fit.py"); checked there at the coarse maps upsampled (auto)."""
        if self.last == 0:
            return factor
        fine_level = self.levels[self.last]
        x_fine = upsample(x, fine_level.shape)
        factor = uniform_light_factor(self.run.problem(fine_level, cells=self.cells), x_fine)
        if self.setting == "auto":
            self._check(self.last, x_fine, log_scale, factor)
        return factor

    def _climb(self, x, log_scale, factor, coarse):
        """Every finer level fitted in turn from the one below (``coarse``: the coarsest's result and
        problem); the levels between take the finest factor's area means. Returns the finest maps,
        scale, fit result and problem."""
        result, hom = coarse
        for i in range(1, len(self.levels)):
            x = upsample(x, self.levels[i].shape)
            area = F.interpolate(factor[None], size=self.levels[i].shape, mode="area")[0]
            hom = self.run.problem(self.levels[i], area, cells=self.cells)
            result = self.run.fit_level(i, hom, x, log_scale, "homogeneous")
            x, log_scale = extend(result.x, hom.index), result.log_scale
        return x, log_scale, result, hom

    def _evaluate(self, x, log_scale, hom):
        """The residual, flags and σ are the renderer's; with the homogeneous model imposed, the same
        render tells how far that model is from it at these maps (the cross-talk it leaves out: a
        warning)."""
        run, fine_level = self.run, self.levels[self.last]
        try:
            noise = run.noise_at(fine_level) if self.setting == "homogeneous" else None
        except ValueError:
            noise = None
        if noise is None:
            return run.problem(fine_level, cells=self.cells).evaluate(x, log_scale)
        found, evaluation = crosstalk_check(self.last, run.problem(fine_level, cells=self.cells), hom, x, log_scale, noise)
        self.choice.checks.append(found)
        return evaluation


def band_weights(target: torch.Tensor, mask: torch.Tensor, used: torch.Tensor, mode: str) -> torch.Tensor:
    """Each band's weight in the loss ``(L,)`` float64 (0 for an unused band) for a cube ``(L, H, W)`` and its
    fit ``mask`` ``(H, W)``: with ``mode`` noise, the typical band's noise over the band's own
    (``band_noise``: the least-squares fit of unequal noise, the estimate σ describes), at most
    ``NOISE_WEIGHT_MAX``; equal (or a cube too small to measure its noise): 1 for every used band."""
    weight = used.to(torch.float64).cpu()
    if mode == "equal" or int(used.sum()) < 2:
        return weight
    try:
        noise = band_noise(target, mask).cpu()
    except ValueError:  # too few pixels to measure the noise: every band alike
        return weight
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


def pixel_rms(problem: LevelProblem, ev) -> torch.Tensor:
    """Each loss pixel's residual RMS over the used bands, unweighted ``(N,)``."""
    used = problem.band_weight > 0
    pred = problem.at_pixels(ev.image) * torch.exp(ev.log_scale)
    return torch.sqrt(((pred - problem.target)[:, used] ** 2).mean(1))


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


def _finish(problem: LevelProblem, result: OptimResult, x, log_scale, checks: DataChecks, settings: FitSettings, mm: float,
            renderer_fit: bool = True, hairs: HairFinding | None = None) -> dict:
    """Residuals, flags and uncertainties on the finest grid (σ widened by ``uncertainty.py``: the
    cross-talk where the renderer's fit was kept, the variation finer than the nodes)."""
    ev = result.evaluation
    scale = torch.exp(log_scale)
    image = ev.image * scale
    used = problem.band_weight > 0
    residual = image - problem.level.target
    residual_rms = torch.sqrt((residual[used] ** 2).mean(0))
    p = to_params(x)
    dx = _proposed_step(problem, ev, settings)
    sigma_pix, sigma_noise, widening = _pixel_sigma(problem, ev, residual, x, settings, renderer_fit)
    # not converged: the optimiser stopped at its iteration cap and the step it still proposes moves one
    # of the pixel's own maps by more than half its uncertainty. (After a passed convergence test the
    # proposed gn-hom step is no measure: it points at the fixed point of the approximate Jacobian, not
    # at the optimum, and stays large where no step lowers the loss: docs/reconstruct.md.)
    remaining = (problem.at_pixels(dparams_dx(x)) * dx).abs()
    fine = problem.layout.fine
    moving_pix = (remaining[:, fine] > 0.5 * sigma_pix.to(remaining.dtype)[:, fine]).any(1) & (not result.converged)
    flags, nodes_at_bound = _flags(problem, checks, settings, p, residual_rms, moving_pix)
    bias, ratio = _data_notes(problem, checks, residual, used)
    if hairs is not None:
        flags[hairs.flagged.reshape(-1).to(x.device)] |= flag_value("hair")
        checks.warn(hair_notes(hairs, int((problem.mask | hairs.flagged.to(x.device)).sum())))
    clear = ~hairs.flagged.reshape(-1).to(x.device)[problem.pixels] if hairs is not None else None
    precision = _sigma_median(p, sigma_pix, problem, clear)
    checks.warn(precision_notes(precision))
    h, w = problem.level.shape
    sigma = torch.full((N_PARAMS, h * w), float("nan"), dtype=x.dtype, device=x.device)
    sigma[:, problem.pixels] = sigma_pix.T.to(x.dtype)
    if hairs is not None and hairs.count:
        sigma *= hair_widening(hairs.flagged.reshape(-1).to(x.device), PARAMETER_NAMES).to(sigma)
    noise_sigma = torch.full_like(sigma, float("nan"))
    noise_sigma[:, problem.pixels] = sigma_noise.T.to(x.dtype)
    return {
        "maps": _final_maps(problem, p, mm), "scale": float(scale), "image": image, "residual": residual,
        "residual_rms": residual_rms, "flags": flags.reshape(h, w), "sigma": sigma.reshape(N_PARAMS, h, w),
        "sigma_noise": noise_sigma.reshape(N_PARAMS, h, w), "maps_at_bound": nodes_at_bound,
        "band_bias": {f"{problem.wavelength_nm[j]:g}": round(b, 5) for j, b in bias.items()},
        "residual_over_noise": round(ratio, 4), "sigma_median": {n: round(v, 5) for n, v in precision.items()},
        "hairs": hairs.as_dict() if hairs is not None else None,
        "uncertainty": {**widening, "noise_sigma_median": {n: float(sigma_noise[:, k].median()) for k, n in enumerate(PARAMETER_NAMES)}},
    }


def _final_maps(problem: LevelProblem, p: torch.Tensor, mm: float) -> SkinMaps:
    """The parameter maps ``p`` ``(N_PARAMS, H, W)`` as ``SkinMaps``, with the grey absorbance at every band."""
    maps = SkinMaps(*(v[None] for v in p.unbind(0)), mm_per_pixel=mm)
    if problem.absorbance is not None:
        bands = problem.wavelength_nm.numel()
        maps = maps.replace(absorbance=problem.absorbance[None, None].expand(1, bands, -1, -1).contiguous(),
                            absorbance_wavelength_nm=problem.wavelength_nm.clone())
    return maps


def _proposed_step(problem: LevelProblem, ev, settings: FitSettings) -> torch.Tensor:
    """The step ``(N, N_PARAMS)`` the optimiser still proposes for each pixel's own maps (zero where every
    map is on nodes)."""
    jac, col = curvature_and_columns(problem, ev)
    dx = torch.zeros(problem.n_pixels, N_PARAMS, dtype=jac.dtype, device=jac.device)
    if problem.layout.fine:
        lam = torch.full((problem.n_pixels,), 1e-3, dtype=jac.dtype, device=jac.device)
        grad = ev.grad if ev.grad is not None else (jac.transpose(1, 2) @ ev.residual[..., None])[..., 0]
        dx = level_step(problem, jac, col, grad, ev.residual, lam, 1e-3, settings.free_scale)[0]
    return dx


def _pixel_sigma(problem: LevelProblem, ev, residual, x, settings: FitSettings, renderer_fit: bool):
    """σ per loss pixel ``(N, N_PARAMS)``: widened, from the noise alone, and the widening's record.
    From the unweighted problem: the robust weights shape the estimate, not the camera's noise."""
    problem.pixel_weight = None
    jac, col = curvature_and_columns(problem, ev)
    plain = problem.at_pixels(residual) * problem.band_weight
    if problem.layout.per_pixel:
        sigma_noise = _sigma(problem, jac, plain, x)
    else:
        sigma_noise = _sigma_shared(problem, jac, col, plain, x, settings.free_scale)
    sigma_pix, widening = _widened(problem, ev, jac, plain, x, sigma_noise, renderer_fit)
    return sigma_pix, sigma_noise, widening


def _flags(problem: LevelProblem, checks: DataChecks, settings: FitSettings, p: torch.Tensor, residual_rms: torch.Tensor,
           moving_pix: torch.Tensor) -> tuple[torch.Tensor, dict[str, float]]:
    """The flag bits per pixel ``(H·W,)`` (masked, saturated, at a bound, not converged, high residual,
    a band excluded) and the maps on nodes that rest at a bound (share of the pixels)."""
    h, w = problem.level.shape
    device = p.device
    flags = torch.zeros(h * w, dtype=torch.int32, device=device)
    flags[~problem.mask.reshape(-1)] |= flag_value("masked")
    flags[checks.saturated.reshape(-1).to(device)] |= flag_value("saturated")
    bound_hit = near_bound(p, settings.at_bound_fraction)  # (N_PARAMS, H, W)
    # a pixel's own maps at a bound flag it; a map on nodes at a bound is the whole region's, reported once
    at_bound = bound_hit[problem.layout.fine].any(0).reshape(-1)
    nodes_at_bound = {PARAMETER_NAMES[k]: float(bound_hit[k][problem.mask].double().mean()) for k in problem.layout.coarse
                      if bool(bound_hit[k][problem.mask].any())}
    flags[at_bound & problem.mask.reshape(-1)] |= flag_value("at_bound")
    moving = torch.zeros(h * w, dtype=torch.bool, device=device)
    moving[problem.pixels] = moving_pix
    flags[moving] |= flag_value("not_converged")
    rms_pix = residual_rms.reshape(-1)[problem.pixels]
    high = torch.zeros(h * w, dtype=torch.bool, device=device)
    high[problem.pixels] = rms_pix > settings.high_residual_factor * rms_pix.median()
    flags[high] |= flag_value("high_residual")
    if not bool(checks.bands_used.all()):
        flags |= flag_value("band_excluded")
    return flags, nodes_at_bound


def _data_notes(problem: LevelProblem, checks: DataChecks, residual: torch.Tensor, used: torch.Tensor) -> tuple[dict, float]:
    """The residual's checks as notes: a band biased, the residual against the cube's own noise, a band
    too smooth for its noise. Returns the per-band bias and the residual-over-noise ratio."""
    seen = problem.mask & ~checks.saturated.to(residual.device)
    bias = band_bias(residual, problem.level.target, used, seen)
    checks.warn(band_bias_notes(bias, problem.wavelength_nm.tolist()))
    noise = _cube_noise(problem.level.target, seen)
    ratio = _residual_over_noise(residual, used, seen, noise)
    checks.warn(residual_notes(ratio))
    if noise is not None:
        level = problem.level.target[:, seen].double().median(dim=1).values.clamp_min(1e-12)
        checks.warn(smooth_band_notes((noise.double() / level).tolist(), problem.wavelength_nm.tolist(), used.tolist()))
    return bias, ratio


def _hairs(cube: Cube, checks: DataChecks) -> HairFinding | None:
    """The hairs in the cube (``hairs.py``) over the pixels the loss may use; None where the cube is too
    small to estimate its noise."""
    noise = _cube_noise(cube.reflectance, checks.fit_mask)
    if noise is None:
        return None
    return find_hairs(cube.reflectance, cube.wavelength_nm.tolist(), checks.fit_mask, cube.mm_per_pixel, noise, checks.bands_used)


def _cube_noise(target: torch.Tensor, pixels: torch.Tensor) -> torch.Tensor | None:
    """Each band's noise σ ``(L,)`` estimated from the cube itself (``band_noise``) over ``pixels`` ``(H, W)``;
    None where too few pixels have their neighbourhood in it."""
    try:
        return band_noise(target, pixels)
    except ValueError:
        return None


def _residual_over_noise(residual: torch.Tensor, used: torch.Tensor, pixels: torch.Tensor, noise: torch.Tensor | None) -> float:
    """The residual's RMS over the cube's noise ``(L,)``, both over ``pixels`` ``(H, W)`` and the ``used`` bands."""
    if noise is None:
        return math.nan
    res = residual[used][:, pixels].double()
    return float(res.pow(2).mean().sqrt() / noise[used].double().pow(2).mean().sqrt())


def _sigma_median(p: torch.Tensor, sigma_pix: torch.Tensor, problem: LevelProblem, clear: torch.Tensor | None = None) -> dict[str, float]:
    """Each map's median σ over the fitted pixels (those ``clear`` ``(N,)`` of a hair where given): relative
    to the map's value, β_m absolute."""
    values = problem.at_pixels(p).double()  # (N, N_PARAMS)
    sigma = sigma_pix.double()
    if clear is not None and bool(clear.any()):
        values, sigma = values[clear], sigma[clear]
    return {n: float((sigma[:, k] if n == "beta_m" else sigma[:, k] / values[:, k].abs().clamp_min(1e-12)).median())
            for k, n in enumerate(PARAMETER_NAMES)}


def _widened(problem: LevelProblem, ev, jac, residual, x, sigma_pix, renderer_fit: bool) -> tuple[torch.Tensor, dict]:
    """σ ``(N, N_PARAMS)`` with the two terms ``uncertainty.py`` measures on the cube, and what they were."""
    sd_band = _band_sd(problem, residual, free_scale=False)
    rho = crosstalk_ratio(problem, ev, jac) if renderer_fit else torch.ones(N_PARAMS, dtype=torch.float64, device=jac.device)
    dpdx = problem.at_pixels(dparams_dx(x)).double()
    spread = subnode_sd(problem, jac, residual, sd_band, rho, dpdx)
    widen = torch.ones(N_PARAMS, dtype=torch.float64, device=jac.device)
    widen[problem.layout.fine] = 1.0 / rho[problem.layout.fine]
    profiles = problem.renderer.settings.profiles
    floor = model_floor(problem.at_pixels(to_params(x)), profiles)
    total = torch.sqrt((sigma_pix.double() * widen) ** 2 + spread**2 + floor**2)
    return total.to(sigma_pix.dtype), {
        "crosstalk_ratio": {n: float(rho[k]) for k, n in enumerate(PARAMETER_NAMES)},
        "crosstalk_measured": renderer_fit,
        "subnode_sd_median": {PARAMETER_NAMES[k]: float(spread[:, k].median()) for k in problem.layout.coarse},
        "model_floor": dict(MODEL_FLOORS[profiles]),
        "model_floor_relative_to_value": [n for n in PARAMETER_NAMES if n not in MODEL_FLOOR_ABSOLUTE],
    }


def _band_sd(problem: LevelProblem, residual: torch.Tensor, free_scale: bool) -> torch.Tensor:
    """Each band's residual σ ``(L,)`` from the loss pixels' residual ``(N, L)``, corrected for the degrees of
    freedom the fit took (its per-pixel maps, nodes and, with ``free_scale``, the scale)."""
    n_used = int((problem.band_weight > 0).sum())
    n_unknowns = len(problem.layout.fine) * problem.n_pixels + problem.layout.n_nodes + int(free_scale)
    dof = max(n_used * problem.n_pixels - n_unknowns, 1) / (n_used * problem.n_pixels)
    return torch.sqrt((residual.double() ** 2).mean(0) / dof).clamp_min(1e-12)


def _sigma_shared(problem: LevelProblem, jac, col, residual, x, free_scale: bool) -> torch.Tensor:
    """Per-pixel standard deviation of each parameter ``(N, N_PARAMS)`` when maps share nodes: the inverse
    Fisher information of the whole fit (``schur.marginal_variance``), each band's noise σ from the
    residual, mapped from x to the parameter at the pixel."""
    used = problem.band_weight > 0
    sd_band = _band_sd(problem, residual, free_scale)
    weight = torch.where(used, 1.0 / sd_band, torch.zeros_like(sd_band))
    h, w = problem.level.shape
    cell = max(int(round(CLUSTER_MM / problem.level.mm_per_pixel)), 1)
    rows, cols = problem.pixels // w, problem.pixels % w
    clusters = (rows // cell) * (w // cell + 1) + cols // cell
    var = marginal_variance(jac.double() * weight[None, :, None], col.double() * weight[None, :], free_scale, problem.layout,
                            problem.pixels, residual.double() * weight[None, :], clusters)
    return var.sqrt() * problem.at_pixels(dparams_dx(x)).double()


def _sigma(problem: LevelProblem, jac: torch.Tensor, residual: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Per-pixel standard deviation of each parameter ``(N, N_PARAMS)`` (sandwich covariance, float64)."""
    used = problem.band_weight > 0
    n_used = int(used.sum())
    dof = max(n_used - N_PARAMS, 1) / n_used
    var_band = (residual.double() ** 2).mean(0) / dof  # (L,)
    dpdx = problem.at_pixels(dparams_dx(x)).double()  # (N, N_PARAMS)
    jp = jac.double() / dpdx.clamp_min(1e-300)[:, None, :]
    jp = jp[:, used]
    a = jp.transpose(1, 2) @ jp
    ridge = 1e-12 * torch.diagonal(a, dim1=1, dim2=2).amax(1)[:, None, None] * torch.eye(N_PARAMS, dtype=a.dtype, device=a.device)
    a_inv = torch.linalg.pinv(a + ridge, hermitian=True)
    meat = jp.transpose(1, 2) @ (var_band[used][None, :, None] * jp)
    cov = a_inv @ meat @ a_inv
    return torch.sqrt(torch.diagonal(cov, dim1=1, dim2=2).clamp_min(0.0))

