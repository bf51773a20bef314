"""The transport reference for skin: parameter maps (or one parameter set) to reflectance by Monte Carlo.

``TransportRenderer(settings).render(maps, light, wavelengths)`` is the renderer's twin: the same maps,
the same optical properties from them (σa of each layer from the chromophores, DWRR08 Eq. 11–12; the
interface absorbance, Eq. 8 and §5.1; σs′ of Eq. 13, halved in the dermis; the refractive indices),
the same lights and the same radiometric convention (light in: F_t(θ_i) E; out: the reflectance factor
ρ(θ_o) = M F_t(θ_o) / (1 − F_dr,ext), ``radiometry.exit_factor``), but the light transport is the
photon walk of ``walk.py`` instead of diffusion profiles. Each pixel comes with its standard error,
the spread of independent batches of photons.

``TransportRenderer.totals(params, wavelengths)``: diffuse reflectance of homogeneous skin (a point
spectrum), with standard errors.

The medium beyond the maps is the maps' edge replicated to infinity; lights that extend beyond the
maps (uniform, stripes) are lit ``margin_mm`` beyond them, the window and a point only where they are.

Randomness: ``seed`` fixes every photon (per wavelength, item and batch a generator of its own, keyed by
the wavelength's value: a band renders the same alone or among others), on a given device; the CPU and
CUDA streams differ, each reproducible.
"""

from __future__ import annotations

import hashlib
import math
import time
from dataclasses import dataclass, field

import torch

from ..render.illumination import Light
from ..patch.maps import SkinMaps
from ..optics.params import SkinParams, layer_absorption
from ..optics.radiometry import entry_transmittance, exit_factor
from ...formats.errors import InputError
from ..settings import MAX_PHOTONS, MIN_PHOTONS, PHYSICS, ModelSettings
from ..optics.specular import torrance_sparrow_factor
from ..optics.spectra import chromophore_spectra
from .walk import Medium, walk

__all__ = ["BYTES_PER_PHOTON", "TransportRenderer", "TransportResult", "TransportTotals", "Y_INVARIANT_LIGHTS", "check_physics_options"]

#: Peak memory per photon of a batch in flight (its state and the step's temporaries), from the peak a
#: large run raised over what the process held before (docs/transport.md, "The transport reference",
#: "Speed and memory").
BYTES_PER_PHOTON = 1100

#: Lights that do not vary along y (and go on beyond the maps): on maps of one row, a scene invariant
#: along y, rendered with every photon tallied in its column.
Y_INVARIANT_LIGHTS = ("uniform", "stripes")


@dataclass
class TransportResult:
    """``exitance`` M / E and ``image`` (the reflectance factor at the view angle) ``(B, L, H, W)``, with
    their standard errors ``exitance_std_error`` and ``image_std_error``; ``photons`` per wavelength;
    ``seconds`` per wavelength; ``lost``: the share of the light still inside at the step cap (≈ 0)."""

    exitance: torch.Tensor
    image: torch.Tensor
    exitance_std_error: torch.Tensor
    image_std_error: torch.Tensor
    wavelength_nm: torch.Tensor
    photons: int
    seconds: list[float] = field(default_factory=list)
    lost: float = 0.0
    mm_per_pixel: float = 0.0


@dataclass
class TransportTotals:
    """Diffuse reflectance per unit incident power ``(L,)`` and its standard error (specular and
    unscattered light excluded, as in the diffusion model)."""

    reflectance: torch.Tensor
    std_error: torch.Tensor
    photons: int


