"""Calibration of sessions made by the acquisition's simulator: the issue's acceptance on a small geometry,
and at full size in the slow test at the end.

The module's session (built once): 430, 550 and 670 nm (a dark-ish blue band; the noisiest red one, at
ISO 2000), cube 64 / rectify 128 (the window 256 raw px across), the default scene (freckles, a scar,
veins, hairs), flash jitter ±5%, subject motion up to 10 px and ±0.2°, 30% vignetting, lens blur, shot
and read noise. Its noiseless twin has the same scene, motion and flash: the RMS difference of the two
cubes is the noise floor. The simulator draws the window's edge by the share of each sample cell it
covers, with 8 samples per raw pixel and axis here (its default is 2; see ``conftest``).
"""

from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pytest

from skinlayers.formats.manifest import ManifestError, read_manifest, write_manifest
from skinlayers.formats.files import file_sha256
from skinlayers.calibration import (
    BandMissingError,
    CalibrationError,
    CalibrationSettings,
    ChecksumMismatchError,
    RawDecodeError,
    calibrate_session,
    default_out_dir,
)
from skinlayers.calibration.align import align_bands

CORNER_PX = 0.3  # raw px; measured here 0.27 (430 nm), 0.10, 0.17; at full size 0.12 at worst (the slow test)
ALIGN_CUBE_PX = 0.2
RMS = 0.01


@pytest.fixture(scope="module")
def sim(synth, tmp_path_factory):
    return synth.build_simulated_session(tmp_path_factory.mktemp("sim") / "sim")


@pytest.fixture(scope="module")
def clean(synth, tmp_path_factory):
    return synth.build_simulated_session(tmp_path_factory.mktemp("clean") / "clean", noiseless=True)


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    """``calibrated(session, **settings)``: each calibration once per module."""
    done = {}

    def run(session, **settings):
        key = (str(session.path), tuple(sorted(settings.items())))
        if key not in done:
            out = tmp_path_factory.mktemp("out") / "cube"
            done[key] = calibrate_session(session.path, out, CalibrationSettings(**settings))
        return done[key]

    return run


def _rms(a, mask):
    return np.sqrt(np.mean(a[:, mask] ** 2, axis=1))


def _cube(result):
    return result.cube.reflectance.numpy()


def _true_corners(session, band_nm):
    frame = session.frames[("skin", band_nm)]
    return session.bench.window_corners_px(frame.shift_px, frame.rotation_deg)


def _cube_displacement(found, true, cube_px):
    """Largest displacement (cube px) over the window between where the found corners and the true ones
    (raw px, TL, TR, BR, BL) put each cube pixel's centre."""
    unit = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32)
    h_found = cv2.getPerspectiveTransform(unit, np.asarray(found, np.float32))
    h_true = cv2.getPerspectiveTransform(unit, np.asarray(true, np.float32))
    centres = (np.arange(cube_px) + 0.5) / cube_px
    uv = np.stack(np.meshgrid(centres, centres), axis=-1).reshape(-1, 1, 2).astype(np.float64)
    raw_found = cv2.perspectiveTransform(uv, h_found)
    back = cv2.perspectiveTransform(raw_found, np.linalg.inv(h_true))  # where the true window has those pixels
    return float(np.abs(back - uv).max() * cube_px)


# ---- accuracy ----------------------------------------------------------------------------------------


def test_cube_within_1_percent_rms_of_the_truth_the_noise_floor_allowing(sim, clean, calibrated, synth):
    noisy, quiet = calibrated(sim), calibrated(clean)
    mask = noisy.cube.mask.numpy() & quiet.cube.mask.numpy()
    assert mask.mean() > 0.85
    rms = _rms(_cube(noisy) - sim.truth, mask)
    noise = _rms(_cube(noisy) - _cube(quiet), mask)  # the same scene, motion and flash: noise alone
    systematic = _rms(_cube(quiet) - clean.truth, mask)
    assert (systematic < RMS).all(), systematic  # measured 0.0011, 0.0011, 0.0023
    assert (rms**2 <= RMS**2 + noise**2).all(), (rms, noise)  # measured rms 0.0043, 0.0033, 0.0159; noise 0.0042, 0.0032, 0.0158
    assert (rms[:2] < RMS).all()  # where the noise leaves room: 430 and 550 nm
    scale = np.median(_cube(quiet)[:, mask] / clean.truth[:, mask], axis=1) - 1
    assert np.abs(scale).max() < 0.003, scale
    # the noise floor as the sensor model predicts it, from the raw frames alone (the slow test's measure)
    cfg = sim.bench.rig.geometry
    predicted = [synth.predicted_noise(sim.path, b, cfg.cube_px, cfg.rectify_px, mask, sim.bench.settings.sensor)
                 for b in noisy.report["bands"]]
    np.testing.assert_allclose(predicted, noise, rtol=0.2)


