"""Gradients of the fit objective (gradcheck in float64 on a tiny grid), the homogeneous Jacobian
against finite differences, and the Schur-complement step against the dense normal equations."""

from __future__ import annotations

import math

import pytest
import torch

from skinlayers.model import N_PARAMS, PARAMETER_NAMES, TABLE2
from skinlayers.model.render.renderer import SkinRenderer
from skinlayers.reconstruct.mapfit.gauss_newton import solve_step
from skinlayers.reconstruct.levels.problem import LevelProblem
from skinlayers.reconstruct.levels.unknowns import Level, from_params

WL = torch.tensor([450.0, 550.0, 650.0], dtype=torch.float64)


SIZE = 5


@pytest.fixture(scope="module")
def problem():
    """A 5×5 grid of 1 mm pixels (small enough for every check to take under a second here)."""
    renderer = SkinRenderer()
    g = torch.Generator().manual_seed(3)
    target = (0.3 + 0.1 * torch.rand(3, SIZE, SIZE, generator=g)).double()
    mask = torch.ones(SIZE, SIZE, dtype=torch.bool)
    mask[0, :] = False  # a masked row: its parameters follow the row below, inside the graph
    level = Level(target, mask, 1.0)
    return LevelProblem(renderer, level, WL, torch.ones(3, dtype=torch.bool), view_angle_deg=30.0, border_mm=1.0)


def _x0(h=SIZE, w=SIZE):
    base = torch.tensor([TABLE2["III interior"][n] for n in PARAMETER_NAMES], dtype=torch.float64).view(5, 1, 1)
    g = torch.Generator().manual_seed(5)
    return from_params(base * torch.exp(0.3 * torch.randn(5, h, w, generator=g, dtype=torch.float64)))


def _objective(problem):
    def objective(x, s):
        image = problem.render(x)
        r = problem._residual(image, s)
        return 0.5 * (r**2).sum()

    return objective


def test_objective_gradcheck_fast(problem):
    """gradcheck's fast mode: random directions in and out, every input at once."""
    inputs = (_x0().requires_grad_(True), torch.tensor(0.02, dtype=torch.float64, requires_grad=True))
    assert torch.autograd.gradcheck(_objective(problem), inputs, eps=1e-6, atol=1e-6, rtol=1e-4, fast_mode=True)


@pytest.mark.slow
def test_objective_gradcheck_full():
    """Every one of the 181 inputs of a 6×6 grid of 0.5 mm pixels by central differences (a minute here)."""
    g = torch.Generator().manual_seed(3)
    mask = torch.ones(6, 6, dtype=torch.bool)
    mask[0, :] = False
    level = Level((0.3 + 0.1 * torch.rand(3, 6, 6, generator=g)).double(), mask, 0.5)
    prob = LevelProblem(SkinRenderer(), level, WL, torch.ones(3, dtype=torch.bool), view_angle_deg=30.0, border_mm=1.0)
    inputs = (_x0(6, 6).requires_grad_(True), torch.tensor(0.02, dtype=torch.float64, requires_grad=True))
    assert torch.autograd.gradcheck(_objective(prob), inputs, eps=1e-6, atol=1e-6, rtol=1e-4)


