"""Stacks of Gaussian blurs of an image: the cost centre of the heterogeneous renderer.

A gather operator (DWRR08 Eq. 9) needs an image blurred by every Gaussian of the basis. Images are
pixel averages (irradiance falling on a pixel, exitance a camera pixel collects), so blurring by
G(v) on the grid means the kernel G(t) ∗ Λ sampled at whole pixels, with t = v / pixel² and Λ the unit
triangle (one pixel box convolved with another): its variance is t + 1/6 per axis and it tends to the
identity as t → 0. Gaussians narrower than ``identity_below_px`` (default half a pixel) merge into
the identity. The chains below apply that exact kernel directly for the narrow Gaussians (up to
2 px std) and then the *discrete Gaussian* of each variance increment (Lindeberg 1990: per axis e^{-t} I_n(t), variance exactly t,
semigroup T(t₁) ∗ T(t₂) = T(t₁ + t₂)), so G(2v) = G(v) ∗ G(v) holds on the grid as in the plane and
every blurred image carries exactly its variance.

Strategies, one interface (``blur_stack(images) -> iterator of blurred images``, smallest first):

- ``fft``: one FFT of the (padded) image, then per Gaussian a product with the exact pixel-averaged
  transfer function (periodised exp(-tω²/2) sinc²(ω/2π) per axis) and an inverse FFT: the reference,
  K inverse FFTs;
- ``chain``: the incremental chain in space, each blur from the previous one by a separable kernel of
  the variance increment: exact variances, cost grows with the widest kernel;
- ``pyramid``: the chain on an image pyramid: once a blur is wide enough (``pyramid_min_px`` pixels
  of the current level), the image is halved (2×2 mean, whose variance is accounted for) and the
  chain goes on at the coarser level; each blurred image returns to full resolution by cubic
  (Keys) interpolation. Approximate, and by far the fastest for wide Gaussians.

Images are ``(N, H, W)``; the boundary is ``zero`` (dark beyond the grid) or ``replicate`` (the scene
continues as its edge).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Iterator

import numpy as np
import torch
import torch.nn.functional as F
from scipy.special import ive

__all__ = ["BLUR_STRATEGIES", "BlurPlan", "blur_stack", "discrete_gaussian_kernel"]

BLUR_STRATEGIES = ("fft", "chain", "pyramid")
#: Gaussians up to this variance (px²) are blurred from the image directly with the exact pixel
#: kernel; the discrete Gaussian differs from it by a few percent in the centre below ~2 px std.
DIRECT_BELOW_PX2 = 4.0


#: Kernel taps below this fraction of the centre tap are dropped: far below what float32 images and
#: the 4σ truncation already leave out.
TAP_FLOOR = 1e-6

#: A pass over images larger than this (bytes) runs in slabs of ``PASS_SLAB_BYTES``, cut across the
#: blurred axis: each tap pair reads and writes the slab, which then stays in the processor's cache
#: instead of streaming from memory once per tap (docs/speed.md, "Cut 3").
PASS_SLAB_ABOVE_BYTES = 8 * 2**20
PASS_SLAB_BYTES = 2**20


def _trim(k: np.ndarray) -> np.ndarray:
    """Drop the symmetric outer taps that fall below ``TAP_FLOOR`` of the peak, renormalise."""
    r = (k.size - 1) // 2
    keep = int(np.nonzero(k[r:] >= TAP_FLOOR * k[r])[0].max())
    k = k[r - keep:r + keep + 1] if keep > 0 else k[r - 1:r + 2]
    return k / k.sum()


@lru_cache(maxsize=256)
def _kernel_np(t: float) -> np.ndarray:
    radius = max(1, int(math.ceil(4.0 * math.sqrt(t) + 2.0)))
    n = np.arange(-radius, radius + 1)
    return _trim(ive(np.abs(n), t))


@lru_cache(maxsize=256)
def _pixel_kernel_np(t: float) -> np.ndarray:
    """Samples of G(t) ∗ Λ, Λ the unit triangle (pixel box ∗ pixel box): the exact kernel between
    pixel-averaged images for a Gaussian of variance t px² (per axis; variance t + 1/6)."""
    radius = max(1, int(math.ceil(4.0 * math.sqrt(t + 1.0 / 6.0) + 2.0)))
    n = np.arange(-radius, radius + 1, dtype=np.float64)
    x = np.linspace(-1.0, 1.0, 2001)
    tri = 1.0 - np.abs(x)
    g = np.exp(-((n[:, None] - x[None, :]) ** 2) / (2.0 * t)) / math.sqrt(2.0 * math.pi * t)
    return _trim(np.trapezoid(g * tri[None, :], x, axis=1))


def discrete_gaussian_kernel(variance_px2: float, dtype=torch.float32, device=None) -> torch.Tensor:
    """Lindeberg's discrete Gaussian e^{-t} I_n(t), truncated at 4σ + 2 and renormalised, ``(2r+1,)``."""
    return torch.as_tensor(_kernel_np(round(float(variance_px2), 12)), dtype=dtype, device=device)


