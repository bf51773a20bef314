"""The fit's optimisers, by name (``FitSettings.method``): one explicit table.

An optimiser takes a ``LevelProblem``, a start (unknowns ``(N_PARAMS, H, W)`` and the log of the global
scale), the settings and a progress callback, and returns an ``OptimResult`` (``problem.py``): the end
point, its evaluation, the history of (process CPU seconds, loss) after every accepted step, and
per-pixel convergence. Every method stops on a convergence test (relative loss decrease below ``ftol``
or largest step below ``xtol``), with ``max_iterations`` only as a safety net.

| name | what | renders per iteration |
|---|---|---|
| ``gn-hom`` | Gauss–Newton/LM, per-pixel normal equations from each pixel's homogeneous Jacobian (scaled by the window's light factor) applied to the *heterogeneous* residual | 1 forward |
| ``gn`` | the same curvature, with the exact gradient Jᵀr of the heterogeneous renderer | 1 forward + backward |
| ``adam`` | Adam (Kingma & Ba 2015) on the exact gradient | 1 forward + backward |
| ``paper-fd`` | DWRR08 §6.3: gradient descent, gradient by forward differences of each parameter map shifted everywhere at once | 1 + N_PARAMS forward |
"""

from __future__ import annotations

from typing import Callable

from .first_order import adam, paper_forward_differences
from .gauss_newton import gn_exact, gn_homogeneous
from ..levels.problem import OptimResult

__all__ = ["METHODS", "OptimResult", "PER_PIXEL_METHODS"]

#: name → callable(problem, x0, log_scale0, settings, progress) → OptimResult
METHODS: dict[str, Callable[..., OptimResult]] = {
    "gn-hom": gn_homogeneous,
    "gn": gn_exact,
    "adam": adam,
    "paper-fd": paper_forward_differences,
}

#: Methods that fit every map per pixel. ``gn`` too: its exact gradient with the homogeneous curvature
#: does not control shared nodes (docs/reconstruct.md).
PER_PIXEL_METHODS = ("gn", "adam", "paper-fd")
