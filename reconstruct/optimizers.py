"""One interface for the fit's optimisers and their registry (``method=``).

An optimiser takes a ``LevelProblem``, a start (unknowns ``(5, H, W)`` and the log of the global
scale) and the settings, and returns an ``OptimResult``: the end point, its evaluation, the history of
(process CPU seconds, loss) after every accepted step, and per-pixel convergence. Every method stops on
a convergence test (relative loss decrease below ``ftol`` or largest step below ``xtol``), with
``max_iterations`` only as a safety net.

| name | what | renders per iteration |
|---|---|---|
| ``gn-hom`` | Gauss–Newton/LM, per-pixel 5×5 normal equations from each pixel's homogeneous Jacobian (scaled by the window's light factor) applied to the *heterogeneous* residual | 1 forward |
| ``gn`` | the same curvature, with the exact gradient Jᵀr of the heterogeneous renderer | 1 forward + backward |
| ``adam`` | Adam (Kingma & Ba 2015) on the exact gradient | 1 forward + backward |
| ``paper-fd`` | DWRR08 §6.3: gradient descent, gradient by forward differences of each parameter map shifted everywhere at once | 6 forward |
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import torch

from .problem import Evaluation

__all__ = ["METHODS", "OptimResult", "register_method"]


@dataclass
class OptimResult:
    """``x`` ``(5, H, W)``; ``log_scale`` 0-d; ``evaluation`` at the end point; ``iterations``;
    ``converged`` (the test, not the cap, stopped it); ``history``: (CPU s, loss) after each accepted
    step; ``pixel_step`` ``(N,)``: size of the last proposed step per loss pixel (∞-norm in x), NaN
    where the method has none; ``curvature`` ``(N, 5, 5)`` Gauss–Newton JᵀJ in x at the end (if any);
    ``shared_decrement``: with maps on nodes, the χ² decrease the last step predicted from the nodes
    (about Σ (move/σ)² over them, σ² from the residual; 0 without)."""

    x: torch.Tensor
    log_scale: torch.Tensor
    evaluation: Evaluation
    iterations: int
    converged: bool
    history: list[tuple[float, float]] = field(default_factory=list)
    pixel_step: torch.Tensor | None = None
    curvature: torch.Tensor | None = None
    shared_decrement: float = 0.0


#: name → callable(problem, x0, log_scale0, settings, progress) → OptimResult
METHODS: dict[str, Callable[..., OptimResult]] = {}


def register_method(name: str):
    def deco(fn):
        METHODS[name] = fn
        return fn

    return deco


def _load_all() -> None:
    from . import first_order, gauss_newton  # noqa: F401, PLC0415 (they register themselves)


_load_all()
