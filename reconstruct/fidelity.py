"""How much forward model a cube needs: each pixel's homogeneous model, or the heterogeneous renderer
(``FitSettings.forward``; ``reconstruct --model auto``: "model no more than a scene needs").

The renderer's cost is the light each pixel receives from its neighbours (DWRR08 §4, Eq. 7): where
the skin changes slowly against the light's spread, that light is what the pixel's own homogeneous
model already predicts, and the fit can do without the renderer. ``forward: auto`` fits the cube
first with ``HomogeneousProblem`` (each pixel's homogeneous R_d times the window's light factor — a
render of uniform skin over its homogeneous value, so the window's dark edges are kept — no render per
evaluation), then asks the renderer at the maps it found: where the two differ, over the loss pixels
and used bands, by at most ``CROSSTALK_LIMIT`` of the cube's own noise (RMS of the difference over each
band's σ, ``grid_choice.band_noise``), the cross-talk the homogeneous fit left out adds at most a
quarter to the noise's variance, and its maps are kept. Otherwise the heterogeneous fit runs as
``forward: heterogeneous`` would, from its own start, so ``auto`` is never worse than the full model by
more than the check's cost. The check runs on the coarsest level first (one small render: a freckle
or a hair fails it there, before the finer levels are fitted), then on the finest.

What was checked, the values and why the winner won go into ``fit.json`` (``ForwardChoice.as_dict``).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import torch

from ..model import N_PARAMS
from .problem import Evaluation, HomogeneousProblem, LevelProblem

__all__ = ["CROSSTALK_LIMIT", "CrossTalkCheck", "ForwardChoice", "crosstalk_check", "window_light_factor"]

#: The homogeneous fit is kept where the renderer at its maps differs from it by at most this RMS, in
#: units of each band's noise σ: the left-out cross-talk then adds at most 0.5² = a quarter to the
#: noise's variance.
CROSSTALK_LIMIT = 0.5


def window_light_factor(problem: LevelProblem, x: torch.Tensor) -> torch.Tensor:
    """The window's light factor ``(L, H, W)`` at this level: the render of uniform skin at the median of
    the unknowns ``x`` ``(N_PARAMS, H, W)`` over the loss pixels, over that skin's homogeneous value
    (1 in the window's middle, less toward its edges). One render."""
    median = x.reshape(N_PARAMS, -1)[:, problem.pixels].median(dim=1).values
    uniform = median.view(N_PARAMS, 1, 1).expand_as(x).contiguous()
    with torch.no_grad():
        rendered = problem.evaluate(uniform, torch.zeros((), dtype=x.dtype, device=x.device)).image
        alone = problem.homogeneous_image(uniform)
    return (rendered / alone.clamp_min(1e-12)).detach()


@dataclass
class CrossTalkCheck:
    """The renderer against the homogeneous model at the homogeneous fit's maps, on one level:
    ``crosstalk_rms`` is the RMS of their difference in units of each band's noise, ``worst_band_nm``
    the band where it is largest, ``residual_rms_noise`` the renderer's residual in the same units."""

    level: int
    shape: list[int]
    mm_per_pixel: float
    crosstalk_rms: float
    worst_band_nm: float
    residual_rms_noise: float
    limit: float = CROSSTALK_LIMIT

    @property
    def passed(self) -> bool:
        return self.crosstalk_rms <= self.limit


def crosstalk_check(level_index: int, rendered: LevelProblem, homogeneous: HomogeneousProblem, x: torch.Tensor,
                    log_scale: torch.Tensor, noise: torch.Tensor) -> tuple[CrossTalkCheck, Evaluation]:
    """Render ``x`` with the renderer (one render) and compare with the homogeneous model, both scaled,
    in units of ``noise`` ``(L,)`` (each band's σ at this level); returns the check and the render's
    evaluation (what the fit keeps if the check passes)."""
    evaluation = rendered.evaluate(x, log_scale)
    with torch.no_grad():
        alone = homogeneous.render(x)
    used = rendered.band_weight > 0
    scale = torch.exp(log_scale)
    diff = rendered.at_pixels((evaluation.image - alone) * scale).double()[:, used] / noise[used].to(torch.float64)
    per_band = diff.pow(2).mean(0).sqrt()
    residual = evaluation.residual.double()[:, used] / noise[used].to(torch.float64)
    wavelengths = rendered.wavelength_nm[used.cpu()]
    check = CrossTalkCheck(
        level=level_index, shape=list(rendered.level.shape), mm_per_pixel=rendered.level.mm_per_pixel,
        crosstalk_rms=round(float(diff.pow(2).mean().sqrt()), 4), worst_band_nm=float(wavelengths[int(per_band.argmax())]),
        residual_rms_noise=round(float(residual.pow(2).mean().sqrt()), 4),
    )
    return check, evaluation


@dataclass
class ForwardChoice:
    """What ``forward`` chose for this cube and why: ``chosen`` ("homogeneous" or "heterogeneous"), the
    checks made (each level's ``CrossTalkCheck``), the seconds the homogeneous detour took."""

    setting: str
    chosen: str
    checks: list[CrossTalkCheck] = field(default_factory=list)
    homogeneous_wall_s: float = 0.0
    note: str = ""

    @property
    def reason(self) -> str:
        if self.setting != "auto":
            return f"forward: {self.setting} (fixed by the settings)"
        if not self.checks:
            return f"{self.note}: the heterogeneous renderer, as the full model"
        last = self.checks[-1]
        where = f"level {last.level + 1} ({last.shape[0]}×{last.shape[1]} px)"
        if self.chosen == "homogeneous":
            return (f"the renderer differs from the homogeneous fit by {last.crosstalk_rms:.2f} of the noise at {where} "
                    f"(limit {last.limit:g}): the cross-talk is below the noise, the homogeneous maps are kept")
        return (f"the renderer differs from the homogeneous fit by {last.crosstalk_rms:.2f} of the noise at {where}, "
                f"most at {last.worst_band_nm:g} nm (limit {last.limit:g}): the scene needs the heterogeneous renderer")

    def as_dict(self) -> dict:
        return {"setting": self.setting, "chosen": self.chosen, "reason": self.reason,
                "checks": [{**asdict(c), "passed": c.passed} for c in self.checks],
                "homogeneous_wall_s": round(self.homogeneous_wall_s, 3)}
