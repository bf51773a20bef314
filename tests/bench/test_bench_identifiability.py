"""How well can any fit know each pixel's parameters? The Cramér–Rao bound of the map fit (on demand:
``pytest -m bench tests/bench/test_bench_identifiability.py -s``).

The heterogeneous renderer's Jacobian by forward differences (relative step 10⁻⁴ of each parameter,
float64) for a free block of ``block``² pixels at the centre of a 64² window of the default scene
(Fitzpatrick III interior; no veins or hairs), every other pixel held at the truth and the scale known
— so the bound is optimistic: freeing more of the field only raises it. Noise per band is the
simulated camera's, measured as the RMS of calibrated cube minus truth on the default 256² session
(seed 0; its 64² session carries the same per-pixel noise): ``CAMERA_NOISE``. The Fisher information
J^T Σ^{-1} J gives the standard deviation of log C per parameter (≈ the relative error of an unbiased
estimate), reported as the median over the block, for three cases: all five maps free; β_m and C_bc
known (three maps per pixel); each pixel's own five with its neighbours known ("local").

Writes ``identifiability.csv``. The bound scales with the noise: ×0.1 noise, ×0.1 bound.
"""

from __future__ import annotations

import pytest
import torch

from skinlayers.acquire.simulator.scene import SkinScene, scene_from_dict
from skinlayers.model import PARAMETER_NAMES, ModelSettings
from skinlayers.model.render.illumination import Light
from skinlayers.model.patch.maps import SkinMaps
from skinlayers.model.render.renderer import SkinRenderer

from bench_io import write_csv

pytestmark = pytest.mark.bench

BANDS_NM = (430.0, 460.0, 490.0, 520.0, 550.0, 580.0, 610.0, 640.0, 670.0)
#: RMS of (calibrated cube − truth) per band, default simulated session (measured, see the docstring)
CAMERA_NOISE = (0.0043, 0.0034, 0.0033, 0.0031, 0.0032, 0.0036, 0.0049, 0.0078, 0.0155)



def bound(size: int = 64, block: int = 4, noise_factor: float = 1.0, profiles: str = "diffusion") -> dict[str, dict[str, float]]:
    """The bound at the centre of a ``size``² window rendered with ``profiles`` (the module docstring)."""
    wl = torch.tensor(BANDS_NM, dtype=torch.float64)
    scene = SkinScene(scene_from_dict({"base": {"preset": "III interior"}, "veins": {"count": 0}, "hairs": {"count": 0}}), seed=0)
    mm = 7.5 / size
    maps = scene.maps(mm, size, wl, dtype=torch.float64)
    base = {n: getattr(maps, n).clone() for n in PARAMETER_NAMES}
    renderer = SkinRenderer(ModelSettings(profiles=profiles))
    light = Light("window", size_mm=7.5, border_mm=3.0)

    def render(values: dict) -> torch.Tensor:
        with torch.no_grad():
            m = SkinMaps(*(values[n] for n in PARAMETER_NAMES), mm_per_pixel=mm)
            return renderer.render(m, light, wl, under_gel=True, view_angle_deg=30.0).image[0].double()

    image = render(base)
    c0, h = size // 2 - block // 2, 1e-4
    columns = []
    for n in PARAMETER_NAMES:
        for i in range(c0, c0 + block):
            for j in range(c0, c0 + block):
                values = {q: base[q].clone() for q in PARAMETER_NAMES}
                values[n][0, i, j] *= 1.0 + h
                columns.append(((render(values) - image) / h).reshape(-1))
    sigma = torch.tensor(CAMERA_NOISE, dtype=torch.float64) * noise_factor
    jac = torch.stack(columns, 1) / sigma.repeat_interleave(size * size)[:, None]
    fisher = jac.T @ jac
    npx = block * block

    def sd(index: list[int]) -> torch.Tensor:
        idx = torch.tensor(index)
        return torch.linalg.pinv(fisher[idx][:, idx], hermitian=True).diagonal().sqrt()

    every = sd(list(range(5 * npx))).reshape(5, npx)
    three = sd([q * npx + p for q in (0, 2, 4) for p in range(npx)]).reshape(3, npx)
    local = torch.stack([sd([q * npx + p for q in range(5)]) for p in range(npx)], 1)
    return {
        "all five free": {n: float(every[q].median()) for q, n in enumerate(PARAMETER_NAMES)},
        "beta_m, C_bc known": {n: float(three[q].median()) for q, n in enumerate(("C_m", "C_he", "C_hd"))},
        "own pixel only": {n: float(local[q].median()) for q, n in enumerate(PARAMETER_NAMES)},
    }


