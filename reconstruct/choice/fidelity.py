"""How much forward model a cube needs: each pixel's homogeneous model, or the heterogeneous renderer
(``FitSettings.forward``; ``reconstruct --model auto``: "model no more than a scene needs").

The renderer's cost is the light each pixel receives from its neighbours (DWRR08 §4, Eq. 7): where
the skin changes slowly against the light's spread, that light is what the pixel's own homogeneous
model already predicts, and the fit can do without the renderer. ``forward: auto`` fits the cube
first with ``HomogeneousProblem`` (each pixel's homogeneous R_d times the window's light factor — a
render of uniform skin over its homogeneous value, so the window's dark edges are kept — no render per
evaluation), then asks the renderer at the maps it found: where the two differ, over the loss pixels
and used bands, by at most ``CROSSTALK_LIMIT`` of the cube's own noise (RMS of the difference over each
band's σ, ``grid_choice.band_noise``), the cross-talk the homogeneous fit left out adds at most a
quarter to the noise's variance, and its maps are kept. Otherwise the heterogeneous fit runs as
``forward: heterogeneous`` would, from its own start, so ``auto`` is never worse than the full model by
more than the check's cost. The check runs on the coarsest level first (one small render: a freckle
or a hair fails it there, before the finer levels are fitted), then on the finest.

What was checked, the values and why the winner won go into ``fit.json`` (``ForwardChoice.as_dict``).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import torch

from ...model import N_PARAMS, PARAMETER_NAMES, SkinParams
from ..levels.grids import MapLayout
from ..levels.problem import Evaluation, HomogeneousProblem, LevelProblem
from ..levels.unknowns import to_params

__all__ = ["CONSTANT_R", "CROSSTALK_LIMIT", "FORECAST_MARGIN", "CrossTalkCheck", "ForwardChoice", "crosstalk_check",
           "crosstalk_forecast", "spatial_structure",
           "uniform_light_factor", "window_light_factor"]

#: The homogeneous fit is kept where the renderer at its maps differs from it by at most this RMS, in
#: units of each band's noise σ: the left-out cross-talk then adds at most 0.5² = a quarter to the
#: noise's variance.
CROSSTALK_LIMIT = 0.5
#: The homogeneous detour is not tried where the cube's forecast cross-talk (``crosstalk_forecast``) is
#: this many times the check's limit: the check would fail, after the detour's fits had been paid for.
FORECAST_MARGIN = 2.0
#: A map is fitted as one value for the patch where the homogeneous fit's values of it show less
#: structure than noise: for a map smooth on the scale of neighbours, the correlation r of neighbouring
#: values is the structure's share of their variance, so r < 1/2 says the variation a per-pixel map
#: would follow is smaller than the noise it would take on — one value then errs less (bias² below
#: variance). Tested on r's upper bound, r + 2/√(pairs) (r's spread for independent noise is 1/√(pairs):
#: each product of distinct neighbours is uncorrelated with every other), on the coarsest level, whose
#: noise is the lowest of all levels (the finest's per-pixel maps would carry 4ᵏ times its variance).
CONSTANT_R = 0.5
#: Fewer neighbour pairs than this tell nothing: the map keeps its grid.
MIN_PAIRS = 16
#: The structure test leaves out per-pixel values this near the window's edges (about the light's spread).
EDGE_MM = 1.0
#: Node spacing that makes a map one value for the patch (as carotene's default).
PATCH_MM = 100.0


def _median_skin(problem: LevelProblem, x: torch.Tensor) -> torch.Tensor:
    """The unknowns' median ``(N_PARAMS,)`` over the loss pixels: the skin a light factor is made at."""
    return x.reshape(N_PARAMS, -1)[:, problem.pixels].median(dim=1).values


