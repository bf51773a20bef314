"""The objective at one grid level: render the window, compare visible pixels at every used band.

``LevelProblem.evaluate(x, log_scale)`` renders the unknowns (``unknowns.py``) under the box
illumination of the tape window with its occluded border (DWRR08 §6.3; ``Light("window")``), at the
cube's wavelengths, seen at the camera's angle, under gel, lit along the normal, times the global
radiometric scale, and returns the residual at the pixels in the loss. With ``grad=True`` it also
returns the exact gradient of ½‖r‖² by one backward pass of the heterogeneous renderer.

Band-pass. Each band is a filter of its own ``band_fwhm_nm`` (Gaussian; the cube's header says how wide),
not a line: where the skin's spectrum
curves within it (hemoglobin's Q bands at 542 and 577 nm) the band's mean differs from the centre's
value enough to bias dermal blood when left out (docs/reconstruct.md, "Settings"). The
renderer draws the centre wavelength; each pixel's value is then multiplied by its homogeneous
model's band mean over its centre value, c = Σᵢ wᵢ R_h(λᵢ)/R_h(λ_c) (3-point Gauss–Hermite
quadrature of the Gaussian, exact for spectra polynomial to degree 5 within the band; the exact
closed-form totals, no tables): exact for homogeneous skin, and the correction's own spatial detail
is far below the render's.

``homogeneous_jacobian`` is each pixel's *homogeneous* model — the renderer's uniform-light limit,
R_d(p) times the exit factor (``model/optics/radiometry.py``), from the renderer's own tables — and its
Jacobian with respect to the unknowns, by reverse-mode autodiff (``least_squares.reverse_jacobian``),
batched over pixels: the cheap per-pixel curvature of the Gauss–Newton methods (``optimizers.py``).

``layout`` (``grids.MapLayout``) says which maps the fit takes per pixel and which on coarser nodes
(``map_cell_mm``); the render always takes all five maps per pixel.

Shapes: unknowns ``(N_PARAMS, H, W)`` (maps, image layout); per-pixel data ``(N, ·)`` over the N pixels
in the loss: residuals ``(N, L)``, gradients ``(N, N_PARAMS)``, Jacobians ``(N, L, N_PARAMS)``.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import torch
import torch.autograd.forward_ad as fwAD

from ...model import SkinParams
from ...model.render.illumination import Light
from ...model.patch.maps import SkinMaps
from ...model.optics.radiometry import exit_factor
from ...model.render.renderer import SkinRenderer
from .grids import MapLayout
from .least_squares import reverse_jacobian
from .unknowns import Level, extend, extension_index, params_of_rows, to_params

__all__ = ["BAND_WEIGHTS", "Evaluation", "HomogeneousProblem", "LevelProblem", "OptimResult", "RenderCounter", "band_nodes"]

#: The fit's quadrature of a band's Gaussian filter: weights of the nodes at its centre and at ∓√3 σ
#: (three-node Gauss–Hermite, exact for polynomials of degree < 6).
BAND_WEIGHTS = (2.0 / 3.0, 1.0 / 6.0, 1.0 / 6.0)


def band_nodes(wavelength_nm: torch.Tensor, fwhm_nm: torch.Tensor) -> torch.Tensor:
    """The quadrature's nodes ``(L, 3)`` in nm of bands centred at ``wavelength_nm`` ``(L,)`` with
    Gaussian filters of ``fwhm_nm`` ``(L,)``: the centre, centre − √3 σ, centre + √3 σ."""
    sigma = fwhm_nm / (2.0 * math.sqrt(2.0 * math.log(2.0)))
    offsets = torch.stack([torch.zeros_like(sigma), -math.sqrt(3.0) * sigma, math.sqrt(3.0) * sigma], dim=1)  # (L, 3)
    return wavelength_nm[:, None] + offsets


@dataclass
class RenderCounter:
    """Renders made and the process CPU seconds they took (robust to other load on the machine)."""

    forward: int = 0
    backward: int = 0
    cpu_s: float = 0.0
    wall_s: float = 0.0

    def as_dict(self) -> dict:
        return {"forward": self.forward, "backward": self.backward, "cpu_s": round(self.cpu_s, 3), "wall_s": round(self.wall_s, 3)}


@dataclass
class Evaluation:
    """The objective at ``x`` ``(N_PARAMS, H, W)`` and ``log_scale`` (0-d): ``image`` ``(L, H, W)`` unscaled
    render, ``residual`` ``(N, L)`` = scale·image − target at the loss pixels and used bands (0 at
    unused bands), ``loss`` = ½‖residual‖², ``grad`` ``(N, N_PARAMS)`` exact ∂loss/∂x where asked for."""

    x: torch.Tensor
    log_scale: torch.Tensor
    image: torch.Tensor
    residual: torch.Tensor
    loss: float
    grad: torch.Tensor | None = None
    cache: dict = field(default_factory=dict, repr=False)


@dataclass
class OptimResult:
    """What every optimiser returns (``optimizers.METHODS``): ``x`` ``(N_PARAMS, H, W)``; ``log_scale``
    0-d; ``evaluation`` at the end point; ``iterations``; ``converged`` (the test, not the cap, stopped
    it); ``history``: (CPU s, loss) after each accepted step; ``pixel_step`` ``(N,)``: size of the last
    proposed step per loss pixel (∞-norm in x), NaN where the method has none; ``curvature``
    ``(N, N_PARAMS, N_PARAMS)`` Gauss–Newton JᵀJ in x at the end (if any); ``shared_decrement``: with
    maps on nodes, the χ² decrease the last step predicted from the nodes (about Σ (move/σ)² over them,
    σ² from the residual; 0 without)."""

    x: torch.Tensor
    log_scale: torch.Tensor
    evaluation: Evaluation
    iterations: int
    converged: bool
    history: list[tuple[float, float]] = field(default_factory=list)
    pixel_step: torch.Tensor | None = None
    curvature: torch.Tensor | None = None
    shared_decrement: float = 0.0


class LevelProblem:
    """One level of the coarse-to-fine fit: data, light and renderer settings. ``band_weight`` ``(L,)``: each
    band's weight in the loss, 0 for a band left out (``fit.band_weights``; a bool mask weighs every used band 1)."""

    def __init__(
        self,
        renderer: SkinRenderer,
        level: Level,
        wavelength_nm: torch.Tensor,
        band_weight: torch.Tensor,
        *,
        view_angle_deg: float,
        border_mm: float,
        band_fwhm_nm: torch.Tensor | float = 0.0,
        map_cell_mm: dict[str, float] | None = None,
        counter: RenderCounter | None = None,
    ) -> None:
        self.renderer = renderer
        self.level = level
        self.wavelength_nm = wavelength_nm.to(torch.float64)
        self.view_angle_deg = float(view_angle_deg)
        h, w = level.shape
        size_mm = h * level.mm_per_pixel
        # the cube is the window: lit exactly over the grid, dark over the border
        self.light = (
            Light("window", size_mm=size_mm, border_mm=border_mm)
            if h == w
            else Light("image", image=torch.ones(h, w), border_mm=border_mm)
        )
        self.mask = level.mask
        self.pixels = level.mask.reshape(-1).nonzero()[:, 0]
        self.index = extension_index(level.mask)
        self.layout = MapLayout(level.shape, level.mm_per_pixel, map_cell_mm, level.target.dtype, level.target.device)
        #: robust weight of each loss pixel ``(N,)`` (None: all 1), set between passes by ``fit.fit_cube``
        self.pixel_weight: torch.Tensor | None = None
        #: grey interface absorbance P ``(H, W)`` the render adds (hairs; ``absorbers.py``), None: none
        self.absorbance: torch.Tensor | None = None
        self.band_weight = band_weight.to(level.target.dtype).to(level.target.device)
        self.target = level.target.reshape(level.target.shape[0], -1)[:, self.pixels].T.contiguous()  # (N, L)
        self.counter = counter or RenderCounter()
        self.exit = exit_factor(
            renderer.settings.optics.n_epidermis, renderer.settings.optics.n_above, math.cos(math.radians(view_angle_deg))
        )
        self.band_nodes_nm = None
        fwhm = torch.as_tensor(band_fwhm_nm, dtype=torch.float64).expand(self.wavelength_nm.shape)
        if bool((fwhm > 0).any()):  # a band of width 0 is a line: its three nodes coincide
            self.band_nodes_nm = band_nodes(self.wavelength_nm, fwhm).reshape(-1)
            self.band_weights = torch.tensor(BAND_WEIGHTS, dtype=torch.float64)

    @property
    def row_weight(self) -> torch.Tensor:
        """Weight of each loss pixel's residual at each band ``(N, L)`` (or ``(L,)`` when every pixel
        counts fully): the band's use times the square root of the pixel's robust weight."""
        if self.pixel_weight is None:
            return self.band_weight
        return self.band_weight[None, :] * self.pixel_weight.sqrt()[:, None]

    @property
    def n_pixels(self) -> int:
        return int(self.pixels.numel())

    def at_pixels(self, maps: torch.Tensor) -> torch.Tensor:
        """``(C, H, W)`` → ``(N, C)`` at the loss pixels."""
        return maps.reshape(maps.shape[0], -1)[:, self.pixels].T

    def render(self, x: torch.Tensor) -> torch.Tensor:
        """Unscaled band reflectance factor ``(L, H, W)`` of unknowns ``(N_PARAMS, H, W)`` (differentiable)."""
        p = to_params(extend(x, self.index))
        maps = SkinMaps(*(v[None] for v in p.unbind(0)), mm_per_pixel=self.level.mm_per_pixel)
        if self.absorbance is not None:  # grey: one band stands for every wavelength (held at the ends)
            maps = maps.replace(absorbance=self.absorbance.to(x.dtype)[None, None],
                                absorbance_wavelength_nm=self.wavelength_nm[:1])
        out = self.renderer.render(
            maps, self.light, self.wavelength_nm, under_gel=True, light_angle_deg=0.0, view_angle_deg=self.view_angle_deg
        )
        return out.image[0] * self.band_correction(p)

    def band_correction(self, p: torch.Tensor) -> torch.Tensor | float:
        """Band mean over centre value of each pixel's homogeneous model ``(L, H, W)`` (1 without a band model)."""
        if self.band_nodes_nm is None:
            return 1.0
        c, h, w = p.shape
        rows = _distinct(p.reshape(c, h * w))
        r = self.renderer.model.diffuse_reflectance(SkinParams(*rows.double().unbind(0)), self.band_nodes_nm)
        r = r.reshape(rows.shape[1], -1, 3)
        ratio = (r * self.band_weights.to(r)).sum(-1) / r[..., 0]
        return ratio.T.expand(-1, h * w).reshape(-1, h, w).to(p.dtype)

    def evaluate(self, x: torch.Tensor, log_scale: torch.Tensor, grad: bool = False) -> Evaluation:
        """Render, residual and loss at ``x``; with ``grad`` the exact gradient (one backward pass)."""
        c0, w0 = time.process_time(), time.perf_counter()
        x = x.detach()
        log_scale = log_scale.detach()
        if grad:
            xg = x.clone().requires_grad_(True)
            with torch.enable_grad():
                image = self.render(xg)
                residual = self._residual(image, log_scale)
                loss = 0.5 * (residual**2).sum()
                (g,) = torch.autograd.grad(loss, xg)
            gradient = self.at_pixels(g).contiguous()
            self.counter.backward += 1
        else:
            with torch.no_grad():
                image = self.render(x)
                residual = self._residual(image, log_scale)
            gradient = None
        self.counter.forward += 1
        self.counter.cpu_s += time.process_time() - c0
        self.counter.wall_s += time.perf_counter() - w0
        image, residual = image.detach(), residual.detach()
        return Evaluation(x, log_scale, image, residual, float(0.5 * (residual.double() ** 2).sum()), gradient)

    def _residual(self, image: torch.Tensor, log_scale: torch.Tensor) -> torch.Tensor:
        pred = self.at_pixels(image) * torch.exp(log_scale)
        return (pred - self.target) * self.row_weight

    def homogeneous_image(self, x: torch.Tensor) -> torch.Tensor:
        """Each pixel's homogeneous reflectance factor ``(L, H, W)`` of unknowns ``(N_PARAMS, H, W)``, band
        corrected as the render is: what the renderer gives for uniform skin under uniform light."""
        return self.homogeneous_of(to_params(extend(x, self.index)))

    def homogeneous_of(self, p: torch.Tensor) -> torch.Tensor:
        """``homogeneous_image`` of parameters ``p`` ``(N_PARAMS, H, W)`` (any grid: ``uniform.py`` asks it
        of its candidate skins as ``(N_PARAMS, M, 1)``) → ``(L, H, W)``."""
        c, h, w = p.shape
        rows = _distinct(p.reshape(c, h * w))
        r = self.renderer.model.diffuse_reflectance(SkinParams(*rows.unbind(0)), self.wavelength_nm, method="tables")
        return (r.T.expand(-1, h * w).reshape(-1, h, w) * self.exit).to(p.dtype) * self.band_correction(p)

    def homogeneous_jacobian(self, x_pixels: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Homogeneous reflectance factor ``(N, L)`` of each pixel's unknowns ``x_pixels`` ``(N, N_PARAMS)``
        and its Jacobian ``(N, L, N_PARAMS)`` with respect to x (reverse mode, one batched pass per band)."""
        model = self.renderer.model
        n = x_pixels.shape[0]
        rows = _distinct(x_pixels.detach().T).T
        value, jac = reverse_jacobian(
            lambda xv: model.diffuse_reflectance(params_of_rows(xv), self.wavelength_nm, method="tables"), rows
        )
        return (value * self.exit).to(x_pixels.dtype).expand(n, -1), (jac * self.exit).to(x_pixels.dtype).expand(n, -1, -1)


def _distinct(columns: torch.Tensor) -> torch.Tensor:
    """``columns`` ``(C, M)``, or its first column ``(C, 1)`` where every column is that one: uniform skin
    (every map one value, ``uniform.py``) is one homogeneous spectrum, evaluated once for all its pixels
    and broadcast (the callers' ``expand``). Never where derivatives flow (a graph or forward-mode
    tangents): equal values there are still each pixel's own unknowns."""
    if columns.requires_grad or fwAD.unpack_dual(columns).tangent is not None:
        return columns
    if columns.shape[1] > 1 and bool((columns == columns[:, :1]).all()):
        return columns[:, :1]
    return columns


class HomogeneousProblem(LevelProblem):
    """The same level with the per-pixel homogeneous forward model instead of the renderer: each
    pixel's R_d (the model's Gaussian tables, as the renderer's) times the exit factor, times the
    window's light factor ``light_factor`` ``(L, H, W)`` — a render of uniform skin over its
    homogeneous value, which carries the window's dark edges but none of the neighbours' light — and
    the band correction. No cross-talk between pixels and no render per evaluation: the model a
    smooth scene needs, checked against a render before it is kept (``fidelity.py``)."""

    def __init__(self, *args, light_factor: torch.Tensor, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.light_factor = light_factor

    def render(self, x: torch.Tensor) -> torch.Tensor:
        return self.homogeneous_image(x) * self.light_factor.to(x.dtype)