def test_evaluate_gradient_is_the_objective_gradient(problem):
    x0 = _x0()
    ev = problem.evaluate(x0, torch.tensor(0.0, dtype=torch.float64), grad=True)
    # masked pixels do not move the objective; a directional derivative matches the returned gradient
    direction = torch.randn(5, SIZE, SIZE, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    h = 1e-5
    up = problem.evaluate(x0 + h * direction, torch.tensor(0.0, dtype=torch.float64)).loss
    down = problem.evaluate(x0 - h * direction, torch.tensor(0.0, dtype=torch.float64)).loss
    fd = (up - down) / (2 * h)
    analytic = float((ev.grad * problem.at_pixels(direction)).sum())
    assert abs(fd - analytic) <= 1e-5 * max(abs(fd), 1e-8)


def test_homogeneous_jacobian_matches_finite_differences(problem):
    x = _x0()[:, 2, :4].T.clone()  # (4 pixels, N_PARAMS)
    value, jac = problem.homogeneous_jacobian(x)
    h = 1e-6
    for k in range(N_PARAMS):
        dx = torch.zeros_like(x)
        dx[:, k] = h
        up, _ = problem.homogeneous_jacobian(x + dx)
        down, _ = problem.homogeneous_jacobian(x - dx)
        fd = (up - down) / (2 * h)
        assert torch.allclose(jac[..., k], fd, rtol=1e-4, atol=1e-9), k
    assert value.shape == (4, 3) and bool((value > 0).all())


def test_uniform_light_limit_matches_the_renderer():
    """The homogeneous model the curvature uses is the renderer's own uniform-light limit."""
    from skinlayers.model.render.illumination import Light
    from skinlayers.model.patch.maps import SkinMaps

    renderer = SkinRenderer()
    params = TABLE2["IV exterior"]
    maps = SkinMaps.uniform(params, (8, 8), 0.1, dtype=torch.float64)
    image = renderer.render(maps, Light("uniform"), WL, view_angle_deg=30.0).image[0, :, 4, 4]
    level = Level(torch.zeros(3, 8, 8, dtype=torch.float64), torch.ones(8, 8, dtype=torch.bool), 0.1)
    prob = LevelProblem(renderer, level, WL, torch.ones(3, dtype=torch.bool), view_angle_deg=30.0, border_mm=0.0)
    x = from_params(torch.tensor([params[n] for n in PARAMETER_NAMES], dtype=torch.float64).view(N_PARAMS, 1)).T
    value, _ = prob.homogeneous_jacobian(x)
    assert torch.allclose(value[0], image, rtol=2e-3)


def test_schur_step_solves_the_full_normal_equations():
    g = torch.Generator().manual_seed(7)
    n, bands = 4, 6
    jac = torch.randn(n, bands, 5, generator=g, dtype=torch.float64)
    col = torch.rand(n, bands, generator=g, dtype=torch.float64) + 0.2
    r = torch.randn(n, bands, generator=g, dtype=torch.float64)
    grad = (jac.transpose(1, 2) @ r[..., None])[..., 0]
    grad_s = (col * r).sum()
    lam = torch.full((n,), 1e-9, dtype=torch.float64)
    dx, ds, _ = solve_step(jac, col, grad, grad_s, lam, 1e-9, True)
    # dense system over all 5n + 1 unknowns
    big = torch.zeros(n * bands, 5 * n + 1, dtype=torch.float64)
    for i in range(n):
        big[i * bands:(i + 1) * bands, 5 * i:5 * i + 5] = jac[i]
        big[i * bands:(i + 1) * bands, -1] = col[i]
    step = torch.linalg.lstsq(big, -r.reshape(-1, 1)).solution[:, 0]
    assert torch.allclose(dx.reshape(-1), step[:-1], rtol=1e-6, atol=1e-8)
    assert math.isclose(float(ds), float(step[-1]), rel_tol=1e-6, abs_tol=1e-9)


def test_step_is_invariant_to_the_scale_of_an_unknown():
    """Jacobi scaling: a parameter near a bound (tiny column) moves as one in the middle would."""
    g = torch.Generator().manual_seed(2)
    jac = torch.randn(3, 9, 5, generator=g, dtype=torch.float64)
    r = torch.randn(3, 9, generator=g, dtype=torch.float64)
    col = torch.zeros(3, 9, dtype=torch.float64)
    lam = torch.full((3,), 1e-3, dtype=torch.float64)

    def step(j):
        grad = (j.transpose(1, 2) @ r[..., None])[..., 0]
        return solve_step(j, col, grad, torch.tensor(0.0, dtype=torch.float64), lam, 0.0, False)[0]

    scaled = jac.clone()
    scaled[..., 2] *= 1e-5
    a, b = step(jac), step(scaled)
    assert torch.allclose(b[:, 2] * 1e-5, a[:, 2], rtol=1e-6)
    assert torch.allclose(b[:, [0, 1, 3, 4]], a[:, [0, 1, 3, 4]], rtol=1e-6)


def test_uniform_unknowns_keep_each_pixels_derivatives():
    """Uniform skin is evaluated once for all its pixels (``problem._distinct``); where derivatives flow
    — the exact gradient's backward pass, forward-mode tangents — each pixel keeps its own. Checked at
    unknowns equal at every pixel, with the band model on (the band correction is where they meet)."""
    g = torch.Generator().manual_seed(4)
    level = Level((0.3 + 0.1 * torch.rand(3, SIZE, SIZE, generator=g)).double(), torch.ones(SIZE, SIZE, dtype=torch.bool), 1.0)
    prob = LevelProblem(SkinRenderer(), level, WL, torch.ones(3, dtype=torch.bool), view_angle_deg=30.0, border_mm=1.0,
                        band_fwhm_nm=10.0)
    x0 = _x0()[:, :1, :1].expand(N_PARAMS, SIZE, SIZE).contiguous()
    inputs = (x0.clone().requires_grad_(True), torch.tensor(0.02, dtype=torch.float64, requires_grad=True))
    assert torch.autograd.gradcheck(_objective(prob), inputs, eps=1e-6, atol=1e-6, rtol=1e-4, fast_mode=True)
    rows = prob.at_pixels(x0)  # every row the same: one evaluation, broadcast
    value, jac = prob.homogeneous_jacobian(rows)
    one_value, one_jac = prob.homogeneous_jacobian(rows[:1])
    assert value.shape == (SIZE * SIZE, 3) and jac.shape == (SIZE * SIZE, 3, N_PARAMS)
    torch.testing.assert_close(value, one_value.expand_as(value), rtol=1e-14, atol=0)
    torch.testing.assert_close(jac, one_jac.expand_as(jac), rtol=1e-14, atol=0)
    image = prob.homogeneous_image(x0)
    torch.testing.assert_close(image, image[:, :1, :1].expand_as(image), rtol=0, atol=0)
    other = x0.clone()
    other[0, 2, 3] += 0.1  # one pixel differs: every pixel its own again
    changed = prob.homogeneous_image(other)
    assert not torch.equal(changed[:, 2, 3], image[:, 2, 3]) and torch.equal(changed[:, 1, 1], image[:, 1, 1])