def window_light_factor(problem: LevelProblem, x: torch.Tensor) -> torch.Tensor:
    """The window's light factor ``(L, H, W)`` at this level: the render of uniform skin at the median of
    the unknowns ``x`` ``(N_PARAMS, H, W)`` over the loss pixels, over that skin's homogeneous value
    (1 in the window's middle, less toward its edges). One render."""
    uniform = _median_skin(problem, x).view(N_PARAMS, 1, 1).expand_as(x).contiguous()
    with torch.no_grad():
        rendered = problem.evaluate(uniform, torch.zeros((), dtype=x.dtype, device=x.device)).image
        alone = problem.homogeneous_image(uniform)
    return (rendered / alone.clamp_min(1e-12)).detach()


def uniform_light_factor(problem: LevelProblem, x: torch.Tensor) -> torch.Tensor:
    """``window_light_factor`` without a render: for uniform skin Eq. 7's series collapses to the
    Fourier-domain combination of the layers (DWRR08 §3, Eq. 3; ``SkinModel.combined_hankel``), so the
    render of uniform skin under the level's light is one FFT of the lit window times R̂₁₂(|k|)/R₁₂(0)
    and the pixels' box, per band, from the renderer's own Gaussian tables. ``(L, H, W)``, the
    problem's dtype. Measured against the render it replaces (the pyramid blur): docs/reconstruct.md."""
    spread = _UniformSpread(problem, x)
    return spread.lit_and_spread(1.0).to(x.dtype).contiguous()


class _UniformSpread:
    """The lateral spread of uniform skin (the median of ``x`` over the loss pixels) under the level's
    light, in the Fourier domain: the lit window ``(H + 2B, W + 2B)`` with its border B, zero padded by B
    more (the renderer's scene is dark beyond its border, and light that would wrap around the FFT's
    period has crossed the border and its dark first), and per band the transfer R̂₁₂(|k|)/R₁₂(0) times the
    pixels' box ``(L, ny, nx // 2 + 1)``."""

    def __init__(self, problem: LevelProblem, x: torch.Tensor) -> None:
        h, w = problem.level.shape
        mm = problem.level.mm_per_pixel
        self.h, self.w = h, w
        self.border = border = problem.light.border_px(mm, problem.renderer.settings.render.border_mm)
        p = SkinParams(*to_params(_median_skin(problem, x).double()).unbind(0))
        self.lit = problem.light.irradiance(h, w, border, mm, torch.float64, x.device)
        self.ny, self.nx = ny, nx = self.lit.shape[-2] + 2 * border, self.lit.shape[-1] + 2 * border
        ky = 2.0 * math.pi * torch.fft.fftfreq(ny, d=mm, dtype=torch.float64, device=x.device)
        kx = 2.0 * math.pi * torch.fft.rfftfreq(nx, d=mm, dtype=torch.float64, device=x.device)
        kk = torch.sqrt(ky[:, None] ** 2 + kx[None, :] ** 2)
        unique, inverse = torch.unique(kk.reshape(-1), return_inverse=True)
        model, wl = problem.renderer.model, problem.wavelength_nm
        transfer = model.combined_hankel(p, wl, unique, method="tables")  # (L, K)
        total = model.total_reflectance(p, wl, method="tables")  # (L,)
        transfer = (transfer / total[:, None])[:, inverse].reshape(-1, *kk.shape)
        box = (torch.sinc(ky * mm / (2.0 * math.pi)) ** 2)[:, None] * (torch.sinc(kx * mm / (2.0 * math.pi)) ** 2)[None, :]
        self.transfer = transfer * box

    def lit_and_spread(self, reflectance: float | torch.Tensor) -> torch.Tensor:
        """The light leaving each pixel of the window ``(L, H, W)`` where the skin's own reflectance
        (relative to the median skin's: 1 for uniform skin) is ``reflectance`` — a number, or ``(L, H, W)``
        over the window (the border's skin taken as the median's) — and every pixel spreads its light as
        the median skin does."""
        b = self.border
        if isinstance(reflectance, torch.Tensor):  # each pixel its own: a field per band
            field = self.lit.expand(self.transfer.shape[0], -1, -1).clone()
            field[:, b: b + self.h, b: b + self.w] *= reflectance.to(field)
        else:
            field = self.lit * reflectance
        padded = field.new_zeros(*field.shape[:-2], self.ny, self.nx)
        padded[..., : field.shape[-2], : field.shape[-1]] = field
        out = torch.fft.irfft2(torch.fft.rfft2(padded) * self.transfer, s=(self.ny, self.nx))
        return out[:, b: b + self.h, b: b + self.w]

    def noise_gain(self) -> torch.Tensor:
        """Per band ``(L,)``, Σ (K − δ)² of the spread's kernel K on the pixel grid: the variance the
        difference ``K * n − n`` takes from white noise n of unit variance."""
        kernel = torch.fft.irfft2(self.transfer, s=(self.ny, self.nx))
        kernel[:, 0, 0] -= 1.0
        return kernel.pow(2).sum(dim=(-2, -1))


