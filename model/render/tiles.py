"""Rendering maps larger than memory: in tiles, each with a halo of its neighbours as wide as the light's reach.

A camera's full frame needs many times the memory of a workstation rendered at once (``render_bytes``). Under
uniform light each pixel's answer depends only on the skin within the light's reach around it, so the
maps are cut into square tiles, each rendered with ``halo_px`` of the real neighbouring skin on every side
(beyond that, as at the maps' own edges, the skin is taken as its edge), and only its core is kept.
Every tile takes the inter-scattering terms of the whole maps (the worst pixel of all), so the tiles
differ from one render of the whole only by the light that travels farther than the halo. How far
that is, measured: docs/renderer.md, "Tiles".

Tiles need uniform light (a window, stripes or a point are placed on the whole grid); the other lights
render whole, and maps too large for that are refused before any large allocation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Iterator

import torch

from ...formats.errors import InputError
from ...formats.resources import USABLE_SHARE, ResourceError, format_bytes
from .illumination import Light
from ..patch.maps import SkinMaps
from .renderer import SkinRenderer, render_bytes

__all__ = ["MemoryPlan", "Tile", "TooLargeError", "plan_render", "render_tiled", "tiles"]

#: Smallest tile core (px): below this a tile's halo costs more than its core.
MIN_TILE_PX = 64
#: Where the budget comes from, for the refusals.
_BUDGET_SOURCE = (f"{USABLE_SHARE:.0%} of what SKINLAYERS_MEMORY_BUDGET_MB leaves beside this process's own memory, "
                  "else of the memory available here")
#: Tile cores are multiples of this (px).
TILE_STEP_PX = 32
#: Bands go in the fewest passes whose tile is at least this share of the largest tile any pass could have.
NEARLY_LARGEST = 0.9
#: The halo as a multiple of the renderer's border (render.border_mm): the light's reach.
HALO_BORDERS = 1.0
#: Bytes per pixel and band of what stays whole: the output image (float32) and its copy on writing.
_OUTPUT_BYTES_PER_CELL = 8
#: Bytes per pixel of the maps held whole (five parameters and the surface term, float32, and one copy).
_MAPS_BYTES_PER_PX = 48
#: What a render command adds whatever its size: the model's tables, the inter-scattering terms' pass
#: over the pixels (``SkinRenderer.series_terms_for``), the allocator's slack (measured: docs/renderer.md).
_COMMAND_BYTES = 100 * 2**20


class TooLargeError(ResourceError):
    """Work that cannot fit in the memory budget even in tiles; the message says what it needs."""


@dataclass(frozen=True)
class Tile:
    """A tile's core ``[y0, y1) × [x0, x1)`` and the region rendered for it (core plus halo, clipped to the maps)."""

    y0: int
    y1: int
    x0: int
    x1: int
    ya: int
    yb: int
    xa: int
    xb: int


@dataclass(frozen=True)
class MemoryPlan:
    """How a render fits the budget: whole (``tile_px`` None) or in tiles of ``tile_px``, the estimates."""

    tile_px: int | None
    halo_px: int
    whole_bytes: float
    peak_bytes: float
    budget_bytes: float
    bands_per_pass: int | None = None

    def describe(self) -> str:
        how = "whole" if self.tile_px is None else f"in tiles of {self.tile_px} px with a {self.halo_px}-px halo"
        if self.bands_per_pass is not None:
            how += f", {self.bands_per_pass} band(s) at a time"
        return (f"{how}: about {format_bytes(self.peak_bytes)} of a {format_bytes(self.budget_bytes)} budget "
                f"(whole: {format_bytes(self.whole_bytes)})")


def tiles(height: int, width: int, tile_px: int, halo_px: int) -> Iterator[Tile]:
    """The tiles covering ``height`` × ``width``, row by row."""
    for y0 in range(0, height, tile_px):
        for x0 in range(0, width, tile_px):
            y1, x1 = min(y0 + tile_px, height), min(x0 + tile_px, width)
            yield Tile(y0, y1, x0, x1, max(0, y0 - halo_px), min(height, y1 + halo_px),
                       max(0, x0 - halo_px), min(width, x1 + halo_px))