def test_window_corners_match_the_simulators(sim, calibrated):
    result = calibrated(sim)
    moved = []
    for band in result.report["bands"]:
        true = _true_corners(sim, band["wavelength_nm"])  # raw px, TL, TR, BR, BL, pixel-centre origin
        found = np.array(band["window_corners_px"])
        errors = np.linalg.norm(found - true, axis=1)
        assert errors.max() <= CORNER_PX, (band["wavelength_nm"], errors)
        moved.append(true.mean(axis=0))
    assert np.ptp(np.array(moved), axis=0).max() > 2.0  # the subject did move between the frames


def test_bands_are_registered_to_each_other_and_to_the_truth_within_0_2_px(sim, clean, calibrated):
    cube_px = sim.bench.rig.geometry.cube_px
    for session in (sim, clean):
        result = calibrated(session)
        for band in result.report["bands"]:
            w = band["wavelength_nm"]
            # geometry: where the found window puts each cube pixel against the true window
            assert _cube_displacement(band["window_corners_px"], _true_corners(session, w), cube_px) <= ALIGN_CUBE_PX / 2
            # ECC across bands of different contrast measures shifts below its 0.5-px threshold (0.02–0.23 px
            # here: its own error, the windows being registered far better); none is applied or flagged
            assert not band["alignment_applied"]
        assert not [f for f in result.flags if f.code in ("misaligned", "alignment_failed")]
    # the image itself: each band of the noiseless cube against its truth band
    result = calibrated(clean)
    for k, w in enumerate(clean.wavelengths):
        pair = np.stack([clean.truth[k], _cube(result)[k]]).astype(np.float32)
        shift = align_bands(pair, 0, sigma_px=1.5).shifts_px[1]
        assert np.hypot(*shift) < ALIGN_CUBE_PX, (w, shift)


def test_the_cube_goes_where_the_reconstruction_reads_it(sim, calibrated, tmp_path):
    copy = tmp_path / "arm"
    shutil.copytree(sim.path, copy)
    result = calibrate_session(copy, settings=CalibrationSettings(align_bands=False, window_edge_model=False))
    assert result.cube_path == tmp_path / "arm_calibrated" / "cube.exr" == default_out_dir(copy) / "cube.exr"


# ---- each correction switched off -------------------------------------------------------------------


def _ratio(result, base):
    mask = base.cube.mask.numpy()
    return np.median(_cube(result)[:, mask] / _cube(base)[:, mask], axis=1)


def test_without_the_gray_card_the_flash_jitter_stays(clean, calibrated):
    base, off = calibrated(clean), calibrated(clean, gray_card=False)
    jitter = np.array([clean.frames[("skin", w)].flash / clean.frames[("reference", w)].flash for w in clean.wavelengths])
    assert np.abs(jitter - 1).max() > 0.02  # there is jitter to see
    np.testing.assert_allclose(_ratio(off, base), jitter, rtol=0.002)
    np.testing.assert_allclose([b["flash_factor"] for b in base.report["bands"]], 1 / jitter, rtol=0.002)


@pytest.mark.parametrize("switch", ["polarization", "spectralon_reflectance"])
def test_without_a_target_factor_the_scale_is_off_by_it(clean, calibrated, switch):
    rig = clean.bench.rig
    factor = {
        "polarization": rig.polarization.skin_factor / rig.polarization.spectralon_factor,
        "spectralon_reflectance": 1 / rig.targets.spectralon_at(550.0),
    }[switch]
    assert abs(factor - 1) > 0.009
    np.testing.assert_allclose(_ratio(calibrated(clean, **{switch: False}), calibrated(clean)), factor, rtol=1e-4)