@dataclass(frozen=True)
class BlurPlan:
    """Which Gaussians of a basis are blurred (and which merge into the identity), on a given grid."""

    variances_px2: tuple[float, ...]
    identity: tuple[bool, ...]
    strategy: str = "pyramid"
    boundary: str = "zero"
    pyramid_min_px: float = 2.5

    @classmethod
    def build(cls, variances_mm2, mm_per_pixel: float, strategy: str = "pyramid", boundary: str = "zero",
              identity_below_px: float = 0.5, pyramid_min_px: float = 2.5) -> "BlurPlan":
        if strategy not in BLUR_STRATEGIES:
            raise ValueError(f"blur strategy must be one of {BLUR_STRATEGIES}, got {strategy!r}")
        if boundary not in ("zero", "replicate"):
            raise ValueError(f"boundary must be 'zero' or 'replicate', got {boundary!r}")
        v = [float(x) / mm_per_pixel**2 for x in torch.as_tensor(variances_mm2).reshape(-1).tolist()]
        ident = tuple(math.sqrt(x) < identity_below_px for x in v)
        return cls(tuple(v), ident, strategy, boundary, pyramid_min_px)

    @property
    def blurred(self) -> list[float]:
        """Variances (px²) of the Gaussians that are actually blurred, increasing."""
        return [v for v, i in zip(self.variances_px2, self.identity) if not i]


def blur_stack(images: torch.Tensor, plan: BlurPlan) -> Iterator[torch.Tensor]:
    """Yield ``images`` ``(N, H, W)`` blurred by each non-identity Gaussian of ``plan``, in order."""
    if images.ndim != 3:
        raise ValueError(f"images must be (N, H, W), got {tuple(images.shape)}")
    targets = plan.blurred
    if not targets:
        return iter(())
    if plan.strategy == "fft":
        return _fft_stack(images, targets, plan.boundary)
    if plan.strategy == "chain":
        return _chain_stack(images, targets, plan.boundary)
    return _pyramid_stack(images, targets, plan.boundary, plan.pyramid_min_px)


def _pad_mode(boundary: str) -> str:
    return "replicate" if boundary == "replicate" else "constant"


def _separable(img: torch.Tensor, variance_px2: float, boundary: str, pixel: bool = False) -> torch.Tensor:
    """Blur ``(N, H, W)`` by the discrete Gaussian of the given variance, separably, same size.

    Symmetric taps are applied as shifted sums (``k_j (x[i-j] + x[i+j])``): on CPUs this is much
    faster than a one-channel ``conv2d`` (docs/renderer.md, "From model/render/blur.py"), and it is plain
    elementwise work on GPUs.
    """
    if variance_px2 <= 0:
        return img
    key = round(float(variance_px2), 12)
    taps = _pixel_kernel_np(key) if pixel else _kernel_np(key)
    r = (taps.size - 1) // 2
    x = F.pad(img[:, None], (r, r, 0, 0), mode=_pad_mode(boundary))[:, 0]
    x = _symmetric_pass(x, taps, r, dim=-1)
    x = F.pad(x[:, None], (0, 0, r, r), mode=_pad_mode(boundary))[:, 0]
    return _symmetric_pass(x, taps, r, dim=-2)


def _symmetric_pass(x: torch.Tensor, taps: np.ndarray, r: int, dim: int) -> torch.Tensor:
    """Valid 1-D correlation along ``dim`` with a symmetric kernel of radius ``r`` (output shrinks by 2r).

    The sums run in place on one scratch buffer: fewer, reused allocations are both faster and kinder
    to the heap than a temporary per tap. Under autograd the pass is one node whose adjoint is the
    same pass over the gradient padded by 2r (a symmetric kernel is its own flip): autograd through
    the shifted sums would allocate a full-size zero image per tap.
    """
    if torch.is_grad_enabled() and x.requires_grad:
        return _SymmetricPass.apply(x, taps, r, dim)
    return _symmetric_sums(x, taps, r, dim)


