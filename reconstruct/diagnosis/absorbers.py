"""Extra unknowns where the residual asks: a grey interface absorbance on the pixels a hair darkens.

The fit's skin has no absorber for hair: a hair lying on or in the skin darkens the light that leaves
through it at every band about alike, and the light that enters through it is missing from its
neighbours, in red light up to a millimetre away. Fitted without it, the hair's pixels are explained by
melanin and the halo by everything around them (docs/reconstruct.md, "Hairs"). DWRR08 §4.2 holds such
absorbers in the thin interface layer between epidermis and dermis (attenuation A = e^{−P}, met once on
the way in and once on the way out); the renderer draws them (``SkinMaps.absorbance``), so the fit can
take P as an unknown wherever the data call for one.

Where. After the finest level's fit, the candidates are the pixels whose residual RMS exceeds
``high_residual_factor`` × the median pixel's (the pixels the fit would flag; Cauchy weights already
discount them), dilated by ``DILATE_PX`` (a hair's edge pixels are darkened less and pass the test less
often). Nothing is added where no pixel is a candidate.

How. P ≥ 0 per candidate pixel, grey (one value for every band), fitted together with the pixel's own
per-pixel maps (alone, P raised the pixel's χ²: melanin had taken the hair's place) by damped
Gauss–Newton: the pixel's Jacobian is its homogeneous model's (with the absorbance) times the render's
light factor, as ``gn-hom`` takes it for the maps (``EXIT_SHARE`` scales P's column: 1, the same rule;
0.5, the exit crossing alone, was tried and was no better). Each step is kept when the whole render's
loss falls, else halved, so the halo that P draws in the neighbours is weighed too.

Which stay. BIC per added unknown with the noise known (``grid_choice.band_noise``): a pixel keeps its P
where its own χ² falls by more than ln n (n the data the fit sees: pixels × used bands); the others go
back to 0. The maps are then refitted on the finest level with the kept P held (``fit.fit_cube``).

Shapes: P ``(H, W)``; per-candidate rows ``(K, ·)``.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
import torch
from scipy import ndimage

from ..levels.least_squares import block_factor, block_solve, reverse_jacobian
from ..levels.problem import LevelProblem
from ..levels.unknowns import X_LIMIT, params_of_rows

__all__ = ["DILATE_PX", "EXIT_SHARE", "AbsorberFit", "candidate_rows", "fit_grey_absorbance"]

#: Candidates grow by this many pixels (a hair's edge pixels are darkened less than its centre).
DILATE_PX = 1
#: Scale of the homogeneous model's ∂R/∂P in the pixel's Jacobian (1: as gn-hom treats the maps).
EXIT_SHARE = 1.0
#: Gauss–Newton steps on P (each one render of the finest level, more where a step is halved), and the
#: relative fall of the loss below which they stop.
ITERATIONS = 8
RTOL = 1e-3
#: A step's halvings before the steps stop (no smaller step lowers the loss).
HALVINGS = 3
#: P is held within [0, P_MAX] (e^{−8} lets 0.03% through) and moves by at most MAX_STEP a step.
P_MAX = 8.0
MAX_STEP = 2.0
#: Marquardt damping of the joint steps (after Jacobi scaling: a tenth of a unit diagonal).
DAMPING = 0.1


@dataclass
class AbsorberFit:
    """What the absorber step found: ``absorbance`` ``(H, W)`` P kept (0 elsewhere), the candidates,
    how many kept their P, the χ² (noise known) of the whole fit before and after, the per-unknown
    penalty ln n, the steps taken, and why."""

    absorbance: torch.Tensor
    candidates: int
    kept: int
    chi2_before: float
    chi2_after: float
    penalty_per_unknown: float
    steps: int
    reason: str

    def as_dict(self) -> dict:
        out = asdict(self)
        out.pop("absorbance")
        out["absorbance_max"] = float(self.absorbance.max()) if self.kept else 0.0
        return out


def candidate_rows(problem: LevelProblem, rms: torch.Tensor, factor: float) -> torch.Tensor:
    """Loss rows ``(N,)`` bool: residual RMS ``rms`` ``(N,)`` above ``factor`` × its median, dilated by
    ``DILATE_PX`` within the loss pixels."""
    high = rms > factor * rms.median()
    h, w = problem.level.shape
    image = np.zeros(h * w, dtype=bool)
    image[problem.pixels.cpu().numpy()] = high.cpu().numpy()
    if DILATE_PX:
        image = ndimage.binary_dilation(image.reshape(h, w), iterations=DILATE_PX).reshape(-1)
    return torch.from_numpy(image[problem.pixels.cpu().numpy()]).to(rms.device)


def _chi2_rows(problem: LevelProblem, residual: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
    """Each loss pixel's χ² ``(N,)`` over the used bands, from an unweighted residual ``(N, L)``."""
    used = problem.band_weight > 0
    return ((residual[:, used] / noise[used]) ** 2).sum(1)


