"""Illumination on the render grid: uniform, the tape window, stripes, a point, an image.

A ``Light`` says what irradiance (relative to 1 = the reference irradiance) falls on each pixel of
the maps' grid and of a border around it. The border stands for skin beyond the maps: its
parameters follow the nearest pixel of the maps (the paper copies them from the nearest visible
pixel, DWRR08 §6.3) and light scattered into it can come back. Beyond the border the scene is dark,
except for uniform light, which extends for ever (the blurs then replicate the edges).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ...formats.errors import InputError

__all__ = ["Light", "parse_light"]

#: Skin beyond the maps, when neither the light nor the settings say (DWRR08 §6.3 uses 1 cm; what 5 mm
#: changes: docs/renderer.md).
DEFAULT_BORDER_MM = 5.0


@dataclass(frozen=True)
class Light:
    """``kind``: uniform, window, stripes, point or image.

    - window: a square of ``size_mm`` centred on the grid, lit; everything else (rest of the grid
      and the border) dark — the black tape of the measurement (DWRR08 §6.1, §6.3);
    - stripes: lit bands of ``period_mm`` × ``duty`` across x, over grid and border;
    - point: unit power into the centre pixel (irradiance 1/pixel area), for profile checks;
    - image: ``image`` ``(H, W)`` or ``(B, H, W)`` on the maps' grid, dark border.
    """

    kind: str = "uniform"
    size_mm: float = 7.5
    period_mm: float = 2.0
    duty: float = 0.5
    border_mm: float | None = None
    image: torch.Tensor | None = None

    def __post_init__(self) -> None:
        if self.kind not in ("uniform", "window", "stripes", "point", "image"):
            raise InputError(f"light must be uniform, window, stripes, point or image, not {self.kind!r}")
        if self.kind == "window" and not self.size_mm > 0:
            raise InputError("window size must be > 0 mm")
        if self.kind == "stripes" and not (self.period_mm > 0 and 0 < self.duty <= 1):
            raise InputError("stripes need a period > 0 mm and a duty cycle in (0, 1]")
        if self.kind == "image" and self.image is None:
            raise InputError("an image light needs an irradiance image")
        if self.border_mm is not None and self.border_mm < 0:
            raise InputError("border must be >= 0 mm")

    @property
    def extends(self) -> bool:
        """True when the scene beyond the grid is as its edge (uniform light)."""
        return self.kind == "uniform"

    def border_px(self, mm_per_pixel: float, default_mm: float = DEFAULT_BORDER_MM) -> int:
        """Border width in pixels: the light's own ``border_mm``, else ``default_mm`` (the settings')."""
        if self.extends:
            return 0
        return int(math.ceil((default_mm if self.border_mm is None else self.border_mm) / mm_per_pixel))

    def irradiance(self, height: int, width: int, border: int, mm_per_pixel: float,
                   dtype: torch.dtype = torch.float32, device=None) -> torch.Tensor:
        """Irradiance on the padded grid, ``(H + 2b, W + 2b)`` (or ``(B, …)`` for a batched image)."""
        hp, wp = height + 2 * border, width + 2 * border
        if self.kind == "uniform":
            return torch.ones(hp, wp, dtype=dtype, device=device)
        if self.kind == "image":
            img = torch.as_tensor(self.image, dtype=dtype, device=device)
            if img.shape[-2:] != (height, width):
                raise ValueError(f"light image has shape {tuple(img.shape[-2:])}, the maps {(height, width)}")
            return torch.nn.functional.pad(img, (border, border, border, border))
        # pixel centres in mm, relative to the centre of the maps' grid
        y = (torch.arange(hp, dtype=torch.float64, device=device) - (hp - 1) / 2.0) * mm_per_pixel
        x = (torch.arange(wp, dtype=torch.float64, device=device) - (wp - 1) / 2.0) * mm_per_pixel
        if self.kind == "point":
            out = torch.zeros(hp, wp, dtype=dtype, device=device)
            out[hp // 2, wp // 2] = 1.0 / mm_per_pixel**2
            return out
        if self.kind == "window":
            half = self.size_mm / 2.0
            inside_y = _coverage(y, -half, half, mm_per_pixel)
            inside_x = _coverage(x, -half, half, mm_per_pixel)
            return (inside_y[:, None] * inside_x[None, :]).to(dtype)
        phase = torch.remainder(x / self.period_mm, 1.0)
        lit = (phase < self.duty).to(torch.float64)
        return lit[None, :].expand(hp, wp).to(dtype).contiguous()


def _coverage(centre_mm: torch.Tensor, lo: float, hi: float, pixel_mm: float) -> torch.Tensor:
    """Fraction of each pixel (1-D) inside [lo, hi]: edges fall between pixels without aliasing."""
    left = centre_mm - pixel_mm / 2.0
    right = centre_mm + pixel_mm / 2.0
    return ((torch.clamp(right, max=hi) - torch.clamp(left, min=lo)).clamp(min=0.0)) / pixel_mm


def parse_light(text: str) -> Light:
    """``uniform``, ``window[:SIZE_MM]``, ``stripes[:PERIOD_MM[:DUTY]]``, ``point``."""
    parts = text.strip().split(":")
    kind = parts[0]
    try:
        values = [float(p) for p in parts[1:]]
    except ValueError:
        raise InputError(f"--light {text!r}: numbers expected after the kind, e.g. window:7.5 or stripes:2:0.5") from None
    if kind == "window" and len(values) <= 1:
        return Light("window", size_mm=values[0] if values else 7.5)
    if kind == "stripes" and len(values) <= 2:
        return Light("stripes", period_mm=values[0] if values else 2.0, duty=values[1] if len(values) > 1 else 0.5)
    if kind in ("uniform", "point") and not values:
        return Light(kind)
    raise InputError(f"--light {text!r}: expected uniform, window[:mm], stripes[:period_mm[:duty]] or point")
