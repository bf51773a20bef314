"""calibrate_session on a tiny synthetic session: accuracy against the truth, outputs, every correction
switched off in turn to show it matters, and the session folder left untouched."""

from __future__ import annotations

import json

import numpy as np
import pytest

from skinlayers.calibration import CalibrationSettings, calibrate_session
from skinlayers.formats.cube import read_cube


@pytest.fixture(scope="module")
def baseline(synthetic_session, tmp_path_factory, synth):
    before = synth.tree_hash(synthetic_session.path)
    steps = []
    out = tmp_path_factory.mktemp("out") / "cube"
    result = calibrate_session(synthetic_session.path, out, progress=lambda *a: steps.append(a))
    return result, before, steps


def _ratio(result, baseline_result):
    """Per-band median of a run's cube over the baseline's, on the baseline's mask."""
    mask = baseline_result.cube.mask.numpy()
    return np.median(result.cube.reflectance.numpy()[:, mask] / baseline_result.cube.reflectance.numpy()[:, mask], axis=1)


def test_cube_matches_the_truth_within_1_percent(baseline, synthetic_session):
    result, _, _ = baseline
    cube, mask = result.cube.reflectance.numpy(), result.cube.mask.numpy()
    truth = synthetic_session.truth
    assert mask.mean() > 0.9
    rms = np.sqrt(np.mean((cube - truth)[:, mask] ** 2, axis=1))
    assert rms.max() < 0.01, rms
    bias = np.median(cube[:, mask] / truth[:, mask], axis=1) - 1
    assert np.abs(bias).max() < 0.005, bias


def test_corners_flash_and_alignment_in_the_report(baseline, synthetic_session, synth):
    result, _, _ = baseline
    for band in result.report["bands"]:
        w = band["wavelength_nm"]
        corners = np.array(band["window_corners_px"])
        # raw px; the window spans only 60 superpixels here
        assert np.linalg.norm(corners - synthetic_session.corners[w], axis=1).max() < 0.45
        expected = synth.FLASH[f"reference_{w:g}"] / synth.FLASH[f"skin_{w:g}"]
        assert band["flash_factor"] == pytest.approx(expected, rel=0.005)
        assert np.hypot(*band["alignment_shift_px"]) < 0.3  # cube px: the windows already agree
        assert band["snr"] > 20
        assert band["saturated_fraction"] == 0


def test_outputs_are_complete_and_readable(baseline, synthetic_session, synth):
    result, _, steps = baseline
    cube = read_cube(result.cube_path)
    assert cube.shape == (3, synth.CUBE_PX, synth.CUBE_PX)
    assert cube.wavelength_nm.tolist() == list(synthetic_session.wavelengths)
    assert cube.mm_per_pixel == pytest.approx(7.5 / synth.CUBE_PX)
    header = cube.header
    assert set(header.calibration["window_corners_px"]) == {"430", "550", "670"}
    assert header.camera_angle_deg == 30.0
    assert header.band_fwhm_nm == [10.0, 10.0, 10.0]  # the rig's filters
    assert header.provenance.session == str(synthetic_session.path.resolve())
    assert header.provenance.made_by == "skinlayers calibrate"
    assert header.calibration["settings"] == CalibrationSettings().model_dump(mode="json")
    report = json.loads(result.report_path.read_text())
    assert set(report["timings_s"]) >= {"verify", "decode", "corrections", "window", "rectify", "align", "write", "total"}
    for key in ("exposure", "flash_factor", "alignment_shift_px", "snr", "saturated_fraction", "window_corners_px"):
        assert all(key in b for b in report["bands"]), key
    png = result.contact_sheet_path.read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
    assert steps[-1][0] == steps[-1][1] and [s[0] for s in steps] == sorted(s[0] for s in steps)


def test_the_session_folder_is_left_untouched(baseline, synthetic_session, synth):
    result, before, _ = baseline
    assert synth.tree_hash(synthetic_session.path) == before
    assert synthetic_session.path.resolve() not in result.out_dir.parents


@pytest.mark.parametrize(
    "switch, expected",
    [
        # without the gray card the flash's jitter stays: skin over reference flash
        ("gray_card", lambda s: np.array([s.FLASH[f"skin_{w:g}"] / s.FLASH[f"reference_{w:g}"] for w in s.BANDS])),
        # without the polarization factors the scale is off by them
        ("polarization", lambda s: np.full(3, s.SKIN_FACTOR / s.SPECTRALON_FACTOR)),
        # without the certificate the Spectralon counts as a perfect white
        ("spectralon_reflectance", lambda s: np.array([1 / s.SPECTRALON[w] for w in s.BANDS])),
    ],
)
def test_switching_a_scale_correction_off_changes_each_band_by_its_factor(
    baseline, synthetic_session, synth, tmp_path, switch, expected
):
    result = calibrate_session(synthetic_session.path, tmp_path / "out", CalibrationSettings(**{switch: False}))
    want = expected(synth)
    assert np.abs(want - 1).max() > 0.007  # the factor is there to be seen
    np.testing.assert_allclose(_ratio(result, baseline[0]), want, rtol=0.002)