def plan_render(maps_shape: tuple[int, int, int], mm_per_pixel: float, bands: int, light: Light, renderer: SkinRenderer,
                budget_bytes: float, tile_px: int | None = None, itemsize: int = 4) -> MemoryPlan:
    """Whole if it fits ``budget_bytes`` (and no ``tile_px`` is asked for), else tiles: the bands rendered
    in the fewest passes whose tile is nearly the largest any pass could have (a halo costs less beside a
    large core); ``TooLargeError`` with the estimate, the budget and the way out where nothing fits."""
    b, h, w = maps_shape
    rs = renderer.settings.render
    border = light.border_px(mm_per_pixel, rs.border_mm)
    halo = int(math.ceil(HALO_BORDERS * rs.border_mm / mm_per_pixel))
    fixed = _COMMAND_BYTES + b * h * w * (_MAPS_BYTES_PER_PX + _OUTPUT_BYTES_PER_CELL * bands)
    whole = fixed + render_bytes(b, bands, h, w, border, itemsize=itemsize, weight_cache_mb=rs.weight_cache_mb)
    for group in range(bands, 0, -1) if tile_px is None else ():  # whole, in the fewest band passes that fit
        need = fixed + render_bytes(b, group, h, w, border, itemsize=itemsize, weight_cache_mb=rs.weight_cache_mb)
        if need <= budget_bytes:
            return MemoryPlan(None, halo, whole, need, budget_bytes, None if group == bands else group)
    if not light.extends:
        raise TooLargeError(
            f"rendering {h}×{w} px at {bands} band(s) needs about {format_bytes(whole)}; the budget is "
            f"{format_bytes(budget_bytes)} ({_BUDGET_SOURCE}), and only uniform light renders in tiles. Render fewer bands "
            f"or a smaller grid, or use --light uniform.")
    tile_bytes = _TileBytes(b, h, w, halo, rs.weight_cache_mb, itemsize)
    sizes = {g: tile_px if tile_px and fixed + tile_bytes(g, tile_px) <= budget_bytes
             else (None if tile_px else _largest_tile(g, fixed, budget_bytes, tile_bytes))
             for g in range(bands, 0, -1)}
    best = max((t for t in sizes.values() if t is not None), default=None)
    group = next((g for g, t in sizes.items() if t is not None and t >= NEARLY_LARGEST * best), None) if best else None
    size = sizes[group] if group is not None else None
    if size is not None and not tile_px:  # as many tiles, of even sizes (no sliver of a last tile)
        count = math.ceil(max(h, w) / size)
        size = min(size, TILE_STEP_PX * math.ceil(max(h, w) / count / TILE_STEP_PX))
    if size is None:
        raise TooLargeError(
            f"rendering {h}×{w} px at {bands} band(s) needs about {format_bytes(whole)} whole and more than "
            f"{format_bytes(budget_bytes)} ({_BUDGET_SOURCE}) even in tiles of {MIN_TILE_PX} px (the maps and the image alone take "
            f"{format_bytes(fixed)}). Render a smaller grid or fewer bands, or raise SKINLAYERS_MEMORY_BUDGET_MB.")
    peak = fixed + tile_bytes(group, size)
    return MemoryPlan(size, halo, whole, peak, budget_bytes, group)


@dataclass(frozen=True)
class _TileBytes:
    """The render estimate of the largest tile of a core side: its core and halo, clipped to the maps
    (a tile at the maps' edge has no halo beyond it; one as large as the maps has none at all)."""

    batch: int
    height: int
    width: int
    halo: int
    cache_mb: float
    itemsize: int

    def __call__(self, bands: int, size: int) -> float:
        rows, cols = self._longest(self.height, size), self._longest(self.width, size)
        return render_bytes(self.batch, bands, rows, cols, 0, itemsize=self.itemsize, weight_cache_mb=self.cache_mb)

    def _longest(self, length: int, size: int) -> int:
        """The longest tile region along an axis of ``length`` px cut in cores of ``size`` (as ``tiles`` cuts it)."""
        return max(min(length, start + size + self.halo) - max(0, start - self.halo) for start in range(0, length, size))


def _largest_tile(bands: int, fixed: float, budget: float, tile_bytes: _TileBytes) -> int | None:
    """The largest tile core (a multiple of ``TILE_STEP_PX``, at least ``MIN_TILE_PX``) whose render fits
    beside what stays whole; None where not even the smallest does."""
    size = max(MIN_TILE_PX, (max(tile_bytes.height, tile_bytes.width) // TILE_STEP_PX) * TILE_STEP_PX)
    while size >= MIN_TILE_PX:
        if fixed + tile_bytes(bands, size) <= budget:
            return size
        size -= TILE_STEP_PX
    return None


def render_tiled(renderer: SkinRenderer, maps: SkinMaps, light: Light, wavelength_nm: torch.Tensor, tile_px: int,
                 halo_px: int, progress: Callable[[int, int], None] | None = None, bands_per_pass: int | None = None,
                 **render_options) -> torch.Tensor:
    """The image ``(B, L, H, W)`` (float32, on the CPU) rendered tile by tile (uniform light only), each
    tile's bands ``bands_per_pass`` at a time (default: all at once)."""
    if not light.extends:
        raise InputError("tiled rendering needs uniform light (other lights are placed on the whole grid)")
    b, h, w = maps.shape
    wl = torch.as_tensor(wavelength_nm, dtype=torch.float64).reshape(-1)
    cut = list(tiles(h, w, tile_px, halo_px))
    terms = max(renderer.series_terms_for(_crop(maps, t), wl) for t in tiles(h, w, tile_px, 0))  # the whole maps' worst pixel
    out = torch.empty(b, wl.numel(), h, w, dtype=torch.float32)
    step = bands_per_pass or wl.numel()
    for k, t in enumerate(cut):
        for j in range(0, wl.numel(), step):
            with torch.no_grad():
                image = renderer.render(_crop(maps, t), light, wl[j:j + step], series_terms=terms, **render_options).image
            out[:, j:j + step, t.y0:t.y1, t.x0:t.x1] = image[..., t.y0 - t.ya:t.y1 - t.ya, t.x0 - t.xa:t.x1 - t.xa].float().cpu()
        if progress is not None:
            progress(k + 1, len(cut))
    return out


def _crop(maps: SkinMaps, t: Tile) -> SkinMaps:
    """The maps of the tile's rendered region (core and halo)."""
    def cut(v):
        return None if v is None else v[..., t.ya:t.yb, t.xa:t.xb]

    return maps.replace(C_m=cut(maps.C_m), beta_m=cut(maps.beta_m), C_he=cut(maps.C_he), C_bc=cut(maps.C_bc),
                        C_hd=cut(maps.C_hd), rho_s=cut(maps.rho_s), absorbance=cut(maps.absorbance))