def crosstalk_forecast(problem: LevelProblem, x: torch.Tensor, noise: torch.Tensor) -> float:
    """What ``crosstalk_check`` would find, told from the cube alone (no fit, no render; FFTs only):
    each pixel's own reflectance read as the cube over the window's light factor, the light it sends to
    its neighbours spread as the median skin's, and the RMS of that render less the homogeneous model
    (``K * (R·E) − R·(K * E)``, E the lit window) in units of each band's noise ``noise`` ``(L,)``, over
    the loss pixels ``EDGE_MM`` inside the window's edges and the used bands, with the share the cube's
    own noise adds to it taken out. ``x`` ``(N_PARAMS, H, W)``: the skin the spread is made at (its
    median). A linear, one-kernel account of the cross-talk: a scene it puts far over the check's limit
    (``FORECAST_MARGIN``) fails the check too."""
    spread = _UniformSpread(problem, x)
    factor = spread.lit_and_spread(1.0)
    cube = problem.level.target.to(torch.float64)
    inside = problem.mask & _interior(problem.mask, problem.level.mm_per_pixel)
    used = (problem.band_weight > 0).cpu()
    if int(inside.sum()) < MIN_PAIRS or not bool(used.any()):
        return 0.0
    relative = cube / factor.clamp_min(1e-12)
    median = relative[:, problem.mask].median(dim=1).values
    relative = torch.where(problem.mask, relative, median[:, None, None]) / median[:, None, None]
    diff = (spread.lit_and_spread(relative) - relative * factor) * median[:, None, None]
    sigma = noise.to(torch.float64)
    excess = diff[:, inside].pow(2).mean(dim=1) / sigma**2 - spread.noise_gain()
    return math.sqrt(max(float(excess[used].mean()), 0.0))


def _interior(mask: torch.Tensor, mm_per_pixel: float) -> torch.Tensor:
    """``(H, W)``: the pixels ``EDGE_MM`` or more inside the frame's edges."""
    inner = int(round(EDGE_MM / mm_per_pixel))
    interior = torch.zeros_like(mask)
    interior[inner: mask.shape[0] - inner, inner: mask.shape[1] - inner] = True
    return interior


def _lag_one(values: torch.Tensor, valid: torch.Tensor) -> tuple[float, int]:
    """Correlation r of horizontally and vertically neighbouring ``values`` ``(H, W)`` where both are
    ``valid``, and the pairs: the values winsorised to their 1–99% range first, so a
    few pixels at a bound do not decide."""
    v = values.double()
    if not bool(valid.any()):  # a window too small for any pixel inside its edge band
        return 0.0, 0
    inside = v[valid]
    q = torch.quantile(inside, torch.tensor([0.01, 0.99], dtype=torch.float64, device=v.device))
    d = v.clamp(float(q[0]), float(q[1]))
    d = torch.where(valid, d - d[valid].mean(), torch.zeros_like(d))
    var = float((d[valid] ** 2).mean())
    pairs_h = valid[:, :-1] & valid[:, 1:]
    pairs_v = valid[:-1, :] & valid[1:, :]
    pairs = int(pairs_h.sum() + pairs_v.sum())
    if pairs == 0 or var <= 0.0:
        return 0.0, pairs
    products = float((d[:, :-1] * d[:, 1:])[pairs_h].sum() + (d[:-1, :] * d[1:, :])[pairs_v].sum())
    return products / (pairs * var), pairs