def test_a_wrong_certified_value_at_one_band_is_flagged_by_the_gray_card(sim, calibrated, tmp_path):
    # the card, read against the Spectralon in each reference frame, is flat across the bands; a certificate
    # 6% low at 550 nm (the simulator photographed the true 0.99) makes that band, and only it, read dark
    assert [f for f in calibrated(sim).flags if f.code == "card_spectrum"] == []
    readings = [b["gray_card_reading"] for b in calibrated(sim).report["bands"]]
    assert max(readings) / min(readings) < 1.01
    session = tmp_path / "session"
    shutil.copytree(sim.path, session)
    manifest = read_manifest(session)
    rig = dict(manifest.rig)
    rig["targets"] = {**rig["targets"], "spectralon_reflectance": {430: 0.99, 550: 0.99 * 0.94, 670: 0.99}}
    write_manifest(session, manifest.model_copy(update={"rig": rig}))
    result = calibrate_session(session, tmp_path / "out")
    flags = [f for f in result.flags if f.code == "card_spectrum"]
    assert [f.band_nm for f in flags] == [550.0] and flags[0].value == pytest.approx(-0.06, abs=0.005)
    assert "certified value" in flags[0].message
    assert _ratio(result, calibrated(sim))[1] == pytest.approx(0.94, rel=1e-4)


def test_without_the_flat_field_the_vignetting_stays(clean, calibrated):
    base, off = calibrated(clean), calibrated(clean, flat_field=False)
    mask, cube_px = base.cube.mask.numpy(), clean.bench.rig.geometry.cube_px
    geo, strength = clean.bench.geometry, clean.bench.settings.camera.vignetting
    centres = (np.arange(cube_px) + 0.5) / cube_px
    uv = np.stack(np.meshgrid(centres, centres), axis=-1).reshape(-1, 1, 2)
    cu, cv_ = (geo.width_px - 1) / 2, (geo.height_px - 1) / 2
    for k, w in enumerate(clean.wavelengths):
        ratio = (_cube(off)[k] / _cube(base)[k])[mask]
        unit = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32)
        h = cv2.getPerspectiveTransform(unit, _true_corners(clean, w).astype(np.float32))
        raw = cv2.perspectiveTransform(uv, h).reshape(cube_px, cube_px, 2)
        # the simulator's vignetting at each cube pixel, 1 − v r²/r_corner² (acquire/simulator/_optics.py)
        fall = 1 - strength * ((raw[..., 0] - cu) ** 2 + (raw[..., 1] - cv_) ** 2) / (cu**2 + cv_**2)
        fall = fall[mask] / np.median(fall[mask])
        ratio = ratio / np.median(ratio)
        assert np.percentile(ratio, 99) / np.percentile(ratio, 1) > 1.05  # the fall-off across the window shows
        assert np.sqrt(np.mean((ratio - fall) ** 2)) < 0.002  # and it is the vignetting


def test_without_the_black_frame_a_stray_offset_stays(clean, calibrated, tmp_path):
    # every frame (the black one too) carries 100 DN the raw tags' black level does not know
    import rawpy

    from skinlayers.acquire.hardware.dng import write_dng

    folder = tmp_path / "offset"
    shutil.copytree(clean.path, folder)
    manifest = read_manifest(folder)
    sensor = clean.bench.settings.sensor
    for f in manifest.frames:
        with rawpy.imread(str(folder / f.file)) as raw:
            data = raw.raw_image_visible.astype(np.int64) + 100
        write_dng(folder / f.file, np.clip(data, 0, sensor.white_level).astype(np.uint16), bits=sensor.bit_depth,
                  black_level=sensor.black_level, white_level=sensor.white_level)
        f.sha256 = file_sha256(folder / f.file)
    write_manifest(folder, manifest)
    session = type(clean)(folder, clean.bench, clean.wavelengths, clean.truth, clean.frames)
    base = calibrated(clean)
    np.testing.assert_allclose(_ratio(calibrated(session), base), 1.0, atol=2e-4)  # the black frame takes it out
    assert (_ratio(calibrated(session, dark_frame=False), base) > 1.01).all()


# ---- bad inputs: refused, named, and the session left as it was --------------------------------------


def _drop_skin_670(folder):
    manifest = read_manifest(folder)
    manifest.frames = [f for f in manifest.frames if not (f.role == "skin" and f.band_nm == 670.0)]
    write_manifest(folder, manifest)


def _truncate(folder):
    path = folder / "skin_550nm.dng"
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    manifest = read_manifest(folder)
    next(f for f in manifest.frames if f.file == path.name).sha256 = file_sha256(path)  # as if captured so
    write_manifest(folder, manifest)


