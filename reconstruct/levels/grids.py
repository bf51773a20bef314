"""Each parameter map on its own grid: per pixel, or on coarser nodes interpolated onto the pixels.

Why. The camera sees the dermis only through the light's millimetre spread, and β_m and C_bc only
through small changes of the spectrum's shape: per pixel, at a real camera's noise, they are not
determined (Cramér–Rao bound, ``tests/bench/test_bench_identifiability.py``; the bounds:
docs/reconstruct.md, "Why: what the data hold"), and their noise leaks into C_m through the
correlations. A map may therefore be fitted on a grid of nodes ``cell_mm`` apart, bilinearly
interpolated onto the pixels in the unconstrained (log-like) parameter — "model no more than a scene
needs": the unknowns are the nodes, each seen by every pixel around it.

``MapGrid`` is the bilinear operator U ``(H·W) × n`` from ``n = h·w`` nodes onto the pixels, stored
sparsely (four nodes and weights per pixel) with exactly the sampling of
``F.interpolate(mode="bilinear", align_corners=False)``: nodes sit at the centres of ``h × w``
equal cells over the grid, so the same node grid serves every level of the coarse-to-fine pyramid.
``MapLayout`` says which maps are per pixel ("fine") and which on nodes ("coarse"), numbers the nodes
of all coarse maps in one vector z, assembles the unknowns ``(5, H, W)`` from the fine maps and z, and
projects unknowns onto z by least squares.

Shapes: unknowns ``(5, H, W)``; z ``(n_nodes,)``; per-pixel local blocks ``(N, 4·n_coarse)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ...model import PARAMETER_NAMES
from .unknowns import X_LIMIT

__all__ = ["MapGrid", "MapLayout", "node_count"]

#: A map whose node spacing is below this many pixels is fitted per pixel.
_MIN_CELL_PX = 2.0


def node_count(size_mm: float, cell_mm: float, pixels: int) -> int:
    """Nodes along one side: one per ``cell_mm`` (at least one), never more than the pixels."""
    if cell_mm <= 0:
        return pixels
    return max(1, min(pixels, round(size_mm / cell_mm)))


def _axis(n_out: int, n_in: int, dtype, device) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Lower and upper source index and the upper one's weight for each of ``n_out`` samples
    (the ``align_corners=False`` rule of ``F.interpolate``)."""
    src = ((torch.arange(n_out, dtype=torch.float64) + 0.5) * (n_in / n_out) - 0.5).clamp_min(0.0)
    lo = src.floor().long().clamp_max(n_in - 1)
    hi = (lo + 1).clamp_max(n_in - 1)
    frac = (src - lo.double()).clamp(0.0, 1.0)
    return lo.to(device), hi.to(device), frac.to(dtype=dtype, device=device)


@dataclass(frozen=True)
class MapGrid:
    """Bilinear interpolation from ``nodes`` ``(h, w)`` onto ``shape`` ``(H, W)``: ``index`` and
    ``weight`` ``(H·W, 4)``."""

    nodes: tuple[int, int]
    shape: tuple[int, int]
    index: torch.Tensor
    weight: torch.Tensor

    @classmethod
    def build(cls, shape: tuple[int, int], nodes: tuple[int, int], dtype=torch.float32, device=None) -> "MapGrid":
        (hh, ww), (h, w) = shape, nodes
        if not (1 <= h <= hh and 1 <= w <= ww):
            raise ValueError(f"a map grid of {h}×{w} nodes does not fit {hh}×{ww} pixels")
        y0, y1, fy = _axis(hh, h, dtype, device)
        x0, x1, fx = _axis(ww, w, dtype, device)
        iy = torch.stack([y0, y0, y1, y1], 1)[:, None, :].expand(hh, ww, 4)
        ix = torch.stack([x0, x1, x0, x1], 1)[None, :, :].expand(hh, ww, 4)
        wy = torch.stack([1 - fy, 1 - fy, fy, fy], 1)[:, None, :]
        wx = torch.stack([1 - fx, fx, 1 - fx, fx], 1)[None, :, :]
        index = (iy * w + ix).reshape(hh * ww, 4)
        return cls((h, w), (hh, ww), index.contiguous(), (wy * wx).reshape(hh * ww, 4).contiguous())

    @property
    def n_nodes(self) -> int:
        return self.nodes[0] * self.nodes[1]

    def up(self, z: torch.Tensor) -> torch.Tensor:
        """Node values ``(h·w,)`` → pixel values ``(H, W)``."""
        return (z[self.index] * self.weight.to(z.dtype)).sum(-1).reshape(self.shape)

    def project(self, values: torch.Tensor) -> torch.Tensor:
        """The node values whose interpolation is nearest to ``values`` ``(H, W)`` in least squares."""
        n = self.n_nodes
        w = self.weight.double()
        normal = torch.zeros(n * n, dtype=torch.float64, device=values.device)
        flat = (self.index[:, :, None] * n + self.index[:, None, :]).reshape(-1)
        normal.index_add_(0, flat, (w[:, :, None] * w[:, None, :]).reshape(-1))
        rhs = torch.zeros(n, dtype=torch.float64, device=values.device)
        rhs.index_add_(0, self.index.reshape(-1), (w * values.reshape(-1, 1).double()).reshape(-1))
        normal = normal.reshape(n, n) + 1e-10 * torch.eye(n, dtype=torch.float64, device=values.device)
        return torch.linalg.solve(normal, rhs).to(values.dtype)