def _plain_residual(problem: LevelProblem, ev) -> torch.Tensor:
    return problem.at_pixels(ev.image) * torch.exp(ev.log_scale) - problem.target


def _moved(x, flat, fine, x_rows, step, p_rows):
    """The maps ``x`` ``(N_PARAMS, H, W)`` with the candidates' own maps moved and their P."""
    out = x.clone()
    grid = out.reshape(out.shape[0], -1)
    for c, m in enumerate(fine):
        grid[m, flat] = (x_rows[:, m] + step[:, c]).clamp(-X_LIMIT, X_LIMIT)
    return out, (p_rows + step[:, -1]).clamp(0.0, P_MAX)


def fit_grey_absorbance(problem: LevelProblem, x: torch.Tensor, log_scale: torch.Tensor, noise: torch.Tensor,
                        candidates: torch.Tensor) -> tuple[AbsorberFit, torch.Tensor]:
    """Fit P on the ``candidates`` rows ``(N,)`` together with their own (per-pixel) maps, the rest of ``x``
    held; returns what was found and the maps ``(N_PARAMS, H, W)`` after (the candidates that keep no P
    keep their maps). ``problem.absorbance`` is left at the kept P. ``noise`` ``(L,)`` the cube's σ per
    band at this level."""
    n_data = problem.n_pixels * int((problem.band_weight > 0).sum())
    penalty = math.log(max(n_data, 2))
    weight, problem.pixel_weight = problem.pixel_weight, None  # P answers the camera's noise, not the robust weights
    try:
        problem.absorbance = None
        ev0 = problem.evaluate(x, log_scale)
        chi2_rows0 = _chi2_rows(problem, _plain_residual(problem, ev0), noise)
        rows = candidates.nonzero()[:, 0]
        search = _GreyAbsorbance(problem, x, rows)
        if rows.numel() == 0:
            chi2 = float(chi2_rows0.sum())
            return AbsorberFit(search.image_of(None), 0, 0, chi2, chi2, penalty, 0,
                               "no pixel's residual is above the flag's threshold"), x
        x_fit, p_rows, ev, steps = search.iterate(x, log_scale, ev0)
        return search.keep(x, x_fit, p_rows, ev, log_scale, noise, chi2_rows0, penalty, steps)
    finally:
        problem.pixel_weight = weight