def test_cramer_rao_bound_of_the_map_fit():
    rows = []
    for block in (2, 4):
        for case, values in bound(block=block).items():
            rows.append({"block": block, "case": case, **{f"sd_log_{k}": round(v, 4) for k, v in values.items()}})
            print(rows[-1])
    write_csv("identifiability.csv", rows)
    # more free neighbours can only loosen the bound
    c_hd = {(r["block"], r["case"]): r["sd_log_C_hd"] for r in rows}
    assert c_hd[(4, "all five free")] >= c_hd[(2, "all five free")] * 0.999


def test_bound_under_each_models_physics():
    """The same bound with the layers' responses from diffusion and from transport (``profiles``), at
    the transport sessions' pixel (32²: 0.23 mm) and at 64²: how much each model's physics lets a fit
    know one pixel's parameters among free neighbours. Transport spreads the dermis's light wider in
    green and red than diffusion (the stripe measured against the Monte Carlo, docs/transport.md), so
    neighbouring pixels' dermal blood is harder to tell apart; a pixel alone (its neighbours known)
    is bound alike. Writes ``identifiability_profiles.csv``."""
    rows = []
    for size in (32, 64):
        for profiles in ("diffusion", "transport"):
            for case, values in bound(size=size, block=4, profiles=profiles).items():
                rows.append({"size": size, "mm_per_pixel": round(7.5 / size, 4), "profiles": profiles, "case": case,
                             **{f"sd_log_{k}": round(v, 4) for k, v in values.items()}})
                print(rows[-1])
    write_csv("identifiability_profiles.csv", rows)
    c_hd = {(r["size"], r["profiles"], r["case"]): r["sd_log_C_hd"] for r in rows}
    # a pixel among free neighbours can only be known less well than alone
    assert all(c_hd[(n, p, "all five free")] >= 0.999 * c_hd[(n, p, "own pixel only")] for n in (32, 64) for p in ("diffusion", "transport"))


def shared_bound(preset: str = "III interior", pixels=(1, 16, 64, 256, 1024)) -> list[dict]:
    """The homogeneous (point) model's bound when some maps are one value over ``n`` pixels and the
    others per pixel: the Fisher information of the shared values is n × the Schur complement of the
    per-pixel block (every pixel alike), the per-pixel values' variance A⁻¹ + X Cov X^T. No cross-talk
    (so optimistic for C_hd, whose neighbours blur it); noise ``CAMERA_NOISE``."""
    from skinlayers.model import TABLE2, SkinModel, SkinParams

    model = SkinModel(ModelSettings())
    wl = torch.tensor(BANDS_NM, dtype=torch.float64)
    noise = torch.tensor(CAMERA_NOISE, dtype=torch.float64)
    p0 = torch.tensor([TABLE2[preset][n] for n in PARAMETER_NAMES], dtype=torch.float64).clamp_min(1e-6)

    def reflectance(log_p: torch.Tensor) -> torch.Tensor:
        p = torch.exp(log_p)
        return model.diffuse_reflectance(SkinParams(*(v.reshape(1) for v in p)), wl, method="exact")[0]

    jac = torch.autograd.functional.jacobian(reflectance, torch.log(p0)) / noise[:, None]
    fisher = jac.T @ jac
    rows = []
    for shared in ((), (1, 3), (1, 3, 4)):
        fine = [k for k in range(5) if k not in shared]
        a_inv = torch.linalg.inv(fisher[fine][:, fine])
        for n in pixels if shared else (1,):
            row = {"shared": ", ".join(PARAMETER_NAMES[k] for k in shared) or "none", "pixels_per_value": n}
            var = torch.zeros(5, dtype=torch.float64)
            if shared:
                b = fisher[fine][:, list(shared)]
                schur = fisher[list(shared)][:, list(shared)] - b.T @ a_inv @ b
                cov = torch.linalg.inv(n * schur)
                x = a_inv @ b
                var[list(shared)] = cov.diagonal()
                var[fine] = (a_inv + x @ cov @ x.T).diagonal()
            else:
                var[fine] = a_inv.diagonal()
            rows.append({**row, **{f"sd_log_{PARAMETER_NAMES[k]}": round(float(var[k].sqrt()), 4) for k in range(5)}})
    return rows


def test_bound_with_maps_on_nodes():
    """Why β_m and carotene go on nodes: per pixel their noise leaks into C_m (correlation −0.93 and
    −0.89 at III interior); shared over a node's pixels, C_m's bound falls ~4×. Writes
    ``identifiability_shared.csv``."""
    rows = shared_bound()
    write_csv("identifiability_shared.csv", rows)
    alone = rows[0]["sd_log_C_m"]
    shared = next(r for r in rows if r["shared"] == "beta_m, C_bc" and r["pixels_per_value"] == 64)["sd_log_C_m"]
    assert shared < 0.5 * alone