def _flip_a_byte(folder):
    path = folder / "reference_430nm.dng"
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))


def _name_outside(folder):
    data = json.loads((folder / "manifest.json").read_text())
    data["frames"][3]["file"] = "../elsewhere/reference_670nm.dng"
    (folder / "manifest.json").write_text(json.dumps(data))


def _link_outside(folder):
    target = folder.parent / "elsewhere.dng"
    shutil.copy(folder / "skin_430nm.dng", target)
    (folder / "skin_430nm.dng").unlink()
    (folder / "skin_430nm.dng").symlink_to(target)


@pytest.mark.parametrize(
    "spoil, error, message",
    [
        (_truncate, RawDecodeError, r"skin_550nm.dng \(skin frame, 550 nm\): cannot decode raw file"),
        (_flip_a_byte, ChecksumMismatchError, r"reference_430nm.dng \(reference frame, 430 nm\): SHA-256 .* does not match"),
        (_drop_skin_670, BandMissingError, r"session lacks skin at 670 nm"),
        (_name_outside, ManifestError, r"manifest.json: .*'\.\./elsewhere/reference_670nm.dng' would leave the session folder"),
        (_link_outside, CalibrationError, r"skin_430nm.dng \(skin frame, 430 nm\): leads out of the session folder"),
    ],
)
def test_bad_input_is_refused_with_its_name_and_nothing_is_written(sim, synth, tmp_path, spoil, error, message):
    folder = tmp_path / "session"
    shutil.copytree(sim.path, folder)
    spoil(folder)
    before = synth.tree_hash(folder)
    with pytest.raises(error, match=message) as caught:
        calibrate_session(folder, tmp_path / "out")
    assert "\n" not in str(caught.value)
    assert synth.tree_hash(folder) == before
    assert not (tmp_path / "out").exists() and not default_out_dir(folder).exists()


# ---- the default geometry -----------------------------------------------------------------------------


@pytest.mark.slow
def test_full_size_session_end_to_end(synth, tmp_path):
    """Cube 256 / rectify 512 (the window 1024 raw px across), the nine bands of the rig, three wavelength
    samples per band: what ``skinlayers capture --sim`` makes, but for the edge supersampling (8, see
    the module docstring). 6.5 min measured on two shared cores, nearly all of it the simulator's frames."""
    bands = (430.0, 460.0, 490.0, 520.0, 550.0, 580.0, 610.0, 640.0, 670.0)
    sim = synth.build_simulated_session(tmp_path / "full", bands=bands, cube_px=256, rectify_px=512, wavelength_samples=3)
    before = synth.tree_hash(sim.path)
    result = calibrate_session(sim.path)
    assert result.cube_path == default_out_dir(sim.path) / "cube.exr"
    assert synth.tree_hash(sim.path) == before
    cube, mask = _cube(result), result.cube.mask.numpy()
    assert cube.shape == (9, 256, 256) and mask.mean() > 0.95
    rms = _rms(cube - sim.truth, mask)
    noise = np.array([synth.predicted_noise(sim.path, b, 256, 512, mask, sim.bench.settings.sensor) for b in result.report["bands"]])
    lines = []
    for k, band in enumerate(result.report["bands"]):
        w = band["wavelength_nm"]
        true = _true_corners(sim, w)
        corners = float(np.linalg.norm(np.array(band["window_corners_px"]) - true, axis=1).max())
        moved = _cube_displacement(band["window_corners_px"], true, 256)
        pair = np.stack([sim.truth[k], cube[k]]).astype(np.float32)
        vs_truth = float(np.hypot(*align_bands(pair, 0, sigma_px=1.5).shifts_px[1]))
        lines.append(f"{w:g} nm: RMS {rms[k]:.4f} (noise {noise[k]:.4f}), corners {corners:.3f} raw px, "
                     f"window {moved:.3f} cube px, against the truth {vs_truth:.3f} cube px")
        assert corners <= CORNER_PX, lines[-1]
        assert moved <= ALIGN_CUBE_PX / 2 and vs_truth < ALIGN_CUBE_PX, lines[-1]
        assert rms[k] ** 2 <= RMS**2 + noise[k] ** 2, lines[-1]
        if noise[k] < RMS / 2:
            assert rms[k] < RMS, lines[-1]
    print("\n" + "\n".join(lines) + f"\ntimings {result.report['timings_s']}")