def spatial_structure(layout: MapLayout, x: torch.Tensor, mask: torch.Tensor, mm_per_pixel: float) -> dict[str, dict]:
    """For every map not already one value for the patch: ``r`` (``_lag_one`` of its own unknowns —
    the loss pixels' values of a per-pixel map, the node values of a map on nodes, never the
    interpolated pixels, which are alike by construction), its upper bound ``r_upper`` = r + 2/√pairs,
    the neighbour ``pairs`` and ``constant`` (``r_upper`` below ``CONSTANT_R`` on at least ``MIN_PAIRS``
    pairs). ``x`` ``(N_PARAMS, H, W)``, ``mask`` ``(H, W)``.

    Per-pixel values count from ``EDGE_MM`` inside the window's edges: nearer, the light factor of the
    skin's median is the model's own approximation (off for other skin), and the maps take it up as a
    ring (docs/reconstruct.md, "From reconstruct/choice/fidelity.py")."""
    interior = _interior(mask, mm_per_pixel)
    out = {}
    for k, name in enumerate(PARAMETER_NAMES):
        if k in layout.grids:
            grid = layout.grids[k]
            if grid.n_nodes == 1:
                continue
            values = grid.project(x[k]).reshape(grid.nodes)
            valid = torch.ones_like(values, dtype=torch.bool)
        else:
            values, valid = x[k], mask & interior
        r, pairs = _lag_one(values, valid)
        upper = r + 2.0 / math.sqrt(max(pairs, 1))
        out[name] = {"r": round(r, 4), "r_upper": round(upper, 4), "pairs": pairs,
                     "constant": pairs >= MIN_PAIRS and upper < CONSTANT_R}
    return out


@dataclass
class CrossTalkCheck:
    """The renderer against the homogeneous model at the homogeneous fit's maps, on one level:
    ``crosstalk_rms`` is the RMS of their difference in units of each band's noise, ``worst_band_nm``
    the band where it is largest, ``residual_rms_noise`` the renderer's residual in the same units."""

    level: int
    shape: list[int]
    mm_per_pixel: float
    crosstalk_rms: float
    worst_band_nm: float
    residual_rms_noise: float
    limit: float = CROSSTALK_LIMIT

    @property
    def passed(self) -> bool:
        return self.crosstalk_rms <= self.limit


def crosstalk_check(level_index: int, rendered: LevelProblem, homogeneous: HomogeneousProblem, x: torch.Tensor,
                    log_scale: torch.Tensor, noise: torch.Tensor) -> tuple[CrossTalkCheck, Evaluation]:
    """Render ``x`` with the renderer (one render) and compare with the homogeneous model, both scaled,
    in units of ``noise`` ``(L,)`` (each band's σ at this level); returns the check and the render's
    evaluation (what the fit keeps if the check passes)."""
    evaluation = rendered.evaluate(x, log_scale)
    with torch.no_grad():
        alone = homogeneous.render(x)
    used = rendered.band_weight > 0
    scale = torch.exp(log_scale)
    diff = rendered.at_pixels((evaluation.image - alone) * scale).double()[:, used] / noise[used].to(torch.float64)
    per_band = diff.pow(2).mean(0).sqrt()
    residual = evaluation.residual.double()[:, used] / noise[used].to(torch.float64)
    wavelengths = rendered.wavelength_nm[used.cpu()]
    check = CrossTalkCheck(
        level=level_index, shape=list(rendered.level.shape), mm_per_pixel=rendered.level.mm_per_pixel,
        crosstalk_rms=round(float(diff.pow(2).mean().sqrt()), 4), worst_band_nm=float(wavelengths[int(per_band.argmax())]),
        residual_rms_noise=round(float(residual.pow(2).mean().sqrt()), 4),
    )
    return check, evaluation