class _GreyAbsorbance:
    """A grey absorbance P per candidate pixel (``rows``), fitted with the maps that pixel owns: damped
    Gauss–Newton on each pixel's homogeneous model scaled to the renderer's image, the whole step or
    its halves while the loss does not fall; then BIC decides which P stay."""

    def __init__(self, problem: LevelProblem, x: torch.Tensor, rows: torch.Tensor) -> None:
        self.problem, self.rows = problem, rows
        self.h, self.w = problem.level.shape
        self.dtype, self.device = x.dtype, x.device
        self.flat = problem.pixels[rows]
        self.fine = list(problem.layout.fine)  # the maps a pixel owns move with its P (melanin took the hair's place)
        self.used = (problem.band_weight > 0).to(x.dtype)

    def image_of(self, p_rows: torch.Tensor | None) -> torch.Tensor:
        """P of the rows on the level's grid ``(H, W)`` (zero elsewhere; all zero for ``None``)."""
        p = torch.zeros(self.h * self.w, dtype=self.dtype, device=self.device)
        if p_rows is not None:
            p[self.flat] = p_rows
        return p.reshape(self.h, self.w)

    def _hom(self, v: torch.Tensor) -> torch.Tensor:
        """``(K, N_PARAMS + 1)`` → ``(K, L)``: the pixel's homogeneous model with its own grey P."""
        wl = self.problem.wavelength_nm
        return self.problem.renderer.model.diffuse_reflectance(params_of_rows(v[:, :-1]), wl, method="tables",
                                                               extra_absorbance=v[:, -1:].expand(-1, wl.numel()))

    def _step(self, x_rows: torch.Tensor, p_rows: torch.Tensor, ev) -> torch.Tensor:
        """The damped Gauss–Newton step ``(K, fine + 1)`` of the rows' own maps and P."""
        problem = self.problem
        value, jac = reverse_jacobian(self._hom, torch.cat([x_rows, p_rows[:, None]], 1).double())
        het = problem.at_pixels(ev.image)[self.rows].double()
        factor = (het / (value * problem.exit).clamp_min(1e-12)).clamp(0.0, 2.0) * float(torch.exp(ev.log_scale))
        cols = self.fine + [x_rows.shape[1]]
        j = jac[..., cols] * (problem.exit * factor * self.used.double())[..., None]  # (K, L, fine + 1)
        j[..., -1] *= EXIT_SHARE
        r = ev.residual[self.rows].double()
        g = (j.transpose(1, 2) @ r[..., None])[..., 0]
        step = -block_solve(block_factor(j.transpose(1, 2) @ j, DAMPING), g[..., None])[..., 0]
        return step.clamp(-MAX_STEP, MAX_STEP).to(self.dtype)

    def iterate(self, x: torch.Tensor, log_scale: torch.Tensor, ev):
        """Steps until the loss stops falling; returns the maps, the rows' P, the last evaluation and the
        evaluations spent. ``problem.absorbance`` holds the P of the last evaluation."""
        problem = self.problem
        x = x.clone()
        x_rows = problem.at_pixels(x)[self.rows]
        p_rows = torch.zeros(int(self.rows.numel()), dtype=self.dtype, device=self.device)
        steps = 0
        for _ in range(ITERATIONS):
            step = self._step(x_rows, p_rows, ev)
            for _halving in range(HALVINGS):  # the whole step, else half of it, while the loss does not fall
                x_trial, p_trial = _moved(x, self.flat, self.fine, x_rows, step, p_rows)
                problem.absorbance = self.image_of(p_trial)
                trial = problem.evaluate(x_trial, log_scale)
                steps += 1
                if trial.loss < ev.loss:
                    break
                step = 0.5 * step
            else:
                problem.absorbance = self.image_of(p_rows)
                break
            relative = (ev.loss - trial.loss) / max(ev.loss, 1e-300)
            x, p_rows, ev = x_trial, p_trial, trial
            x_rows = problem.at_pixels(x)[self.rows]
            if relative < RTOL:
                break
        return x, p_rows, ev, steps

    def keep(self, x_start, x, p_rows, ev, log_scale, noise, chi2_rows0, penalty: float, steps: int):
        """BIC per unknown: the pixel's own χ² must fall by more than ln n for its P to stay; a pixel
        that keeps no P keeps its maps as they were. Leaves ``problem.absorbance`` at the kept P."""
        problem, k = self.problem, int(self.rows.numel())
        chi2_rows = _chi2_rows(problem, _plain_residual(problem, ev), noise)
        keep = chi2_rows0[self.rows] - chi2_rows[self.rows] > penalty
        p_kept = torch.where(keep, p_rows, torch.zeros_like(p_rows))
        dropped = self.flat[~keep]
        x.reshape(x.shape[0], -1)[:, dropped] = x_start.reshape(x.shape[0], -1)[:, dropped]
        problem.absorbance = self.image_of(p_kept) if bool(keep.any()) else None
        final = problem.evaluate(x, log_scale)
        chi2_after = float(_chi2_rows(problem, _plain_residual(problem, final), noise).sum())
        kept = int(keep.sum())
        reason = (f"{kept} of {k} candidate pixel(s) lowered their own chi2 by more than ln n = {penalty:.1f} with a "
                  f"grey absorbance (the fit's chi2 {float(chi2_rows0.sum()):.4g} -> {chi2_after:.4g})")
        return AbsorberFit(self.image_of(p_kept) if kept else self.image_of(None), k, kept,
                           float(chi2_rows0.sum()), chi2_after, penalty, steps, reason), x