class MapLayout:
    """Which maps are per pixel and which on nodes, at one grid level.

    ``cell_mm`` maps parameter names to node spacing in mm (0 or absent: per pixel; below two pixels:
    per pixel too, on coarse cubes). ``fine`` and
    ``coarse`` list map indices (order of ``PARAMETER_NAMES``); ``grids[k]`` is map k's ``MapGrid``;
    ``offsets[k]`` where its nodes start in z."""

    def __init__(self, shape: tuple[int, int], mm_per_pixel: float, cell_mm: dict[str, float] | None, dtype=torch.float32, device=None):
        cell_mm = dict(cell_mm or {})
        unknown = set(cell_mm) - set(PARAMETER_NAMES)
        if unknown:
            raise ValueError(f"map_cell_mm: unknown map(s) {sorted(unknown)}; the maps are {', '.join(PARAMETER_NAMES)}")
        self.shape = tuple(shape)
        self.grids: dict[int, MapGrid] = {}
        self.offsets: dict[int, int] = {}
        total = 0
        for k, name in enumerate(PARAMETER_NAMES):
            cell = float(cell_mm.get(name, 0.0) or 0.0)
            if cell < _MIN_CELL_PX * mm_per_pixel:
                continue  # nodes nearly as dense as the pixels: per pixel (resampling would only blur)
            nodes = (node_count(shape[0] * mm_per_pixel, cell, shape[0]), node_count(shape[1] * mm_per_pixel, cell, shape[1]))
            if nodes == tuple(shape):
                continue  # a node per pixel: the map is per pixel
            self.grids[k] = MapGrid.build(self.shape, nodes, dtype, device)
            self.offsets[k] = total
            total += self.grids[k].n_nodes
        self.coarse = sorted(self.grids)
        self.fine = [k for k in range(len(PARAMETER_NAMES)) if k not in self.grids]
        self.n_nodes = total

    @property
    def per_pixel(self) -> bool:
        """True when every map is per pixel (the plain 5×5 per-pixel fit)."""
        return not self.coarse

    def describe(self) -> dict[str, list[int] | str]:
        """Map name → node grid ``[h, w]``, or "pixel"."""
        return {name: (list(self.grids[k].nodes) if k in self.grids else "pixel") for k, name in enumerate(PARAMETER_NAMES)}

    def project(self, x: torch.Tensor, clip_quantile: float = 0.0) -> torch.Tensor:
        """Unknowns ``(5, H, W)`` → z ``(n_nodes,)`` (least squares per coarse map), each map first
        clipped to its ``clip_quantile``…1 − ``clip_quantile`` range (a start from noisy per-pixel fits
        puts many values at the start's bounds)."""
        parts = []
        for k in self.coarse:
            values = x[k]
            if clip_quantile > 0:
                q = torch.quantile(values.reshape(-1).double(), torch.tensor([clip_quantile, 1.0 - clip_quantile], dtype=torch.float64, device=values.device))
                values = values.clamp(float(q[0]), float(q[1]))
            parts.append(self.grids[k].project(values))
        return torch.cat(parts) if parts else x.new_zeros(0)

    def assemble(self, x: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """Unknowns ``(5, H, W)``: the fine maps of ``x``, the coarse ones interpolated from ``z``."""
        out = x.clone()
        for k in self.coarse:
            g = self.grids[k]
            out[k] = g.up(z[self.offsets[k]: self.offsets[k] + g.n_nodes]).clamp(-X_LIMIT, X_LIMIT)
        return out

    def local(self, pixels: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """For the loss ``pixels`` ``(N,)`` (flat indices): the z index and weight of each of the four
        nodes of every coarse map, ``(N, 4·n_coarse)`` each, coarse maps in order."""
        idx = [self.grids[k].index[pixels] + self.offsets[k] for k in self.coarse]
        wts = [self.grids[k].weight[pixels] for k in self.coarse]
        return torch.cat(idx, 1), torch.cat(wts, 1)

    def at_pixels(self, dz: torch.Tensor, pixels: torch.Tensor) -> torch.Tensor:
        """A change of z → the change of each coarse map at the ``pixels`` ``(N, n_coarse)``."""
        idx, wts = self.local(pixels)
        n = pixels.numel()
        return (dz[idx] * wts.to(dz.dtype)).reshape(n, len(self.coarse), 4).sum(-1)