def test_without_the_black_frame_the_stray_offset_stays(baseline, synthetic_session, tmp_path):
    result = calibrate_session(synthetic_session.path, tmp_path / "out", CalibrationSettings(dark_frame=False))
    assert (_ratio(result, baseline[0]) > 1.03).all()


def test_without_the_flat_field_the_flash_hot_spot_shows(baseline, synthetic_session, tmp_path):
    # the flash rises by 30% across the frame (8% across the window): the pixel-by-pixel reference takes it out
    result = calibrate_session(synthetic_session.path, tmp_path / "out", CalibrationSettings(flat_field=False))

    def slope(cube, mask):
        ratio = cube[:, mask] / synthetic_session.truth[:, mask]
        x = np.nonzero(mask)[1] / mask.shape[1]
        return np.array([np.polyfit(x, r, 1)[0] for r in ratio])

    mask = baseline[0].cube.mask.numpy()
    assert np.abs(slope(baseline[0].cube.reflectance.numpy(), mask)).max() < 0.01
    assert (slope(result.cube.reflectance.numpy(), mask) > 0.05).all()


def test_without_alignment_no_shift_is_applied(baseline, synthetic_session, tmp_path):
    result = calibrate_session(synthetic_session.path, tmp_path / "out", CalibrationSettings(align_bands=False))
    assert all(b["alignment_shift_px"] == [0.0, 0.0] for b in result.report["bands"])
    assert not any(f.code in ("misaligned", "alignment_failed") for f in result.flags)
    assert np.hypot(*baseline[0].report["bands"][0]["alignment_shift_px"]) > 0  # baseline measured one


def test_alignment_brings_back_skin_that_slid_under_the_tape(synth, tmp_path):
    # the skin slid by 0.025 window sides (1.6 cube px) under the tape before the 670 nm frame: the
    # window still cuts the same square, the skin's features moved; alignment finds and undoes it
    slide = 0.025
    session = synth.build_session(tmp_path / "slid", slide={670.0: (slide, 0.0)})
    aligned = calibrate_session(session.path, tmp_path / "on")
    as_cut = calibrate_session(session.path, tmp_path / "off", CalibrationSettings(align_bands=False))
    shift = aligned.report["bands"][2]["alignment_shift_px"]
    assert shift[0] == pytest.approx(slide * synth.CUBE_PX, abs=0.2) and abs(shift[1]) < 0.2
    assert ("misaligned", 670.0) in {(f.code, f.band_nm) for f in aligned.flags}  # above 1 cube px
    inner = np.zeros((synth.CUBE_PX, synth.CUBE_PX), bool)
    inner[8:-8, 8:-8] = True  # away from the edge, whose darkening stays with the window

    def rms(result):
        return float(np.sqrt(np.mean((result.cube.reflectance.numpy()[2] - session.truth[2])[inner] ** 2)))

    assert rms(aligned) < 0.65 * rms(as_cut)  # measured 0.0060 against 0.0110 (0.0048 with no slide)


def test_the_rigs_filter_widths_reach_the_fit(session_copy, tmp_path):
    """A rig with 12-nm filters: calibration writes each band's width and the camera angle into the cube's
    header, and the fit's band model takes them from there (not a 10-nm default)."""
    import math

    import torch

    from skinlayers.formats.manifest import read_manifest, write_manifest
    from skinlayers.model.render.renderer import SkinRenderer
    from skinlayers.reconstruct.mapfit.fit import band_fwhm_of, view_angle_of
    from skinlayers.reconstruct.levels.problem import LevelProblem
    from skinlayers.reconstruct.settings import FitSettings
    from skinlayers.reconstruct.levels.unknowns import Level

    manifest = read_manifest(session_copy.path)
    rig = {**manifest.rig, "bands": [{**b, "fwhm_nm": 12.0} for b in manifest.rig["bands"]], "camera": {**manifest.rig["camera"], "angle_deg": 25.0}}
    write_manifest(session_copy.path, manifest.model_copy(update={"rig": rig}))
    cube = read_cube(calibrate_session(session_copy.path, tmp_path / "cal").cube_path)
    assert cube.header.band_fwhm_nm == [12.0, 12.0, 12.0] and cube.header.camera_angle_deg == 25.0
    fwhm, source = band_fwhm_of(cube, FitSettings())
    assert fwhm.tolist() == [12.0, 12.0, 12.0] and source == "cube header"
    assert view_angle_of(cube, FitSettings()) == (25.0, "cube header")
    level = Level(cube.reflectance, cube.mask, cube.mm_per_pixel)
    problem = LevelProblem(SkinRenderer(), level, cube.wavelength_nm, torch.ones(3, dtype=torch.bool), view_angle_deg=25.0,
                           border_mm=0.0, band_fwhm_nm=fwhm)
    sigma = 12.0 / (2.0 * math.sqrt(2.0 * math.log(2.0)))
    nodes = problem.band_nodes_nm.reshape(3, 3) - cube.wavelength_nm[:, None]
    assert torch.allclose(nodes[:, 2], torch.full((3,), math.sqrt(3.0) * sigma, dtype=torch.float64))
    # a user's setting replaces the header's width for every band
    assert band_fwhm_of(cube, FitSettings(band_fwhm_nm=9.0))[0].tolist() == [9.0, 9.0, 9.0]