@dataclass
class ForwardChoice:
    """What ``forward`` chose for this cube and why: ``chosen`` ("homogeneous" or "heterogeneous"), the
    checks made (each level's ``CrossTalkCheck``), the seconds the homogeneous detour took."""

    setting: str
    chosen: str
    checks: list[CrossTalkCheck] = field(default_factory=list)
    homogeneous_wall_s: float = 0.0
    note: str = ""
    #: each map's spatial-structure test on the coarsest level's homogeneous fit (``spatial_structure``)
    structure: dict[str, dict] = field(default_factory=dict)
    #: the cross-talk forecast from the cube before any fit (``crosstalk_forecast``), in units of the noise
    forecast: float | None = None

    @property
    def constant_maps(self) -> list[str]:
        """The maps the structure test made one value for the patch."""
        return [name for name, found in self.structure.items() if found["constant"]]

    @property
    def uniform(self) -> bool:
        """Every map one value: uniform skin, for which the homogeneous model under the window's light
        is the renderer's own answer (Fourier-domain combination): no render is needed."""
        return bool(self.structure) and len(self.constant_maps) == len(self.structure)

    @property
    def reason(self) -> str:
        if self.setting != "auto":
            return f"forward: {self.setting} (fixed by the settings)"
        if not self.checks and self.forecast is not None and self.forecast > FORECAST_MARGIN * CROSSTALK_LIMIT:
            return (f"the cube's cross-talk, forecast from its own pixels before any fit, is {self.forecast:.2f} of the noise "
                    f"(over {FORECAST_MARGIN * CROSSTALK_LIMIT:g}, {FORECAST_MARGIN:g}× the check's limit): the scene needs the "
                    "heterogeneous renderer, and the homogeneous fit was not tried")
        if not self.checks:
            return f"{self.note}: the heterogeneous renderer, as the full model"
        last = self.checks[-1]
        where = f"level {last.level + 1} ({last.shape[0]}×{last.shape[1]} px)"
        if self.chosen == "homogeneous":
            why = (f"the renderer differs from the homogeneous fit by {last.crosstalk_rms:.2f} of the noise at {where} "
                   f"(limit {last.limit:g}): the cross-talk is below the noise, the homogeneous maps are kept")
            constant = self.constant_maps
            if constant:
                rs = ", ".join(f"{n} {self.structure[n]['r_upper']:.2f}" for n in constant)
                why += (f"; {', '.join(constant)} vary less than their noise (neighbour correlation at most {rs} < "
                        f"{CONSTANT_R:g}): one value for the patch" + (" (uniform skin: no render needed)" if self.uniform else ""))
            return why
        return (f"the renderer differs from the homogeneous fit by {last.crosstalk_rms:.2f} of the noise at {where}, "
                f"most at {last.worst_band_nm:g} nm (limit {last.limit:g}): the scene needs the heterogeneous renderer")

    def model_notes(self) -> list[str]:
        """A warning where the homogeneous model was imposed (``forward: homogeneous``) and the renderer,
        at its maps, differs from it by more than the check's limit: the light the skin carries between
        pixels is left out and the maps take it."""
        if self.setting != "homogeneous" or not self.checks or self.checks[-1].passed:
            return []
        last = self.checks[-1]
        return [f"homogeneous model on skin that varies within the light's reach: the renderer differs from it by "
                f"{last.crosstalk_rms:.1f}× the noise, most at {last.worst_band_nm:g} nm (limit {last.limit:g}); the maps "
                "are biased where the skin changes; fit with forward: auto (or heterogeneous)"]

    def as_dict(self) -> dict:
        return {"setting": self.setting, "chosen": self.chosen, "reason": self.reason,
                "checks": [{**asdict(c), "passed": c.passed} for c in self.checks],
                "forecast": self.forecast, "structure": self.structure, "constant_maps": self.constant_maps, "uniform": self.uniform,
                "homogeneous_wall_s": round(self.homogeneous_wall_s, 3)}