class TransportRenderer:
    """Monte Carlo renders of ``SkinMaps`` (see the module docstring)."""

    def __init__(self, settings: ModelSettings | None = None) -> None:
        self.settings = settings or ModelSettings()

    def render(
        self, maps: SkinMaps, light: Light, wavelength_nm: torch.Tensor, *, photons: int | None = None, seed: int = 0,
        under_gel: bool = True, light_angle_deg: float = 0.0, view_angle_deg: float = 0.0, azimuth_deg: float = 180.0, progress=None,
    ) -> TransportResult:
        """Render every band of ``wavelength_nm`` ``(L,)`` with ``photons`` per band (default: the settings').
        Maps of one row under uniform or striped light are a scene invariant along y (the renderer
        replicates the row too): every photon is tallied in its column, as ``profile`` does. Without
        gel, the surface's own reflection (``rho_s``) is added as the renderer adds it (it is not
        transport: the same Torrance–Sparrow term, without noise)."""
        wl = torch.as_tensor(wavelength_nm, dtype=torch.float64).reshape(-1)
        ts = self.settings.transport
        photons = int(photons or ts.photons)
        b, h, w = maps.shape
        device = maps.device
        out = torch.zeros(b, wl.numel(), h, w, dtype=torch.float64, device=device)
        err = torch.zeros_like(out)
        seconds, lost = [], 0.0
        along_y = h == 1 and light.kind in Y_INVARIANT_LIGHTS  # a row replicated along y: the profile's tally
        irradiance = self._launch_irradiance(light, h, w, maps.mm_per_pixel, device, along_y)
        for j in range(wl.numel()):
            start = time.perf_counter()
            for i in range(b):
                medium = self._medium(maps, i, wl[j: j + 1])
                mean, se, _, _, lost_j = self._tally(medium, irradiance, photons, (seed, float(wl[j]), i), light_angle_deg,
                                                     across_y=along_y, twin=ts.twin and not along_y)
                out[i, j], err[i, j] = mean, se
                lost = max(lost, lost_j)
            seconds.append(time.perf_counter() - start)
            if progress is not None:
                progress(j + 1, wl.numel())
        o = self.settings.optics
        f = exit_factor(o.n_epidermis, o.n_above, math.cos(math.radians(view_angle_deg)))
        image = out * f
        if not under_gel and maps.rho_s is not None:
            spec = torrance_sparrow_factor(
                math.cos(math.radians(light_angle_deg)), math.cos(math.radians(view_angle_deg)), azimuth_deg,
                o.n_epidermis / o.n_above, self.settings.render.surface_roughness,
            )
            lit = light.irradiance(h, w, 0, maps.mm_per_pixel, torch.float64, device)
            image = image + (spec * maps.rho_s.to(torch.float64) * lit)[:, None]
        return TransportResult(out, image, err, err * f, wl, photons, seconds, lost, maps.mm_per_pixel)

    def profile(self, row: SkinMaps, light: Light, wavelength_nm: torch.Tensor, *, photons: int | None = None, seed: int = 0,
                view_angle_deg: float = 0.0) -> TransportResult:
        """A scene that does not vary along y (maps of one row ``(B, 1, W)``) under a light that does not
        either (uniform, stripes): the reflectance profile across it, ``(B, L, 1, W)``, every photon
        tallied in its column (``walk``'s ``across_y``). ``render`` does the same for such maps; this
        refuses any other."""
        if row.shape[1] != 1 or light.kind not in Y_INVARIANT_LIGHTS:
            raise ValueError("a profile needs maps of one row and a light that does not vary along y (uniform, stripes)")
        return self.render(row, light, wavelength_nm, photons=photons, seed=seed, view_angle_deg=view_angle_deg)

    def totals(self, params: SkinParams, wavelength_nm: torch.Tensor, *, photons: int | None = None, seed: int = 0,
               progress=None) -> TransportTotals:
        """Diffuse reflectance of homogeneous skin ``params`` (one set: 0-d tensors) at normal incidence:
        every photon's light out of the surface, wherever it leaves (the plane is homogeneous).
        ``progress(done, total)`` after each wavelength."""
        wl = torch.as_tensor(wavelength_nm, dtype=torch.float64).reshape(-1)
        maps = SkinMaps(*(torch.as_tensor(v, dtype=torch.float64).reshape(1, 1, 1) for v in params.values()), mm_per_pixel=1.0)
        photons = int(photons or self.settings.transport.photons)
        point = torch.ones(1, 1, dtype=torch.float64)
        values = []
        for j in range(wl.numel()):
            values.append(self._tally(self._medium(maps, 0, wl[j: j + 1]), point, photons, (seed, float(wl[j]), 0), 0.0)[2:4])
            if progress is not None:
                progress(j + 1, wl.numel())
        return TransportTotals(torch.tensor([v[0] for v in values]), torch.tensor([v[1] for v in values]), photons)

    # -- pieces ----------------------------------------------------------------------------------
    def _medium(self, maps: SkinMaps, index: int, wl: torch.Tensor) -> Medium:
        """The two layers and their interface at one wavelength, from item ``index`` of the maps."""
        o, g = self.settings.optics, self.settings.transport.anisotropy
        spectra = chromophore_spectra(wl, o)
        params = SkinParams(*(v[index].to(torch.float64) for v in maps.params().values()))
        ab = layer_absorption(params, spectra.to(maps.device, torch.float64), o.interface_melanin_fraction, o.epidermis_thickness_mm)
        absorbance = ab.interface_absorbance[..., 0]
        if maps.absorbance is not None:
            absorbance = absorbance + _interpolate_bands(maps.absorbance[index], maps.absorbance_wavelength_nm, float(wl[0]))
        scattering = (float(spectra.scattering_epidermis[0]) / (1.0 - g), float(spectra.scattering_dermis[0]) / (1.0 - g))
        return Medium(
            thickness_mm=(o.epidermis_thickness_mm, math.inf), n=(o.n_epidermis, o.n_dermis), n_above=o.n_above, n_below=1.0,
            sigma_s_per_mm=scattering, anisotropy=g,
            sigma_a_per_mm=torch.stack([ab.epidermis[..., 0], ab.dermis[..., 0]]), interface_transmittance=torch.exp(-absorbance)[None],
            mm_per_pixel=maps.mm_per_pixel,
        )

    def _launch_irradiance(self, light: Light, h: int, w: int, mm: float, device, along_y: bool = False) -> torch.Tensor:
        """The irradiance photons are launched from, on the maps' grid and, for lights that go on beyond
        the maps, a lit border around it (centred on the grid as the medium is); ``along_y``: its one
        row (the scene does not vary along y)."""
        border = math.ceil(self.settings.transport.margin_mm / mm) if light.kind in Y_INVARIANT_LIGHTS else 0
        lit = light.irradiance(h, w, border, mm, torch.float64, device)
        return lit[border: border + 1] if along_y else lit

    def _twin_kernel(self, medium: Medium, twin_optics, irradiance_shape: tuple[int, int], batches: int, per_batch: int,
                     stream: tuple[int, float, int], cos_t: float, entering: float) -> torch.Tensor:
        """The homogeneous twin's point response ``(batches, 2·(h + b) − 1, 2·(w + c) − 1)``: the weight
        each pixel offset receives per photon entering uniformly over one pixel, offset 0 at the centre
        (every offset a scene's pixel can be from a lit cell)."""
        ts = self.settings.transport
        h, w = medium.shape
        hl, wl = irradiance_shape
        kh, kw = 2 * (h + (hl - h) // 2) - 1, 2 * (w + (wl - w) // 2) - 1
        layers = len(medium.thickness_mm)
        dev = medium.sigma_a_per_mm.device
        sa = torch.tensor(twin_optics[0], dtype=torch.float64, device=dev)[:, None, None].expand(layers, kh, kw)
        tr = torch.tensor(twin_optics[1], dtype=torch.float64, device=dev)[:, None, None].expand(layers - 1, kh, kw)
        flat = Medium(medium.thickness_mm, medium.n, medium.n_above, medium.n_below, medium.sigma_s_per_mm, medium.anisotropy,
                      sa.contiguous(), tr.contiguous(), medium.mm_per_pixel)
        kernel = torch.zeros(batches, kh, kw, dtype=torch.float64, device=dev)
        m = medium.mm_per_pixel
        for group, g, label in _walk_groups(batches, per_batch, ts.batch_photons, (*stream, "twin"), dev):
            jitter = torch.rand(2, label.numel(), dtype=torch.float64, device=dev, generator=g) - 0.5
            tally = walk(flat, jitter[0] * m, jitter[1] * m, torch.full_like(jitter[0], cos_t), torch.full_like(jitter[0], entering), g,
                         label=label, labels=len(group), roulette_weight=ts.roulette_weight, max_depth_mm=ts.max_depth_mm)
            kernel[group.start:group.stop] = tally.surface / per_batch
        return kernel

    def _tally(self, medium: Medium, irradiance: torch.Tensor, photons: int, stream: tuple[int, float, int], light_angle_deg: float,
               across_y: bool = False, twin: bool = False):
        """``stream``: (seed, wavelength, item), the photons' key (``_stream``). Over the batches: the mean
        exitance per unit irradiance ``(H, W)`` and its standard error, the
        total diffuse reflectance per unit incident power and its standard error, the lost share.
        ``across_y``: ``irradiance`` is one row and the result is per unit length along y.

        ``twin``: the exitance as the homogeneous twin's (each layer's mean σa, the interface's mean
        transmittance) plus the scene's difference from it, both from the same photons (``walk``'s
        ``twin``); the twin's own image is exact in expectation — its point response (``_twin_kernel``,
        pooled over the plane) convolved with the irradiance — and each batch pairs with a batch of it,
        so the standard error covers both. The totals stay the scene's own."""
        ts, o = self.settings.transport, self.settings.optics
        batches = max(ts.batches_min, math.ceil(photons / ts.batch_photons))
        per_batch = math.ceil(photons / batches)
        m = medium.mm_per_pixel
        hl, wl = irradiance.shape
        power = float(irradiance.sum()) * m * (1.0 if across_y else m)  # across y: per unit length of the line
        weights = irradiance.reshape(-1)
        cos_i = math.cos(math.radians(light_angle_deg))
        entering = entry_transmittance(o.n_epidermis, o.n_above, cos_i)
        sin_t = math.sin(math.radians(light_angle_deg)) * o.n_above / o.n_epidermis
        cos_t = math.sqrt(1.0 - sin_t * sin_t)
        surface = torch.zeros(batches, *medium.shape, dtype=torch.float64, device=irradiance.device)
        reflected = torch.zeros(batches, dtype=torch.float64, device=irradiance.device)
        lost = torch.zeros_like(reflected)
        twin_optics = None
        if twin:
            layers = len(medium.thickness_mm)
            twin_optics = (tuple(medium.sigma_a_per_mm.reshape(layers, -1).mean(1).tolist()),
                           tuple(medium.interface_transmittance.reshape(layers - 1, -1).mean(1).tolist()))
        for group, g, label in _walk_groups(batches, per_batch, ts.batch_photons, stream, irradiance.device):
            first, count = group.start, label.numel()
            cells = torch.multinomial(weights, count, replacement=True, generator=g)
            jitter = torch.rand(2, count, dtype=torch.float64, device=irradiance.device, generator=g)
            x = ((cells % wl).to(torch.float64) + jitter[0] - wl / 2.0) * m
            y = torch.zeros_like(x) if across_y else ((cells // wl).to(torch.float64) + jitter[1] - hl / 2.0) * m
            tally = walk(medium, x, y, torch.full_like(x, cos_t), torch.full_like(x, entering), g, label=label, labels=len(group),
                         roulette_weight=ts.roulette_weight, max_depth_mm=ts.max_depth_mm, across_y=across_y, twin=twin_optics)
            measured = tally.surface if twin_optics is None else tally.surface - tally.surface_twin
            surface[first:first + len(group)] = measured * (power / per_batch) / (m * (1.0 if across_y else m))
            reflected[first:first + len(group)] = tally.reflected / per_batch
            lost[first:first + len(group)] = tally.lost / (per_batch * entering)
        if twin_optics is not None:
            kernel = self._twin_kernel(medium, twin_optics, irradiance.shape, batches, max(1, math.ceil(per_batch * ts.twin_kernel_share)),
                                       stream, cos_t, entering)
            surface = surface + _convolve_kernel(irradiance, kernel, medium.shape)
        mean, se = surface.mean(0), surface.std(0, unbiased=True) / math.sqrt(batches)
        return mean, se, float(reflected.mean()), float(reflected.std(unbiased=True) / math.sqrt(batches)), float(lost.max())


def _convolve_kernel(irradiance: torch.Tensor, kernel: torch.Tensor, shape: tuple[int, int]) -> torch.Tensor:
    """The exitance ``(K, h, w)`` on the medium's grid (centred in the irradiance's ``(hl, wl)``) of a
    homogeneous medium whose point response is ``kernel`` ``(K, 2·(h + b) − 1, 2·(w + c) − 1)`` (offset 0 at
    its centre; b, c the irradiance's border): Σ_cells E(cell) K(pixel − cell). By FFT: the kernel is
    twice the lit field's side, so a direct convolution's work and memory grow with the fourth power of
    the side (far beyond memory already for a 128² cube under the window: docs/transport.md,
    "From model/transport/reference.py")."""
    h, w = shape
    hl, wl = irradiance.shape
    kh, kw = kernel.shape[-2:]
    fh, fw = hl + kh - 1, wl + kw - 1  # the full linear convolution: no wrap-around
    full = torch.fft.irfft2(torch.fft.rfft2(irradiance, s=(fh, fw)) * torch.fft.rfft2(kernel, s=(fh, fw)), s=(fh, fw))
    top, left = (hl - h) // 2 + (kh - 1) // 2, (wl - w) // 2 + (kw - 1) // 2  # pixel (0, 0) at offset 0
    return full[:, top: top + h, left: left + w]


def check_physics_options(physics: str | None, photons: int | None) -> None:
    """The one rule for a command's ``--physics`` and ``--photons`` (render, spectrum, capture, demo)."""
    if physics is not None and physics not in PHYSICS:
        raise InputError(f"--physics {physics!r}: expected {' or '.join(PHYSICS)}")
    if photons is not None and physics != "transport":
        raise InputError("--photons goes with --physics transport")
    if photons is not None and not MIN_PHOTONS <= photons <= MAX_PHOTONS:
        raise InputError(f"--photons {photons}: expected {MIN_PHOTONS:,}–{MAX_PHOTONS:,} per wavelength")


def _walk_groups(batches: int, per_batch: int, batch_photons: int, stream: tuple, device):
    """The batches walked together (as many as ``batch_photons`` holds): per group its range of batch
    labels, its generator (keyed by ``stream`` and the group's first batch, ``_stream``) and each
    photon's label within the group."""
    per_walk = max(1, batch_photons // per_batch)
    for first in range(0, batches, per_walk):
        group = range(first, min(first + per_walk, batches))
        g = torch.Generator(device=device).manual_seed(_stream(*stream[:3], first, *stream[3:]))
        yield group, g, torch.arange(len(group), device=device).repeat_interleave(per_batch)


def _stream(seed: int, wavelength_nm: float, item: int, batch: int, purpose: str = "") -> int:
    """One generator seed per (seed, wavelength, item of the maps, batch[, purpose]): the batches are
    independent, and a band's photons are the same whatever other bands are rendered with it."""
    key = f"transport {int(seed)} {float(wavelength_nm):.6f} {int(item)} {int(batch)}{' ' + purpose if purpose else ''}".encode()
    return int.from_bytes(hashlib.sha256(key).digest()[:8], "little") >> 1


def _interpolate_bands(values: torch.Tensor, source_nm: torch.Tensor, target_nm: float) -> torch.Tensor:
    """Linear interpolation of ``(L_src, H, W)`` along its bands at ``target_nm`` (ends held)."""
    src = source_nm.to(torch.float64).cpu()
    j = int(torch.searchsorted(src, torch.tensor(target_nm, dtype=torch.float64)))
    if j <= 0:
        return values[0].to(torch.float64)
    if j >= src.numel():
        return values[-1].to(torch.float64)
    t = (target_nm - float(src[j - 1])) / float(src[j] - src[j - 1])
    return (values[j - 1] * (1 - t) + values[j] * t).to(torch.float64)
