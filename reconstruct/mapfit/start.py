"""Where the map fit starts: the paper's pale skin, or every pixel's own homogeneous inversion.

``paper``: DWRR08 §8's "very pale Caucasian" parameters everywhere (``PAPER_START``).

``homogeneous``: the point-spectrum fit (``spectrum_fit.fit_spectra`` with ``method="tables"``:
batched projected Levenberg–Marquardt on the homogeneous model's tabulated totals, four starts per
spectrum; faster than the exact fit at the render bands and hardly worse: docs/model.md, "From
reconstruct/mapfit/start.py") of every loss pixel's
spectrum, divided by the camera's exit factor (the cube holds reflectance factors at the view angle,
the homogeneous model diffuse reflectance), ignoring the cross-talk between pixels and the window's
dark edges. It runs on the coarsest level only, where pixels are few; finer levels start from the
level below, which already carries the cross-talk.

Shapes: unknowns ``(N_PARAMS, H, W)``.
"""

from __future__ import annotations

import torch

from ...model import N_PARAMS, PARAMETER_NAMES, SkinModel
from ..levels.problem import LevelProblem
from ..spectrum.spectrum_fit import PAPER_START, fit_spectra
from ..levels.unknowns import X_START_LIMIT, extend, from_params

__all__ = ["STARTS", "homogeneous_start", "mean_spectrum_start", "paper_start"]


def paper_start(problem: LevelProblem, dtype=torch.float32, device=None) -> torch.Tensor:
    h, w = problem.level.shape
    p = torch.tensor([PAPER_START[n] for n in PARAMETER_NAMES], dtype=torch.float64).view(N_PARAMS, 1, 1).expand(N_PARAMS, h, w)
    return from_params(p, X_START_LIMIT).to(dtype=dtype, device=device).contiguous()


def _inverted(problem: LevelProblem, spectra: torch.Tensor) -> torch.Tensor:
    """The homogeneous inversion of reflectance-factor ``spectra`` ``(M, L)`` at the problem's used bands:
    parameters ``(M, N_PARAMS)``."""
    used = problem.band_weight > 0
    model = SkinModel(problem.renderer.settings, problem.renderer.model.cache_dir)
    fit = fit_spectra((spectra[:, used].to(torch.float64) / problem.exit).cpu(), problem.wavelength_nm[used.cpu()].cpu(), model,
                      max_iterations=50, method="tables")
    return fit.params.as_tensor()


def homogeneous_start(problem: LevelProblem, dtype=torch.float32, device=None) -> torch.Tensor:
    """Per-pixel homogeneous inversion of the loss pixels; the others follow their nearest one."""
    h, w = problem.level.shape
    p = torch.tensor([PAPER_START[n] for n in PARAMETER_NAMES], dtype=torch.float64).view(N_PARAMS, 1).repeat(1, h * w)
    p[:, problem.pixels.cpu()] = _inverted(problem, problem.target).T
    x = from_params(p.reshape(N_PARAMS, h, w), X_START_LIMIT).to(dtype=dtype, device=device)
    return extend(x, problem.index)


def mean_spectrum_start(problem: LevelProblem, dtype=torch.float32, device=None) -> torch.Tensor:
    """The homogeneous inversion of the loss pixels' mean spectrum, everywhere: one point fit instead of
    one per pixel, where the skin is to be fitted as uniform first (``forward: auto``'s light factor)."""
    h, w = problem.level.shape
    p = _inverted(problem, problem.target.mean(0, keepdim=True))[0]
    return from_params(p.view(N_PARAMS, 1, 1), X_START_LIMIT).expand(N_PARAMS, h, w).to(dtype=dtype, device=device).contiguous()


#: ``FitSettings.start`` → the function that makes the coarsest level's unknowns.
STARTS = {"paper": paper_start, "homogeneous": homogeneous_start}
