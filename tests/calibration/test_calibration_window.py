"""Window detection (sub-pixel corners against rendered truth), its refusals, and the rectification."""

from __future__ import annotations

import numpy as np
import pytest

from skinlayers.calibration.errors import WindowNotFoundError
from skinlayers.calibration.window import (
    box_filter,
    find_window,
    order_corners,
    raw_to_superpixel_xy,
    rectify,
    superpixel_to_raw_xy,
    window_interior,
)

SHAPE = (300, 400)


def _scene(synth, seed, band, **kw):
    rng = np.random.default_rng(100 + seed)
    shift, turn = tuple(rng.uniform(-10, 10, 2)), rng.uniform(-2, 2)
    homography = synth.camera_homography(SHAPE, window_px=110, shift_px=shift, rotation_deg=turn)
    return synth.render_scene(SHAPE, homography=homography, seed=seed, texture_seed=seed, leak=synth.LEAK[band], **kw)


@pytest.mark.parametrize("seed, band", [(0, 430), (1, 550), (2, 670), (3, 430)])
def test_corners_within_0_3_px_with_noise_vignetting_and_the_skin_darkening_at_the_tape(synth, seed, band):
    # 110-px window seen 30° off axis, subject moved ±10 px and turned ±2°, 30% vignetting, shot and
    # read noise, a Gaussian PSF, freckles, and the renderer's darkening of the skin towards the tape
    scene = _scene(synth, seed, band, psf_sigma_px=0.6, vignetting=0.3)
    window = find_window(scene.image, exclude=[scene.gray_box])
    errors = np.linalg.norm(window.corners - scene.corners, axis=1)
    assert errors.max() <= 0.3, errors
    assert window.model_sides == 4
    assert 0.3 < window.blur_px < 1.2  # the PSF (0.6) with the pixel's own spread


def test_the_edge_model_is_what_removes_the_inward_bias(synth):
    # derivative peaks alone sit inside the edge where the skin darkens towards the tape
    scene = _scene(synth, 0, 430, psf_sigma_px=0.6)
    peaks = find_window(scene.image, exclude=[scene.gray_box], edge_model=False)
    modelled = find_window(scene.image, exclude=[scene.gray_box])
    centre = scene.corners.mean(axis=0)
    outward = (scene.corners - centre) / np.linalg.norm(scene.corners - centre, axis=1, keepdims=True)
    inward_bias = -np.mean(np.sum((peaks.corners - scene.corners) * outward, axis=1))
    assert inward_bias > 0.25
    worst = {name: np.linalg.norm(w.corners - scene.corners, axis=1).max() for name, w in (("peaks", peaks), ("model", modelled))}
    assert worst["model"] < 0.5 * worst["peaks"]


def test_no_window_is_refused_with_the_image_named(synth):
    scene = synth.render_scene(SHAPE, skin=0.03)  # skin as dark as the tape: nothing to find
    with pytest.raises(WindowNotFoundError, match="frame_x.dng: no window found"):
        find_window(scene.image, exclude=[scene.gray_box], name="frame_x.dng")


def test_two_windows_are_ambiguous(synth):
    scene = synth.render_scene(SHAPE)
    image = scene.image.copy()
    # a second bright square in the tape, as large as the window
    x0, y0 = 20, 20
    image[y0 : y0 + 80, x0 : x0 + 80] = np.median(image[140:160, 190:210])
    with pytest.raises(WindowNotFoundError, match="2 window candidates.*ambiguous"):
        find_window(image, exclude=[scene.gray_box], name="skin_550.dng")


def test_the_gray_card_is_not_taken_for_the_window(synth):
    scene = synth.render_scene(SHAPE, background=0.03)  # tape all round: the card is the only bright thing left
    with pytest.raises(WindowNotFoundError, match="no window found.*the gray card's region is left out"):
        find_window(np.where(_window_region(scene), np.float32(scene.image.min()), scene.image), exclude=[scene.gray_box])


def _window_region(scene):
    import cv2

    mask = np.zeros(scene.image.shape, np.uint8)
    cv2.fillConvexPoly(mask, np.round(scene.corners).astype(np.int32), 1)
    return cv2.dilate(mask, np.ones((9, 9), np.uint8)).astype(bool)


def test_rectification_round_trip(synth):
    # a smooth pattern on the plane, point-sampled through the camera's homography; rectifying with the
    # true corners must give the pattern back at the square's pixel centres (corners on pixel edges)
    n = 96
    homography = synth.camera_homography(SHAPE, window_px=180, rotation_deg=3.0)
    hinv = np.linalg.inv(homography)
    ys, xs = np.mgrid[0 : SHAPE[0], 0 : SHAPE[1]].astype(np.float64)
    den = hinv[2, 0] * xs + hinv[2, 1] * ys + hinv[2, 2]
    u = (hinv[0, 0] * xs + hinv[0, 1] * ys + hinv[0, 2]) / den
    v = (hinv[1, 0] * xs + hinv[1, 1] * ys + hinv[1, 2]) / den

    def pattern(a, b):
        return 1.0 + 0.3 * np.sin(20 * a + 0.3) * np.cos(16 * b - 0.2) + 0.2 * a

    image = pattern(u, v).astype(np.float32)
    corners = homography @ np.array([[-0.5, 0.5, 0.5, -0.5], [-0.5, -0.5, 0.5, 0.5], [1, 1, 1, 1]])
    corners = (corners[:2] / corners[2]).T
    centres = (np.arange(n) + 0.5) / n - 0.5
    truth = pattern(*np.meshgrid(centres, centres))
    for kernel in ("linear", "cubic", "lanczos"):
        out = rectify(image, corners, n, kernel)
        assert out.shape == (n, n)
        assert np.abs(out - truth)[2:-2, 2:-2].max() < 0.003, kernel
    shifted = rectify(image, corners + 0.5, n, "cubic")  # a half-pixel convention error shows
    assert np.abs(shifted - truth)[2:-2, 2:-2].max() > 0.015


def test_box_filter_and_coordinates():
    image = np.arange(16, dtype=np.float32).reshape(4, 4)
    np.testing.assert_allclose(box_filter(image, 2), [[2.5, 4.5], [10.5, 12.5]])
    with pytest.raises(ValueError, match="does not divide"):
        box_filter(image, 3)
    xy = np.array([[3.25, 7.5]])
    np.testing.assert_allclose(raw_to_superpixel_xy(superpixel_to_raw_xy(xy)), xy)
    np.testing.assert_allclose(superpixel_to_raw_xy([[0.0, 0.0]]), [[0.5, 0.5]])  # cell 0 spans photosites 0 and 1
    shuffled = np.array([[9.0, 9.0], [0.0, 0.0], [9.0, 0.0], [0.0, 9.0]])
    np.testing.assert_array_equal(order_corners(shuffled), [[0, 0], [9, 0], [9, 9], [0, 9]])


def test_the_windows_interior_leaves_out_its_edge_by_the_blur():
    inside = np.zeros((40, 40), bool)
    inside[5:35, 5:35] = True
    sharp = window_interior(inside, 0.3)
    assert sharp.sum() == 28 * 28 and sharp[6:34, 6:34].all()
    blurred = window_interior(inside, 1.2)  # 2σ = 2.4 px: three superpixels off each side
    assert blurred.sum() == 24 * 24 and blurred[8:32, 8:32].all()
    assert window_interior(inside, float("nan")).sum() == 28 * 28
    tiny = np.zeros((40, 40), bool)
    tiny[10:12, 10:12] = True
    assert (window_interior(tiny, 1.0) == tiny).all()  # nothing left: the window as it is