def _symmetric_sums(x: torch.Tensor, taps: np.ndarray, r: int, dim: int) -> torch.Tensor:
    """The pass along ``dim`` (-1 or -2 of ``(N, H, W)``), in cache-sized slabs when ``x`` is large."""
    dim = dim % x.ndim
    if x.ndim != 3 or dim == 0 or x.numel() * x.element_size() <= PASS_SLAB_ABOVE_BYTES:
        return _sums(x, taps, r, dim)
    across = 3 - dim  # the other image axis: rows for a pass along columns' neighbours, and back
    shape = list(x.shape)
    shape[dim] -= 2 * r
    out = x.new_empty(shape)
    line = x.shape[dim] * x.element_size()
    width = max(16, PASS_SLAB_BYTES // line)
    for i in range(x.shape[0]):
        for start in range(0, x.shape[across], width):
            take = min(width, x.shape[across] - start)
            out[i].narrow(across - 1, start, take).copy_(_sums(x[i].narrow(across - 1, start, take), taps, r, dim - 1))
    return out


def _sums(x: torch.Tensor, taps: np.ndarray, r: int, dim: int) -> torch.Tensor:
    n = x.shape[dim] - 2 * r
    out = torch.mul(x.narrow(dim, r, n), float(taps[r]))
    scratch = torch.empty_like(out)
    for j in range(r):
        torch.add(x.narrow(dim, j, n), x.narrow(dim, 2 * r - j, n), out=scratch)
        out.add_(scratch, alpha=float(taps[j]))
    return out


class _SymmetricPass(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, taps, r, dim):
        ctx.taps, ctx.r, ctx.dim = taps, r, dim % x.ndim
        return _symmetric_sums(x, taps, r, dim)

    @staticmethod
    def backward(ctx, grad):
        d, r = ctx.dim, ctx.r
        pad = [0, 0] * (grad.ndim - 1 - d) + [2 * r, 2 * r]
        return _symmetric_sums(F.pad(grad, pad), ctx.taps, r, d), None, None, None


def _margin(variance_px2: float) -> int:
    """Pixels beyond the grid that light blurred by this variance reaches (4σ, rounded up, + 2)."""
    return int(math.ceil(4.0 * math.sqrt(max(variance_px2, 0.0)))) + 2


def _grow(img: torch.Tensor, by: int, boundary: str) -> torch.Tensor:
    if by <= 0:
        return img
    return F.pad(img[:, None], (by, by, by, by), mode=_pad_mode(boundary))[:, 0]


def _chain_stack(images: torch.Tensor, targets: list[float], boundary: str) -> Iterator[torch.Tensor]:
    """Exact chain: the grid grows as the blur widens, so that light leaving the grid (zero boundary)
    or the scene beyond it (replicate) is carried into every later blur."""
    h, w = images.shape[-2:]
    current, have, margin = images, 0.0, 0
    for t in targets:
        need = _margin(t)
        current = _grow(current, need - margin, boundary)
        margin = max(margin, need)
        if t <= DIRECT_BELOW_PX2:
            current = _separable(_grow(images, margin, boundary), t, boundary, pixel=True)
        else:
            current = _separable(current, t - have, boundary)
        have = t
        yield current[:, margin:margin + h, margin:margin + w]


def _fft_stack(images: torch.Tensor, targets: list[float], boundary: str) -> Iterator[torch.Tensor]:
    n, h, w = images.shape
    pad = int(math.ceil(4.0 * math.sqrt(targets[-1]))) + 2
    x = F.pad(images[:, None], (pad, pad, pad, pad), mode=_pad_mode(boundary))[:, 0]
    hp, wp = x.shape[-2:]
    spectrum = torch.fft.rfft2(x.to(torch.float64) if x.dtype == torch.float64 else x)
    wy = 2.0 * math.pi * torch.fft.fftfreq(hp, device=x.device, dtype=torch.float64)
    wx = 2.0 * math.pi * torch.fft.rfftfreq(wp, device=x.device, dtype=torch.float64)
    for t in targets:
        transfer = (_pixel_transfer(wy, t)[:, None] * _pixel_transfer(wx, t)[None, :]).to(spectrum.real.dtype)
        out = torch.fft.irfft2(spectrum * transfer, s=(hp, wp))
        yield out[:, pad:pad + h, pad:pad + w].to(images.dtype)


def _pixel_transfer(omega: torch.Tensor, t: float) -> torch.Tensor:
    """DFT of the samples of G(t) ∗ Λ: the continuous transform exp(-tω²/2) sinc²(ω/2π), periodised."""
    total = torch.zeros_like(omega)
    for m in range(-3, 4):
        w = omega + 2.0 * math.pi * m
        total = total + torch.exp(-0.5 * t * w * w) * torch.sinc(w / (2.0 * math.pi)) ** 2
    return total


def _pyramid_stack(images: torch.Tensor, targets: list[float], boundary: str, min_px: float) -> Iterator[torch.Tensor]:
    """The chain on a pyramid. ``origin`` is where the core (the input grid) starts in the current
    grid, in full-resolution pixels; it is kept a multiple of the level's pixel size, and the margin
    around the core grows with the blur as in the exact chain (in the current level's pixels)."""
    h, w = images.shape[-2:]
    current = images
    level, origin = 0, 0
    have = 0.0  # variance applied so far, full-resolution px², including what the 2×2 means added
    for t in targets:
        while math.sqrt((t - have) / 4.0**level) >= 2.0 * min_px and math.sqrt(t / 4.0**level) >= 2.0 * min_px:
            step = 2**level
            if (origin // step) % 2:  # align the core to the coarser grid
                current = _grow(current, 1, boundary)
                origin += step
            hh, ww = current.shape[-2:]
            if hh % 2 or ww % 2:
                current = F.pad(current[:, None], (0, ww % 2, 0, hh % 2), mode=_pad_mode(boundary))[:, 0]
            current = F.avg_pool2d(current[:, None], 2)[:, 0]
            have += 0.25 * 4.0**level  # a 2×2 mean adds 1/4 of a level-j pixel² per axis
            level += 1
        scale = 4.0**level
        step = 2**level
        need = _margin(t / scale)
        margin = origin // step
        if need > margin:
            current = _grow(current, need - margin, boundary)
            origin += (need - margin) * step
        if level == 0 and t <= DIRECT_BELOW_PX2:
            current = _separable(_grow(images, origin, boundary), t, boundary, pixel=True)
        else:
            current = _separable(current, max(t - have, 0.0) / scale, boundary)
        have = max(t, have)
        yield _core(current, level, origin, h, w)


def _core(img: torch.Tensor, level: int, origin: int, h: int, w: int) -> torch.Tensor:
    """The input grid's region of a level-j image, at full resolution (cubic, centres aligned)."""
    if level == 0:
        return img[:, origin:origin + h, origin:origin + w]
    step = 2**level
    first = origin // step - 2  # two coarse pixels of context for the cubic kernel
    patch = img[:, first:first + -(-h // step) + 4, first:first + -(-w // step) + 4]
    up = _upsample_axis(_upsample_axis(patch, step, dim=-1), step, dim=-2)
    return up[:, :h, :w]


@lru_cache(maxsize=32)
def _keys_phases(factor: int) -> tuple[tuple[float, ...], ...]:
    """Per output phase p, the weights of coarse offsets -2..2 for the sample at (p + ½)/f - ½.

    Keys cubic convolution with a = -1/2, which reproduces quadratics, so interpolation adds no
    variance (PyTorch's bicubic uses a = -3/4 and shrinks every upsampled blur by ~0.07 coarse px²).
    """
    a = -0.5

    def keys(u: float) -> float:
        u = abs(u)
        if u <= 1:
            return (a + 2) * u**3 - (a + 3) * u**2 + 1
        if u < 2:
            return a * (u**3 - 5 * u**2 + 8 * u - 4)
        return 0.0

    return tuple(tuple(keys((p + 0.5) / factor - 0.5 - m) for m in range(-2, 3)) for p in range(factor))


def _upsample_axis(x: torch.Tensor, factor: int, dim: int) -> torch.Tensor:
    """Cubic upsampling along ``dim`` of samples with two samples of context at each end.

    Fine sample X of the output lies at coarse coordinate 2 + (X + ½)/factor - ½ of the input; the
    output has (n - 4)·factor samples. Each phase is a few shifted multiply-adds, written into the
    interleaved output; under autograd the adjoint (the transposed interpolation) is written by hand.
    """
    if torch.is_grad_enabled() and x.requires_grad:
        return _Upsample.apply(x, factor, dim)
    return _upsample_sums(x, factor, dim)


def _phase_taps(factor: int) -> list[list[tuple[int, float]]]:
    return [[(m, w) for m, w in zip(range(-2, 3), weights) if w != 0.0] for weights in _keys_phases(factor)]


def _upsample_sums(x: torch.Tensor, factor: int, dim: int) -> torch.Tensor:
    dim = dim % x.ndim
    n = x.shape[dim] - 4
    shape = list(x.shape)
    shape[dim:dim + 1] = [n, factor]
    out = x.new_empty(shape)
    for p, taps in enumerate(_phase_taps(factor)):
        dst = out.select(dim + 1, p)
        torch.mul(x.narrow(dim, 2 + taps[0][0], n), taps[0][1], out=dst)
        for m, wgt in taps[1:]:
            dst.add_(x.narrow(dim, 2 + m, n), alpha=wgt)
    return out.flatten(dim, dim + 1)


class _Upsample(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, factor, dim):
        ctx.factor, ctx.dim, ctx.shape = factor, dim % x.ndim, x.shape
        return _upsample_sums(x, factor, dim)

    @staticmethod
    def backward(ctx, grad):
        d, f = ctx.dim, ctx.factor
        n = ctx.shape[d] - 4
        g = grad.unflatten(d, (n, f))
        out = grad.new_zeros(ctx.shape)
        for p, taps in enumerate(_phase_taps(f)):
            gp = g.select(d + 1, p)
            for m, wgt in taps:
                out.narrow(d, 2 + m, n).add_(gp, alpha=wgt)
        return out, None, None
