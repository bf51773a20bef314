"""The simulated bench: what its frames show (band, target, card, tape), its noise against the sensor
model, vignetting, flash jitter, subject motion, and its truth against the renderer."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from skinlayers.acquire.hardware.devices import ExposureSettings
from skinlayers.acquire.hardware.rig import load_rig
from skinlayers.acquire.simulator.scene import scene_from_dict
from skinlayers.acquire.simulator.simulated import SimulatedBench
from skinlayers.acquire.simulator.simulation_settings import SimulationError, simulation_from_dict
from skinlayers.model.render.illumination import Light
from skinlayers.model.patch.maps_io import read_maps
from skinlayers.formats.exr import read_spectral

BANDS = [{"wavelength_nm": 550, "filter_position": 2, "iso": 200}, {"wavelength_nm": 650, "filter_position": 3, "iso": 400}]
EXPOSURE = {550.0: ExposureSettings(200, 0.01, 10.0), 650.0: ExposureSettings(400, 0.01, 10.0)}
HOMOGENEOUS = {"variation": {"C_m": 0, "beta_m": 0, "C_he": 0, "C_bc": 0, "C_hd": 0}, "freckles": {"count": 0},
               "scar": {"count": 0}, "veins": {"count": 0}, "hairs": {"count": 0}}


def small_rig(rectify_px: int = 48):
    return load_rig(bands=BANDS, geometry={"cube_px": 32, "rectify_px": rectify_px})


def small_settings(**sections):
    data = {"motion": {"max_shift_px": 2.0}, "filters": {"wavelength_samples": 1}}
    for key, value in sections.items():
        data[key] = {**data.get(key, {}), **value}
    return simulation_from_dict(data)


@pytest.fixture(scope="module")
def bench():
    """A small bench (96 raw px across the window, 160×112 sensor) on the default textured scene."""
    return SimulatedBench(small_rig(), None, small_settings(), seed=11, device="cpu")


@pytest.fixture(scope="module")
def flat_bench():
    """A bench with a larger sensor for frame statistics of flat targets (no skin render needed)."""
    return SimulatedBench(small_rig(rectify_px=160), None, small_settings(), seed=12, device="cpu")


def superpixels(raw: np.ndarray, black: tuple) -> np.ndarray:
    """Sum of each 2×2 cell, black subtracted: ``(H/2, W/2)``."""
    x = raw.astype(np.float64) - np.tile(np.array(black, dtype=np.float64).reshape(2, 2), (raw.shape[0] // 2, raw.shape[1] // 2))
    return x[0::2, 0::2] + x[0::2, 1::2] + x[1::2, 0::2] + x[1::2, 1::2]


def test_rig_as_used_carries_the_gray_card_region(bench):
    rig = bench.rig_as_used()
    roi = rig.geometry.gray_card_roi_px
    assert roi == bench.gray_card_roi_px
    assert rig.camera.driver == "simulated"
    x0, y0, x1, y1 = roi
    assert 0 <= x0 < x1 <= bench.geometry.width_px and 0 <= y0 < y1 <= bench.geometry.height_px
    assert x0 % 2 == y0 % 2 == x1 % 2 == y1 % 2 == 0
    bench.set_target("spectralon")
    raw = bench.frame(2, EXPOSURE[550.0])
    sp = superpixels(raw, bench.settings.sensor.black_level)
    card = sp[y0 // 2:y1 // 2, x0 // 2:x1 // 2]
    ring = sp[max(y0 // 2 - 6, 0):y1 // 2 + 6, x1 // 2 + 2:x1 // 2 + 6]  # Spectralon just right of the card
    ratio = card.mean() / ring.mean()
    expected = 0.30 / (0.99 * 1.0527)
    assert ratio == pytest.approx(expected, rel=0.03)  # gray card vs Spectralon (vignetting differs a little)
    assert card.std() / card.mean() < 0.1  # the region is clear of the card's blurred edge


def test_skin_frame_shows_tape_card_and_window_and_the_ratio_to_the_reference_is_the_truth():
    """Homogeneous skin: at the window centre, (skin - dark)/(ref - dark) × gray_ref/gray_skin × ρ × s_f / k_f
    is the truth reflectance (the calibration's recipe, bench_layout.md)."""
    b = SimulatedBench(small_rig(), scene_from_dict(HOMOGENEOUS), small_settings(motion={"max_shift_px": 0.0}), seed=3,
                       device="cpu")
    black = b.settings.sensor.black_level
    dark = superpixels(b.frame(1, EXPOSURE[550.0]), black)
    b.set_target("spectralon")
    ref = superpixels(b.frame(2, EXPOSURE[550.0]), black) - dark
    b.set_target("skin")
    skin = superpixels(b.frame(2, EXPOSURE[550.0]), black) - dark
    x0, y0, x1, y1 = (v // 2 for v in b.gray_card_roi_px)
    gray = ref[y0:y1, x0:x1].mean() / skin[y0:y1, x0:x1].mean()
    flash = [f.flash for f in b.frames]
    assert gray == pytest.approx(flash[1] / flash[2], rel=0.01)
    cy, cx = (b.geometry.height_px // 4, b.geometry.width_px // 4)
    centre = (skin / ref)[cy - 3:cy + 3, cx - 3:cx + 3].mean() * gray
    rig = b.rig
    measured = centre * rig.targets.spectralon_at(550) * rig.polarization.spectralon_factor / rig.polarization.skin_factor
    truth = b.truth_reflectance()[0]
    assert measured == pytest.approx(float(truth[14:18, 14:18].mean()), rel=0.02)
    tape = (skin / ref)[0:3, cx - 3:cx + 3].mean() * gray  # above the window (its top edge at raw row 13.6): tape
    assert tape * 0.99 * 1.0527 == pytest.approx(0.03, rel=0.1)


def test_dark_frame_is_black_level_and_read_noise(flat_bench):
    s = flat_bench.settings.sensor
    raw = flat_bench.frame(flat_bench.rig.wheel.dark_position, ExposureSettings(800, 0.01, 10.0)).astype(np.float64)
    g = s.e_per_dn_iso100 * 100 / 800
    var = (s.read_noise_e / g) ** 2 + s.read_noise_dn**2 + 1 / 12
    for k in range(4):
        block = raw[k // 2::2, k % 2::2]
        assert block.mean() == pytest.approx(s.black_level[k], abs=4 * math.sqrt(var / block.size))
        assert block.var() == pytest.approx(var, rel=6 * math.sqrt(2 / block.size))


def _vignetting(b) -> np.ndarray:
    h, w = b.geometry.height_px, b.geometry.width_px
    cv, cu = (h - 1) / 2, (w - 1) / 2
    v, u = np.mgrid[0:h, 0:w]
    return 1 - 0.3 * ((u - cu) ** 2 + (v - cv) ** 2) / (cu**2 + cv**2)


@pytest.mark.parametrize("band, iso", [(550.0, 200), (650.0, 800)])
def test_flat_frame_mean_and_variance_follow_shot_and_read_noise(flat_bench, band, iso):
    """Spectralon away from the card: DN = black + μ/g with μ from the flash, filter, sensitivity and
    vignetting; Var = (μ + σ_e²)/g² + σ_dn² + 1/12 (EMVA 1288). Checked per Bayer position on z-scores."""
    b = flat_bench
    s = b.settings.sensor
    b.set_target("spectralon")
    exposure = ExposureSettings(iso, 0.01, 10.0)
    raw = b.frame(b.rig.band(band).filter_position, exposure).astype(np.float64)
    flash = b.frames[-1].flash
    rho = b.rig.targets.spectralon_at(band) * b.rig.polarization.spectralon_factor
    per_channel = b.electrons_per_reflectance(band, 10.0) * flash * rho
    g = s.e_per_dn_iso100 * 100 / iso
    vig = _vignetting(b)
    x0, y0, x1, y1 = b.gray_card_roi_px
    keep = np.ones_like(raw, dtype=bool)
    keep[: y1 + 10, : x1 + 10] = False  # away from the card and its blur
    keep[:, :4] = keep[:, -4:] = keep[:4] = keep[-4:] = False
    for k, c in enumerate((0, 1, 1, 2)):
        sl = (slice(k // 2, None, 2), slice(k % 2, None, 2))
        mu = per_channel[c] * vig[sl]
        mean = s.black_level[k] + mu / g
        var = (mu + s.read_noise_e**2) / g**2 + s.read_noise_dn**2 + 1 / 12
        z = ((raw[sl] - mean) / np.sqrt(var))[keep[sl]]
        assert abs(z.mean()) < 4 / math.sqrt(z.size), (k, z.mean())
        assert z.var() == pytest.approx(1.0, abs=6 * math.sqrt(2 / z.size)), (k, z.var())
    assert per_channel.max() / g > 50  # a real signal, not the read noise alone
    assert raw.max() < s.white_level  # and no pixel saturated


def test_vignetting_darkens_the_corners_by_thirty_percent(flat_bench):
    b = flat_bench
    b.set_target("spectralon")
    sp = superpixels(b.frame(2, EXPOSURE[550.0]), b.settings.sensor.black_level)
    h, w = sp.shape
    centre = sp[h // 2 - 4:h // 2 + 4, w // 2 - 4:w // 2 + 4].mean()
    corner = sp[-4:, -4:].mean()  # the bottom-right corner (the card is on the left)
    assert corner / centre == pytest.approx(_vignetting(b)[-4:, -4:].mean(), rel=0.02)
    assert corner / centre < 0.75


def test_flash_jitters_within_its_range_and_the_gray_card_tracks_it(flat_bench):
    b = flat_bench
    b.set_target("spectralon")
    x0, y0, x1, y1 = (v // 2 for v in b.gray_card_roi_px)
    cards, centres, flashes = [], [], []
    for _ in range(6):
        sp = superpixels(b.frame(3, EXPOSURE[650.0]), b.settings.sensor.black_level)
        h, w = sp.shape
        cards.append(sp[y0:y1, x0:x1].mean())
        centres.append(sp[h // 2 - 8:h // 2 + 8, w // 2 - 8:w // 2 + 8].mean())
        flashes.append(b.frames[-1].flash)
    flashes = np.array(flashes)
    assert np.all(np.abs(flashes - 1) <= 0.05) and flashes.max() - flashes.min() > 0.02
    # shot noise of a region's mean: 1/sqrt(electrons); DN × e/DN ≈ electrons (4 pixels a superpixel)
    g = b.settings.sensor.e_per_dn_iso100 * 100 / 400
    for means, pixels in ((cards, (y1 - y0) * (x1 - x0)), (centres, 256)):
        noise = 1 / math.sqrt(min(means) * g * pixels)
        np.testing.assert_allclose(np.array(means) / means[0], flashes / flashes[0], rtol=5 * math.sqrt(2) * noise)
        assert 5 * math.sqrt(2) * noise < 0.2 * (flashes.max() - flashes.min())


def _window_centroid(raw: np.ndarray, ref: np.ndarray, bench) -> np.ndarray:
    """Centroid (raw px) of the flat-fielded skin frame above the tape, over a box holding the window
    wherever it moves: the window moves rigidly, so this centroid moves with it."""
    black = bench.settings.sensor.black_level
    ratio = superpixels(raw, black) / superpixels(ref, black)
    (u0, v0), (u1, v1) = (np.asarray(c) / 2 for c in bench._window_region)
    box = ratio[int(v0):int(v1), int(u0):int(u1)]
    w = np.clip(box - np.median(np.concatenate([box[0], box[-1]])), 0, None)
    v, u = np.mgrid[0:box.shape[0], 0:box.shape[1]]
    return np.array([(w * u).sum() / w.sum(), (w * v).sum() / w.sum()]) * 2


def test_subject_motion_moves_the_window_by_the_logged_shift(bench):
    bench.set_target("spectralon")
    ref = bench.frame(2, EXPOSURE[550.0])
    bench.set_target("skin")
    raws, shifts = [], []
    for _ in range(3):
        raws.append(bench.frame(2, EXPOSURE[550.0]))
        shifts.append(np.array(bench.frames[-1].shift_px))
    assert all(np.hypot(*s) <= 2.0 for s in shifts) and np.hypot(*(shifts[1] - shifts[0])) > 0.3
    c = [_window_centroid(r, ref, bench) for r in raws]
    for i in (1, 2):
        np.testing.assert_allclose(c[i] - c[0], shifts[i] - shifts[0], atol=0.2)
    corners = bench.window_corners_px(tuple(shifts[1]), bench.frames[-2].rotation_deg)
    assert np.allclose(corners.mean(axis=0) - bench.window_corners_px().mean(axis=0), shifts[1], atol=0.05)


def test_the_window_spans_twice_rectify_px_and_is_a_trapezoid(bench):
    tl, tr, br, bl = bench.window_corners_px()
    middle = bench.geometry.project(3.75, 0.0)[0] - bench.geometry.project(-3.75, 0.0)[0]
    assert middle == pytest.approx(2 * 48)
    assert tr[0] - tl[0] > br[0] - bl[0]  # the side nearer the camera is wider
    assert (bl[1] - tl[1]) == pytest.approx(2 * 48 * math.cos(math.radians(30)), rel=0.01)
    x, y = bench.geometry.unproject(*bench.geometry.project(np.array([1.0, -2.0]), np.array([3.0, 0.5])))
    np.testing.assert_allclose([x, y], [[1.0, -2.0], [3.0, 0.5]], atol=1e-12)


def test_same_seed_same_frames_whatever_came_before():
    a = SimulatedBench(small_rig(), None, small_settings(), seed=5, device="cpu")
    b = SimulatedBench(small_rig(), None, small_settings(), seed=5, device="cpu")
    a.set_target("spectralon")
    a.frame(1, EXPOSURE[550.0])
    first = a.frame(3, EXPOSURE[650.0])
    b.set_target("spectralon")
    assert np.array_equal(b.frame(3, EXPOSURE[650.0]), first)  # no dark frame before it in b
    assert not np.array_equal(b.frame(3, EXPOSURE[650.0]), first)  # the next one is another exposure


def test_truth_is_the_render_on_the_cube_grid_and_is_written(bench, tmp_path):
    """One wavelength per band here: the truth is the renderer's image at the band centre, cropped to
    the window and box-averaged 2×2 to the cube grid (the weighting: test_truth_weights_*)."""
    band = 650.0
    maps = bench.scene_maps()
    image = bench.renderer.render(maps, Light("window", size_mm=7.5, border_mm=3.0), torch.tensor([band]), under_gel=True,
                                  view_angle_deg=30.0).image[0, 0]
    m = (bench.truth_size_px - 64) // 2
    expected = image[m:m + 64, m:m + 64].double().reshape(32, 2, 32, 2).mean(dim=(1, 3))
    truth = bench.truth_reflectance()
    torch.testing.assert_close(truth[1], expected, rtol=1e-5, atol=1e-7)
    paths = bench.write_truth(tmp_path)
    assert sorted(p.name for p in paths) == ["maps.exr", "reflectance.exr", "simulation.json"]
    cube, wl, header = read_spectral(tmp_path / "truth" / "reflectance.exr")
    assert wl.tolist() == [550.0, 650.0] and cube.shape == (2, 32, 32)
    assert float(header["mm_per_pixel"]) == pytest.approx(7.5 / 32)
    torch.testing.assert_close(cube, truth.float())
    written = read_maps(tmp_path / "truth" / "maps.exr")
    assert written.shape == (1, 64, 64) and written.mm_per_pixel == pytest.approx(7.5 / 64)
    torch.testing.assert_close(written.C_m, maps.C_m[:, m:m + 64, m:m + 64])
    assert written.absorbance_wavelength_nm.tolist() == [550.0, 650.0]


@pytest.mark.slow
def test_truth_weights_filter_flash_and_all_four_bayer_positions():
    """Three nodes across the band: truth = Σ_k w_k R(λ_k) with w = filter × 6000 K Planck × (R + 2G + B),
    computed here from the closed forms, each node rendered on its own."""
    from skinlayers.acquire.simulator._optics import channel_sensitivity

    rig = load_rig(bands=[BANDS[0]], geometry={"cube_px": 32, "rectify_px": 48})
    b = SimulatedBench(rig, None, small_settings(filters={"wavelength_samples": 3}), seed=2, device="cpu")
    nodes = b.spectra[550.0].nodes_nm
    sigma = 10 / (2 * math.sqrt(2 * math.log(2)))
    assert np.allclose(nodes, 550 + np.array([-1, 0, 1]) * math.sqrt(3) * sigma)  # Gauss–Hermite, n = 3
    hermite_w = np.array([1, 4, 1]) / 6
    planck = 1 / (nodes**5 * np.expm1(1.438776877e7 / (nodes * 6000)))
    sens = sum(f * channel_sensitivity(b.settings.sensor.sensitivity[c], nodes) for c, f in (("red", 1), ("green", 2), ("blue", 1)))
    w = hermite_w * planck * sens
    w /= w.sum()
    maps = b.scene_maps()
    images = [b.renderer.render(maps, Light("window", size_mm=7.5, border_mm=3.0), torch.tensor([n]), under_gel=True,
                                view_angle_deg=30.0).image[0, 0].double() for n in nodes]
    m = (b.truth_size_px - 64) // 2
    expected = sum(wk * im for wk, im in zip(w, images))[m:m + 64, m:m + 64].reshape(32, 2, 32, 2).mean(dim=(1, 3))
    torch.testing.assert_close(b.truth_reflectance()[0], expected, rtol=1e-5, atol=1e-7)


def test_a_sensor_too_small_for_the_window_and_its_motion_is_refused():
    with pytest.raises(SimulationError, match="does not fit"):
        SimulatedBench(small_rig(), None, small_settings(camera={"field_of_view_mm": [8.0, 6.0]},
                                                         scene={"gray_card_mm": [-3.9, -1.0, -3.85, 1.0]}), device="cpu")
    with pytest.raises(SimulationError, match="gray_card_mm"):
        SimulatedBench(small_rig(), None, small_settings(scene={"gray_card_mm": [-20.0, -1.0, -19.0, 1.0]}), device="cpu")
    with pytest.raises(SimulationError, match="overlaps the window"):
        SimulatedBench(small_rig(), None, small_settings(scene={"gray_card_mm": [-4.0, -1.0, -2.0, 1.0]}), device="cpu")


def test_unknown_target_and_position_are_refused(bench):
    with pytest.raises(ValueError, match="target"):
        bench.set_target("gel")
    with pytest.raises(ValueError, match="wheel position 13"):
        bench.frame(13, EXPOSURE[550.0])


def test_the_truths_series_stays_tighter_than_the_fits_and_within_the_noise_of_a_tight_one():
    """The truth's inter-scattering series (1% left, closed by its geometric rest) against one to 0.1%:
    every pixel of the window within 2·10⁻⁴ of reflectance (the demo's cube noise is 6.6·10⁻³ RMS),
    yet not identical (the setting is in effect); and always tighter than the fit's."""
    from skinlayers.reconstruct.settings import FitSettings

    default = small_settings()
    assert default.truth.series_tolerance < FitSettings().model.render.series_tolerance
    tight = small_settings(truth={"series_tolerance": 1e-3})
    rig = small_rig()
    band = 650.0
    a = SimulatedBench(rig, None, default, seed=0, device="cpu")
    b = SimulatedBench(rig, None, tight, seed=0, device="cpu")
    m, n = a._margin_px, a._window_px
    difference = (a.render_band(band).truth - b.render_band(band).truth)[m:m + n, m:m + n].abs()
    assert 0.0 < float(difference.max()) < 2e-4, float(difference.max())


def test_the_truth_rendered_node_by_node_is_the_band_rendered_at_once():
    """The simulator renders a band's wavelength nodes one at a time (docs/speed.md, cut 3) with the
    series terms of all of them: the same image as one render of every node."""
    settings = small_settings(filters={"wavelength_samples": 3})
    bench = SimulatedBench(small_rig(), None, settings, seed=0, device="cpu")
    band = 650.0
    nodes = torch.tensor(bench.spectra[band].nodes_nm)
    assert nodes.numel() == 3
    light = Light("window", size_mm=bench.rig.geometry.window_mm, border_mm=settings.truth.border_mm)
    with torch.no_grad():
        at_once = bench.renderer.render(bench.scene_maps(), light, nodes, view_angle_deg=bench.rig.camera.angle_deg).image[0]
    by_node = bench._render_nodes(light, nodes)
    assert by_node.shape == at_once.shape
    assert torch.allclose(by_node, at_once, rtol=0, atol=1e-7)
    assert not torch.equal(by_node[0], by_node[2])
