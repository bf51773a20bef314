"""The fit's unknowns: five bounded parameter maps through a smooth reparameterisation, the extension
of visible pixels' parameters onto masked ones, and the grid pyramid for coarse-to-fine.

Parameters. Each map p ∈ [lo, hi] (DWRR08 Table 1 ranges, ``PARAMETER_BOUNDS``) is
p = lo + (hi − lo) σ(x) with x unconstrained and σ the logistic function. Every lower bound is 0, and
for σ(x) ≪ 1, p ≈ (hi − lo) eˣ: the parameterisation is *logarithmic* where skin lives (C_m from 10⁻⁴
to 0.04 is x from −8.3 to −2.5), so a Gauss–Newton step moves a concentration by a relative amount and
C_m's four decades are one scale to the optimiser; near the upper bound it saturates smoothly. x is held
within ±``X_LIMIT`` (σ = 6·10⁻⁶ of the range from a bound) so a parameter driven to a bound stops there.

Extension. Pixels left out of the loss (outside the cube's mask: the window's edge ring, saturated or
dark pixels) still scatter light into visible ones. Their parameters are those of the nearest visible
pixel (DWRR08 §6.3 copies them after every step); here the copy is an index gather inside the graph,
so gradients reach the visible pixel they follow. The renderer pads the occluded border by replicating
the grid's edge (``model/render/renderer.py``: ``F.pad(..., mode="replicate")``, also inside the graph), and the
edge pixels already carry their nearest visible pixel's values: the border follows the nearest visible
pixel, as in the paper, without any copy between steps.

Shapes: unknowns ``(N_PARAMS, H, W)`` (maps: image layout); masks ``(H, W)``; cubes ``(L, H, W)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from scipy import ndimage

from ...formats.errors import InputError
from ...model import N_PARAMS, SkinParams, parameter_bounds

__all__ = [
    "X_LIMIT", "X_START_LIMIT", "Level", "bounds", "dparams_dx", "extend", "extension_index", "from_params", "near_bound",
    "params_of", "params_of_rows", "pyramid", "to_params", "upsample",
]

#: |x| cap: σ(±12) is 6·10⁻⁶ of the range from a bound — "at the bound" for every purpose here.
X_LIMIT = 12.0
#: Starts keep 0.25% of the range from a bound (σ(±6)), so no unknown starts where the map is flat.
X_START_LIMIT = 6.0


def bounds(dtype=torch.float32, device=None) -> tuple[torch.Tensor, torch.Tensor]:
    """Lower and upper bounds ``(N_PARAMS, 1, 1)`` (``model.parameter_bounds``), to broadcast over maps."""
    lo, hi = parameter_bounds(dtype, device)
    return lo.view(N_PARAMS, 1, 1), hi.view(N_PARAMS, 1, 1)


def near_bound(p: torch.Tensor, fraction: float, dim: int = 0) -> torch.Tensor:
    """Where a parameter lies within ``fraction`` of its range of a bound (the flag ``at_bound``, the
    point fit's ``at_bound`` list): ``p`` holds the ``N_PARAMS`` parameters along ``dim``; bool, ``p``'s shape."""
    lo, hi = parameter_bounds(p.dtype, p.device)
    shape = [1] * p.ndim
    shape[dim] = N_PARAMS
    lo, hi = lo.view(shape), hi.view(shape)
    margin = fraction * (hi - lo)
    return (p <= lo + margin) | (p >= hi - margin)


def to_params(x: torch.Tensor) -> torch.Tensor:
    """Unconstrained ``(N_PARAMS, ...)`` → parameters ``(N_PARAMS, ...)`` within their bounds."""
    lo, hi = bounds(x.dtype, x.device)
    shape = (N_PARAMS,) + (1,) * (x.ndim - 1)
    return lo.view(shape) + (hi - lo).view(shape) * torch.sigmoid(x)


def dparams_dx(x: torch.Tensor) -> torch.Tensor:
    """∂p/∂x ``(N_PARAMS, ...)``."""
    lo, hi = bounds(x.dtype, x.device)
    s = torch.sigmoid(x)
    return (hi - lo).view((N_PARAMS,) + (1,) * (x.ndim - 1)) * s * (1.0 - s)


def from_params(p: torch.Tensor, limit: float = X_LIMIT) -> torch.Tensor:
    """Parameters ``(N_PARAMS, ...)`` → unconstrained, clamped to ±``limit``."""
    lo, hi = bounds(p.dtype, p.device)
    shape = (N_PARAMS,) + (1,) * (p.ndim - 1)
    s = ((p - lo.view(shape)) / (hi - lo).view(shape)).clamp(1e-9, 1.0 - 1e-9)
    return torch.logit(s).clamp(-limit, limit)


def params_of_rows(x: torch.Tensor) -> SkinParams:
    """Unconstrained rows ``(N, N_PARAMS)`` (per-pixel layout) → ``SkinParams`` of contiguous ``(N,)``
    tensors: each parameter's values adjacent in memory, so the model's transcendental functions take
    their vectorised path for every pixel alike (a strided column rounds its tail differently)."""
    return params_of(x.T.contiguous())


def params_of(x: torch.Tensor) -> SkinParams:
    """``(N_PARAMS, ...)`` unconstrained → ``SkinParams`` of ``(...)`` tensors."""
    return SkinParams(*to_params(x).unbind(0))


def extension_index(mask: torch.Tensor) -> torch.Tensor:
    """For every pixel, the flat index of the nearest pixel where ``mask`` ``(H, W)`` is True ``(H·W,)``.

    Raises ``InputError`` (a ``ValueError``) when no pixel is visible."""
    m = mask.detach().cpu().numpy().astype(bool)
    if not m.any():
        raise InputError("no visible pixel: the cube's mask is empty (nothing to fit)")
    _, (iy, ix) = ndimage.distance_transform_edt(~m, return_indices=True)
    return torch.from_numpy((iy * m.shape[1] + ix).reshape(-1).astype(np.int64)).to(mask.device)


def extend(x: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """``(C, H, W)`` with every pixel replaced by the pixel ``index`` names (differentiable gather)."""
    c, h, w = x.shape
    return x.reshape(c, h * w).index_select(1, index).reshape(c, h, w)


def upsample(x: torch.Tensor, shape: tuple[int, int]) -> torch.Tensor:
    """Unconstrained maps ``(N_PARAMS, h, w)`` → ``(N_PARAMS, H, W)`` by bilinear interpolation (log-like in p)."""
    return F.interpolate(x[None], size=shape, mode="bilinear", align_corners=False)[0]


@dataclass(frozen=True)
class Level:
    """One grid of the coarse-to-fine pyramid: ``target`` ``(L, H, W)``, ``mask`` ``(H, W)`` of pixels
    in the loss, pixel size."""

    target: torch.Tensor
    mask: torch.Tensor
    mm_per_pixel: float

    @property
    def shape(self) -> tuple[int, int]:
        return tuple(self.mask.shape)  # type: ignore[return-value]


def pyramid(target: torch.Tensor, mask: torch.Tensor, mm_per_pixel: float, coarsest_px: int) -> list[Level]:
    """Levels from coarsest to finest: each halves the one above by 2×2 means (a coarse pixel is in the
    loss only when its four children are) while the longer side exceeds ``coarsest_px`` and both sides
    are even (so the window keeps its size in mm exactly)."""
    levels = [Level(target, mask, mm_per_pixel)]
    while coarsest_px > 0:
        t, m, mm = levels[-1].target, levels[-1].mask, levels[-1].mm_per_pixel
        h, w = m.shape
        if max(h, w) <= coarsest_px or h % 2 or w % 2 or min(h, w) < 8:
            break
        coarse_t = F.avg_pool2d(t[None], 2)[0]
        coarse_m = F.avg_pool2d(m[None, None].to(t.dtype), 2)[0, 0] > 0.999
        if not bool(coarse_m.any()):
            break
        levels.append(Level(coarse_t, coarse_m, 2.0 * mm))
    return levels[::-1]
