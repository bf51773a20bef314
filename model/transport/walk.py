"""The photon walk: Monte Carlo radiative transport through layers whose absorption varies across the skin.

One batch of photons is walked at once as tensors (torch, any device). A photon is a position
(x, y, z) in mm — x to the right, y down the grid, z into the skin from the surface at z = 0 — a
direction (u_x, u_y, u_z), a weight, the layer it is in, and whether it has scattered.

- **Free paths** by delta tracking (Woodcock): within a layer the walk samples distances with the
  layer's majorant σ̄ = σs + max σa; at a tentative collision the pixel's own σt = σa(x, y) + σs is
  looked up, and the collision is real with probability σt/σ̄ (else the photon goes on). No pixel
  boundary is ever intersected, and a laterally piecewise-constant medium is walked exactly.
- **Absorption** by implicit capture: at a real collision the weight is multiplied by the albedo
  σs/σt; Russian roulette (1 in 10 survives, its weight ×10) ends photons below ``roulette_weight``.
- **Scattering**: Henyey–Greenstein with anisotropy g (g = 0: isotropic).
- **Boundaries**: the surface and the bottom of a finite stack are smooth Fresnel boundaries; the
  photon is split there — the transmitted share (1 − R) leaves and is tallied, the reflected share R
  goes on. Between layers the photon is reflected with the Fresnel probability R or refracted by
  Snell's law (a unit index ratio: always through), and each crossing of an interface multiplies its
  weight by that interface's transmittance A(x, y) (DWRR08 §4.2, Eq. 8: the thin absorbing layer).
- **Tallies**: the weight leaving the surface, per pixel of the tally grid and in total, and the
  weight leaving the bottom in total; light that left without scattering is counted apart (the
  diffusion model and "diffuse" adding-doubling quantities exclude it). Each photon carries the label
  of its batch and every tally is kept per batch, so one walk serves many independent batches (their
  spread is the standard error) at the cost of one.

**A homogeneous twin** (``twin``, for a control variate): the same photons walked at once through
skin of one absorption everywhere (each layer's σa and the interface's transmittance given as
numbers). Scattering does not depend on the chromophores (σs per layer only), so a path can be
drawn independently of the absorption and every absorption weighted along it — the microscopic
Beer–Lambert law of perturbation Monte Carlo. Free paths are then sampled at σs + μ̄ per layer,
where μ̄ = 2·max |σa(x, y) − σa,twin| bounds the difference: both weights are attenuated exactly by
exp(−σa,twin t) over every flight, an event is a scattering with probability σs/(σs + μ̄), and
otherwise it multiplies the medium's weight alone by 1 − (σa(x, y) − σa,twin)/μ̄ (ratio tracking of
the difference, unbiased; the factor stays within 0.5–1.5). Roulette treats both weights alike.
The twin's surface tally is correlated with the medium's pixel by pixel, so the difference of the
two has a fraction of either's variance where the skin is near the twin.

Lateral position beyond the medium's grid takes the nearest edge pixel's properties (skin replicated
to infinity). The walk shares nothing with the diffusion profiles; it uses only the Fresnel equations.

Shapes: per-photon tensors ``(P,)``; medium maps ``(layers, H, W)``; tallies ``(H, W)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..optics.fresnel import fresnel_reflectance

__all__ = ["Medium", "Tally", "walk"]

_SURVIVE = 0.1  # Russian roulette: the chance to go on, the weight then ×1/this
_MAX_STEPS = 2_000_000  # a safety cap on the iterations of one batch; photons still alive then are counted as lost
#: Fewer photons alive than this on a CPU: the walk's tail runs on one thread. Its steps are too small to
#: share, and when the cores are busy a shared step waits for a descheduled thread, far longer than one
#: thread takes (docs/transport.md, "The transport reference", "Speed and memory").
_SERIAL_BELOW = 1 << 15
#: The dead (weight 0, which tally nothing) are dropped once they are 1/this of the photons: each drop
#: copies every photon's state, so the walk carries a few dead rather than copy at every step.
_COMPACT_WHEN_ALIVE = 16


@dataclass(frozen=True)
class Medium:
    """A stack of layers over a lateral grid of pixels.

    ``thickness_mm`` per layer (the last may be ``math.inf``: a half-space); ``n`` per layer; ``n_above``
    and ``n_below`` (the latter used under a finite stack); ``sigma_s_per_mm`` per layer (the scattering,
    not reduced, coefficient); ``sigma_a_per_mm`` ``(layers, H, W)``; ``interface_transmittance``
    ``(layers − 1, H, W)``; ``mm_per_pixel``. The grid is centred on x = y = 0."""

    thickness_mm: tuple[float, ...]
    n: tuple[float, ...]
    n_above: float
    n_below: float
    sigma_s_per_mm: tuple[float, ...]
    anisotropy: float
    sigma_a_per_mm: torch.Tensor
    interface_transmittance: torch.Tensor
    mm_per_pixel: float

    def __post_init__(self) -> None:
        layers = len(self.thickness_mm)
        if not (len(self.n) == len(self.sigma_s_per_mm) == layers == self.sigma_a_per_mm.shape[0]):
            raise ValueError("thickness_mm, n, sigma_s_per_mm and sigma_a_per_mm need one entry per layer")
        if self.interface_transmittance.shape[0] != layers - 1:
            raise ValueError(f"{layers} layers need {layers - 1} interface transmittance maps")
        if any(not t > 0 for t in self.thickness_mm) or any(math.isinf(t) for t in self.thickness_mm[:-1]):
            raise ValueError("layer thicknesses must be > 0, and only the last may be infinite")

    @property
    def shape(self) -> tuple[int, int]:
        return tuple(self.sigma_a_per_mm.shape[1:])  # type: ignore[return-value]


@dataclass
class Tally:
    """What each batch left, ``(K, …)`` for the K batch labels: ``surface`` ``(K, H, W)`` weight out of the
    surface per pixel of the medium's grid (scattered light only, in units of one photon's weight);
    ``reflected`` / ``transmitted`` ``(K,)``: out of the top / bottom (scattered only);
    ``unscattered_reflected``, ``unscattered_transmitted`` ``(K,)``; ``lost`` ``(K,)``: the weight of photons
    still alive at the step cap; ``steps``: the iterations run; ``surface_twin`` ``(K, H, W)``: the
    homogeneous twin's surface tally from the same photons (``walk``'s ``twin``), else None; ``bottom``
    ``(K, H, W)``: the scattered weight out of the bottom of a finite stack per pixel (``walk``'s
    ``tally_bottom``), else None."""

    surface: torch.Tensor
    reflected: torch.Tensor
    transmitted: torch.Tensor
    unscattered_reflected: torch.Tensor
    unscattered_transmitted: torch.Tensor
    lost: torch.Tensor
    steps: int
    surface_twin: torch.Tensor | None = None
    bottom: torch.Tensor | None = None


def walk(
    medium: Medium, x: torch.Tensor, y: torch.Tensor, cos_in: torch.Tensor, weight: torch.Tensor, generator: torch.Generator,
    *, label: torch.Tensor | None = None, labels: int = 1, roulette_weight: float = 1e-4, max_depth_mm: float = 50.0,
    across_y: bool = False, azimuth: torch.Tensor | None = None, twin: tuple[tuple[float, ...], tuple[float, ...]] | None = None,
    tally_bottom: bool = False,
) -> Tally:
    """Walk photons that have just entered the top layer at (``x``, ``y``) with direction cosine
    ``cos_in`` (> 0, into the skin; in the x–z plane, or at ``azimuth`` (radians) from the x axis) and
    ``weight``, each of batch ``label`` (0 … ``labels`` − 1; default: one batch); float64 throughout.

    ``across_y``: a medium of one row that does not vary along y, under light that does not either:
    every exit is tallied in its column whatever its y — the profile M(x) from photons launched on
    one line, each photon counting where a 2-D tally would keep one in hundreds.

    ``twin``: (σa per layer (per mm), transmittance per interface) of a homogeneous twin walked with the
    same photons (the module docstring); its tally is ``Tally.surface_twin``.

    ``tally_bottom``: also tally, per pixel, the scattered light leaving the bottom of a finite stack
    (``Tally.bottom``; a slab's transmittance profile)."""
    dev, f64 = x.device, torch.float64
    h, w = medium.shape
    m = medium.mm_per_pixel
    n_layers = len(medium.thickness_mm)
    z_top = torch.tensor([sum(medium.thickness_mm[:k]) for k in range(n_layers)], dtype=f64, device=dev)
    z_bot = torch.tensor([sum(medium.thickness_mm[: k + 1]) for k in range(n_layers)], dtype=f64, device=dev)
    sigma_s = torch.tensor(medium.sigma_s_per_mm, dtype=f64, device=dev)
    sigma_a = medium.sigma_a_per_mm.to(dev, f64)
    if twin is None:
        majorant = sigma_s + sigma_a.reshape(n_layers, -1).amax(1)
    else:
        twin_sigma_a = torch.tensor(twin[0], dtype=f64, device=dev)
        twin_transmit = torch.tensor(twin[1] if n_layers > 1 else (1.0,), dtype=f64, device=dev)
        if twin_sigma_a.numel() != n_layers or (n_layers > 1 and twin_transmit.numel() != n_layers - 1):
            raise ValueError("twin needs one σa per layer and one transmittance per interface")
        difference = sigma_a - twin_sigma_a[:, None, None]
        bound = 2.0 * difference.reshape(n_layers, -1).abs().amax(1)  # μ̄: the factor 1 − Δ/μ̄ stays in [0.5, 1.5]
        majorant = sigma_s + bound
    n = torch.tensor(medium.n, dtype=f64, device=dev)
    transmit = medium.interface_transmittance.to(dev, f64).reshape(n_layers - 1, h * w)
    finite_bottom = math.isfinite(medium.thickness_mm[-1])
    g = float(medium.anisotropy)

    p = x.numel()
    px, py = x.to(f64), y.to(f64)
    pz = torch.zeros(p, dtype=f64, device=dev)
    sin_in = torch.sqrt((1.0 - cos_in.to(f64) ** 2).clamp_min(0.0))
    if azimuth is None:
        ux, uy, uz = sin_in, torch.zeros(p, dtype=f64, device=dev), cos_in.to(f64)
    else:
        ux, uy, uz = sin_in * torch.cos(azimuth.to(f64)), sin_in * torch.sin(azimuth.to(f64)), cos_in.to(f64)
    wt = weight.to(f64).clone()
    wtw = wt.clone() if twin is not None else None  # the twin's weight
    layer = torch.zeros(p, dtype=torch.long, device=dev)
    scattered = torch.zeros(p, dtype=torch.bool, device=dev)
    batch = torch.zeros(p, dtype=torch.long, device=dev) if label is None else label.to(dev, torch.long)
    surface = torch.zeros(labels * h * w, dtype=f64, device=dev)
    surface_twin = torch.zeros_like(surface) if twin is not None else None
    if tally_bottom and not math.isfinite(medium.thickness_mm[-1]):
        raise ValueError("tally_bottom needs a finite stack (a half-space has no bottom)")
    below = torch.zeros_like(surface) if tally_bottom else None
    totals = torch.zeros(4 * labels, dtype=f64, device=dev)  # per label: reflected, transmitted, unscattered R, unscattered T

    def add(kind: int, where: torch.Tensor, amount: torch.Tensor) -> None:
        totals.index_add_(0, batch[where] * 4 + kind, amount[where])

    def pixel(xx, yy):
        """The flat index of the pixel under each photon (the nearest edge pixel beyond the grid) and
        whether the photon is over the grid."""
        fx, fy = xx / m + w / 2.0, (torch.full_like(yy, 0.5) if across_y else yy / m + h / 2.0)
        inside = (fx >= 0) & (fx < w) & (fy >= 0) & (fy < h)
        return fy.floor().clamp(0, h - 1).long() * w + fx.floor().clamp(0, w - 1).long(), inside

    steps = 0
    threads = torch.get_num_threads()
    try:
        while px.numel() and steps < _MAX_STEPS:
            steps += 1
            if dev.type == "cpu" and px.numel() < _SERIAL_BELOW and torch.get_num_threads() != 1:
                torch.set_num_threads(1)
            u = torch.rand(px.shape, dtype=f64, device=dev, generator=generator)
            s = -torch.log1p(-u) / majorant[layer]
            inf = torch.full_like(s, math.inf)
            to_bottom = torch.where(uz > 0, (z_bot[layer] - pz) / uz.clamp_min(1e-300), inf)
            to_top = torch.where(uz < 0, (z_top[layer] - pz) / uz.clamp_max(-1e-300), inf)
            boundary = torch.minimum(to_bottom, to_top)
            hit = boundary <= s
            t = torch.where(hit, boundary, s)
            px, py = px + ux * t, py + uy * t
            pz = torch.where(hit, torch.where(uz > 0, z_bot[layer], z_top[layer]), pz + uz * t)

            # tentative collisions: real with probability σt(x, y) / σ̄; a real one scatters, the weight × albedo
            collide = ~hit
            flat, inside = pixel(px, py)  # the pixel under each photon, for its σa and, at the surface, its tally
            sa = sigma_a.reshape(n_layers, -1)[layer, flat]
            if twin is None:
                st = sa + sigma_s[layer]
                real = collide & (torch.rand(px.shape, dtype=f64, device=dev, generator=generator) * majorant[layer] < st)
                wt = torch.where(real, wt * sigma_s[layer] / st.clamp_min(1e-300), wt)
            else:  # a path independent of the absorption: scatter at σs; the difference from the twin by ratio tracking
                attenuation = torch.exp(-twin_sigma_a[layer] * t)
                wt, wtw = wt * attenuation, wtw * attenuation
                real = collide & (torch.rand(px.shape, dtype=f64, device=dev, generator=generator) * majorant[layer] < sigma_s[layer])
                ratio = collide & ~real
                mu = bound[layer].clamp_min(1e-300)
                wt = torch.where(ratio, wt * (1.0 - (sa - twin_sigma_a[layer]) / mu), wt)
            if bool(real.any()):
                ux, uy, uz = _scatter(ux, uy, uz, real, g, generator)
                scattered = scattered | real

            # boundaries
            up, down = hit & (uz < 0), hit & (uz > 0)
            top = up & (layer == 0)
            bottom = down & (layer == n_layers - 1) if finite_bottom else torch.zeros_like(hit)
            inner = (up & (layer > 0)) | (down & (layer < n_layers - 1))
            if bool(top.any()):
                r = fresnel_reflectance(-uz, medium.n_above / n[layer]).to(f64)
                out = torch.where(top, wt * (1.0 - r), torch.zeros_like(wt))
                keep = top & scattered & inside
                surface.index_add_(0, batch[keep] * (h * w) + flat[keep], out[keep])
                add(0, top & scattered, out)
                add(2, top & ~scattered, out)
                wt = torch.where(top, wt * r, wt)
                if twin is not None:
                    surface_twin.index_add_(0, batch[keep] * (h * w) + flat[keep], (wtw * (1.0 - r))[keep])
                    wtw = torch.where(top, wtw * r, wtw)
                uz = torch.where(top, -uz, uz)
            if bool(bottom.any()):
                r = fresnel_reflectance(uz, medium.n_below / n[layer]).to(f64)
                out = torch.where(bottom, wt * (1.0 - r), torch.zeros_like(wt))
                add(1, bottom & scattered, out)
                add(3, bottom & ~scattered, out)
                if below is not None:
                    keep = bottom & scattered & inside
                    below.index_add_(0, batch[keep] * (h * w) + flat[keep], out[keep])
                wt = torch.where(bottom, wt * r, wt)
                if twin is not None:
                    wtw = torch.where(bottom, wtw * r, wtw)
                uz = torch.where(bottom, -uz, uz)
            if bool(inner.any()):
                other = torch.where(uz > 0, layer + 1, layer - 1).clamp(0, n_layers - 1)
                eta = n[other] / n[layer]
                cos_i = uz.abs()
                r = fresnel_reflectance(cos_i, eta).to(f64)
                reflect = inner & (torch.rand(px.shape, dtype=f64, device=dev, generator=generator) < r)
                cross = inner & ~reflect
                sin_t2 = (1.0 - cos_i**2) / eta**2
                cos_t = torch.sqrt((1.0 - sin_t2).clamp_min(0.0))
                ux = torch.where(cross, ux / eta, ux)
                uy = torch.where(cross, uy / eta, uy)
                uz = torch.where(reflect, -uz, torch.where(cross, torch.sign(uz) * cos_t, uz))
                which = torch.minimum(layer, other).clamp_max(max(n_layers - 2, 0))  # the interface crossed: between layer k and k + 1
                a = transmit[which, flat] if n_layers > 1 else torch.ones_like(wt)
                wt = torch.where(cross, wt * a, wt)
                if twin is not None:
                    wtw = torch.where(cross, wtw * twin_transmit[which], wtw)
                layer = torch.where(cross, other, layer)

            # roulette, the depth cut, and the survivors
            low = wt < roulette_weight if twin is None else torch.maximum(wt, wtw) < roulette_weight
            if bool(low.any()):
                survive = torch.rand(px.shape, dtype=f64, device=dev, generator=generator) < _SURVIVE
                wt = torch.where(low, torch.where(survive, wt / _SURVIVE, torch.zeros_like(wt)), wt)
                if twin is not None:
                    wtw = torch.where(low, torch.where(survive, wtw / _SURVIVE, torch.zeros_like(wtw)), wtw)
            deep = pz > max_depth_mm
            wt = torch.where(deep, torch.zeros_like(wt), wt)
            alive = wt > 0
            if twin is not None:
                wtw = torch.where(deep, torch.zeros_like(wtw), wtw)
                alive = alive | (wtw > 0)
            if int(alive.sum()) * _COMPACT_WHEN_ALIVE < px.numel() * (_COMPACT_WHEN_ALIVE - 1) or not bool(alive.any()):
                px, py, pz, ux, uy, uz, wt, layer, scattered, batch = (
                    v[alive] for v in (px, py, pz, ux, uy, uz, wt, layer, scattered, batch))
                if twin is not None:
                    wtw = wtw[alive]
    finally:
        torch.set_num_threads(threads)
    lost = torch.zeros(labels, dtype=f64, device=dev).index_add_(0, batch, wt)
    per = totals.reshape(labels, 4)
    return Tally(surface.reshape(labels, h, w), per[:, 0], per[:, 1], per[:, 2], per[:, 3], lost, steps,
                 None if twin is None else surface_twin.reshape(labels, h, w),
                 None if below is None else below.reshape(labels, h, w))


def _scatter(ux, uy, uz, where, g: float, generator):
    """New directions after a Henyey–Greenstein scattering where ``where`` (Prahl et al. 1989's rotation)."""
    dev, f64 = ux.device, ux.dtype
    xi = torch.rand(ux.shape, dtype=f64, device=dev, generator=generator)
    if g == 0.0:
        cos_t = 2.0 * xi - 1.0
    else:
        frac = (1.0 - g * g) / (1.0 - g + 2.0 * g * xi)
        cos_t = ((1.0 + g * g - frac * frac) / (2.0 * g)).clamp(-1.0, 1.0)
    sin_t = torch.sqrt((1.0 - cos_t**2).clamp_min(0.0))
    phi = 2.0 * math.pi * torch.rand(ux.shape, dtype=f64, device=dev, generator=generator)
    cos_p, sin_p = torch.cos(phi), torch.sin(phi)
    vertical = uz.abs() > 0.99999
    root = torch.sqrt((1.0 - uz**2).clamp_min(1e-300))
    nx = torch.where(vertical, sin_t * cos_p, sin_t * (ux * uz * cos_p - uy * sin_p) / root + ux * cos_t)
    ny = torch.where(vertical, sin_t * sin_p, sin_t * (uy * uz * cos_p + ux * sin_p) / root + uy * cos_t)
    nz = torch.where(vertical, torch.sign(uz) * cos_t, -sin_t * cos_p * root + uz * cos_t)
    norm = torch.sqrt(nx * nx + ny * ny + nz * nz)
    return (torch.where(where, nx / norm, ux), torch.where(where, ny / norm, uy), torch.where(where, nz / norm, uz))
