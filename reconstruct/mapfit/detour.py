"""The homogeneous detour (``forward: auto`` and ``homogeneous``): every level fitted with each pixel's own
homogeneous model under the window's light (``fidelity``), checked against the renderer where the setting
asks, and the renderer's fit called for (``None``) where a check fails."""

from __future__ import annotations

import time
from typing import Protocol

import torch
import torch.nn.functional as F

from ..choice.fidelity import (
    CROSSTALK_LIMIT, FORECAST_MARGIN, PATCH_MM, ForwardChoice, crosstalk_check, crosstalk_forecast, spatial_structure,
    uniform_light_factor, window_light_factor,
)
from .optimizers import OptimResult
from ..levels.problem import LevelProblem
from ..settings import FitSettings
from .uniform import fit_uniform
from ..levels.unknowns import extend, upsample

__all__ = ["LIGHT_FACTOR_PASSES", "FitRun", "homogeneous_fit"]

#: The homogeneous fit makes the window's light factor on its coarsest level this many times: at the
#: skin of a point fit of the level's mean spectrum (which ignores the window's edges), then at the skin
#: of a uniform fit of the level (its light-weighted mean spectrum) under the factor before. The factors
#: toward the skin are the Fourier-domain combination, the last a render; every pixel is fitted once,
#: under the last, from the uniform skin. Three passes: β_m's error falls with the second and the third factor
#: and no further with a fourth (with one ``auto``'s check fails and the renderer fits); re-making the
#: factor after each of three per-pixel fits instead (the scheme before) ends about as well at several
#: times the cost (docs/reconstruct.md, "From reconstruct/mapfit/detour.py").
LIGHT_FACTOR_PASSES = 3


class FitRun(Protocol):
    """What the detour needs of the fit it belongs to (``fit.CubeFit``, named by its shape so that the two
    modules do not import each other): its settings, pyramid, map grids and noise, a level's problem and
    its fit."""

    settings: FitSettings
    levels: list
    cells: dict[str, float]

    def problem(self, level, light_factor: torch.Tensor | None = None, cells: dict[str, float] | None = None) -> LevelProblem: ...

    def noise_at(self, level) -> torch.Tensor: ...

    def fit_level(self, i: int, problem: LevelProblem, x, log_scale, forward: str, method=None) -> OptimResult: ...


def homogeneous_fit(run: FitRun, problem: LevelProblem, x, log_scale, setting: str):
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
    model does not). Both: docs/reconstruct.md, "From reconstruct/mapfit/detour.py".
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

    def __init__(self, run: FitRun, setting: str) -> None:
        self.run, self.setting, self.levels, self.cells = run, setting, run.levels, run.cells
        self.wall0 = time.perf_counter()
        self.choice = ForwardChoice(setting, "homogeneous")
        self.last = len(self.levels) - 1

    def fit(self, problem: LevelProblem, x, log_scale) -> OptimResult:
        """The steps: noise known and the cross-talk forecast (auto), the coarsest level, then the finest at once (uniform skin) or
        every level in turn; the answer evaluated with the renderer."""
        if self.setting == "auto":
            try:
                self.run.noise_at(self.levels[self.last])
            except ValueError as err:  # too few pixels to tell the noise: nothing to weigh the cross-talk against
                raise _RendererNeeded(f"the cube's noise cannot be measured ({err})") from err
            self._forecast(problem, x)
        x, log_scale, factor, coarse = self._coarsest(problem, x, log_scale)
        if self.choice.uniform:
            return self._uniform(x, log_scale)
        factor = self._finest_factor(x, log_scale, factor)
        x, log_scale, result, hom = self._climb(x, log_scale, factor, coarse)
        evaluation = self._evaluate(x, log_scale, hom)
        self.choice.homogeneous_wall_s = time.perf_counter() - self.wall0
        return OptimResult(x, log_scale, evaluation, result.iterations, result.converged, result.history)

    def _forecast(self, problem: LevelProblem, x) -> None:
        """The cross-talk told from the cube alone (``crosstalk_forecast``: FFTs, no fit, no render); where it
        is ``FORECAST_MARGIN`` times the check's limit the check would fail, and the detour is not tried."""
        forecast = crosstalk_forecast(problem, x, self.run.noise_at(self.levels[0]))
        self.choice.forecast = round(forecast, 4)
        if forecast > FORECAST_MARGIN * CROSSTALK_LIMIT:
            raise _RendererNeeded

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
        # the factors toward it need no render (close to one here: docs/reconstruct.md, "From reconstruct/mapfit/detour.py")
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
        reconstruct/mapfit/detour.py"); checked there at the coarse maps upsampled (auto)."""
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


