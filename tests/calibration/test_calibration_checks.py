"""Every bad input is refused with a message naming it, or flagged and masked; nothing is written into
the session folder either way."""

from __future__ import annotations

import numpy as np
import pytest

from skinlayers.formats.files import file_sha256
from skinlayers.formats.manifest import read_manifest, write_manifest
from skinlayers.formats.outputs import OutputError
from skinlayers.calibration import (
    BandMissingError,
    CalibrationError,
    CalibrationSettings,
    ChecksumMismatchError,
    FrameMissingError,
    RawDecodeError,
    WindowNotFoundError,
    calibrate_session,
)


def _edit_manifest(session, change):
    manifest = read_manifest(session)
    change(manifest)
    write_manifest(session, manifest)


def _keep(predicate):
    def change(manifest):
        manifest.frames = [f for f in manifest.frames if predicate(f)]

    return change


def _replace_frame(session, name, data, synth):
    """Write a new DNG under ``name`` and record its checksum, as if it had been captured so."""
    synth.write_dng(session / name, data, black=synth.BLACK)

    def update(manifest):
        for f in manifest.frames:
            if f.file == name:
                f.sha256 = file_sha256(session / name)

    _edit_manifest(session, update)


def test_missing_file_is_named(session_copy, tmp_path):
    (session_copy.path / "skin_550.dng").unlink()
    with pytest.raises(FrameMissingError, match=r"skin_550.dng \(skin frame, 550 nm\)"):
        calibrate_session(session_copy.path, tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_checksum_mismatch_is_named(session_copy, tmp_path):
    path = session_copy.path / "reference_430.dng"
    data = bytearray(path.read_bytes())
    data[-100] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(ChecksumMismatchError, match=r"reference_430.dng \(reference frame, 430 nm\): SHA-256"):
        calibrate_session(session_copy.path, tmp_path / "out")


def test_missing_band_and_missing_black_frame(session_copy, tmp_path):
    _edit_manifest(session_copy.path, _keep(lambda f: f.file != "skin_670.dng"))
    with pytest.raises(BandMissingError, match="skin at 670 nm"):
        calibrate_session(session_copy.path, tmp_path / "out")
    _edit_manifest(session_copy.path, _keep(lambda f: f.role != "dark"))
    with pytest.raises(BandMissingError, match="black frame.*skin at 670 nm"):
        calibrate_session(session_copy.path, tmp_path / "out")


def test_frame_at_the_wrong_filter_position(session_copy, tmp_path):
    def move(manifest):
        manifest.frames[-1].filter_position = 9

    _edit_manifest(session_copy.path, move)
    with pytest.raises(CalibrationError, match="skin_670.dng: skin frame at 670 nm was taken at filter position 9"):
        calibrate_session(session_copy.path, tmp_path / "out")


def test_truncated_raw_with_a_matching_checksum_is_named(session_copy, tmp_path):
    path = session_copy.path / "skin_430.dng"
    path.write_bytes(path.read_bytes()[:-5000])

    def record(manifest):
        for f in manifest.frames:
            if f.file == "skin_430.dng":
                f.sha256 = file_sha256(path)

    _edit_manifest(session_copy.path, record)
    with pytest.raises(RawDecodeError, match=r"skin_430.dng \(skin frame, 430 nm\): cannot decode"):
        calibrate_session(session_copy.path, tmp_path / "out")


def test_skin_frame_without_a_window(session_copy, tmp_path, synth):
    scene = synth.render_scene(synth.RAW_SHAPE, homography=synth.camera_homography(synth.RAW_SHAPE, window_px=120), skin=0.03,
                               full_scale_dn=2600.0, gray_box=session_copy.gray_roi_raw)
    _replace_frame(session_copy.path, "skin_550.dng", synth.mosaic(scene.image, black=synth.BLACK), synth)
    with pytest.raises(WindowNotFoundError, match=r"skin_550.dng \(skin frame, 550 nm\): no window found"):
        calibrate_session(session_copy.path, tmp_path / "out")


def test_gray_card_region_unknown_or_saturated(session_copy, tmp_path, synth):
    _edit_manifest(session_copy.path, lambda m: m.rig["geometry"].__setitem__("gray_card_roi_px", None))
    with pytest.raises(CalibrationError, match="no geometry.gray_card_roi_px.*--no-gray-card"):
        calibrate_session(session_copy.path, tmp_path / "out")
    roi = session_copy.gray_roi_raw
    with pytest.raises(CalibrationError, match=r"region \[0, 0, 9999, 10\] .*beyond"):
        calibrate_session(session_copy.path, tmp_path / "out", CalibrationSettings(gray_card_roi_px=[0, 0, 9999, 10]))
    # the card clipped in one reference frame
    from skinlayers.calibration.raw import read_raw

    raw = read_raw(session_copy.path / "reference_550.dng")
    data = (raw.values + np.tile(raw.black_cell, (raw.shape[0] // 2, raw.shape[1] // 2))).astype(np.uint16)
    data[roi[1] : roi[3], roi[0] : roi[2]] = 4095
    _replace_frame(session_copy.path, "reference_550.dng", data, synth)
    with pytest.raises(CalibrationError, match=r"reference_550.dng \(reference frame, 550 nm\): 100.0% of the gray card is saturated"):
        calibrate_session(session_copy.path, tmp_path / "out", CalibrationSettings(gray_card_roi_px=roi))


def test_output_folder_inside_the_session_or_already_used(session_copy, tmp_path):
    with pytest.raises(OutputError, match="inside the session"):
        calibrate_session(session_copy.path, session_copy.path / "calibrated")
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "cube.exr").write_bytes(b"earlier")
    with pytest.raises(FileExistsError, match="already holds cube.exr.*--force"):
        calibrate_session(session_copy.path, tmp_path / "out")


def test_problems_that_leave_the_cube_usable_are_flagged_and_masked(session_copy, tmp_path, synth):
    # a clipped highlight inside the window of the 430 nm skin frame
    from skinlayers.calibration.raw import read_raw

    raw = read_raw(session_copy.path / "skin_430.dng")
    data = (raw.values + np.tile(raw.black_cell, (raw.shape[0] // 2, raw.shape[1] // 2))).astype(np.uint16)
    cx, cy = session_copy.corners[430.0].mean(axis=0).round().astype(int)
    data[cy - 6 : cy + 6, cx - 6 : cx + 6] = 4095
    _replace_frame(session_copy.path, "skin_430.dng", data, synth)
    settings = CalibrationSettings(gray_card_drift=0.05, max_misalignment_px=1e-4, underexposure_level=0.06)
    result = calibrate_session(session_copy.path, tmp_path / "out", settings)
    codes = {(f.code, f.band_nm) for f in result.flags}
    assert ("saturated", 430.0) in codes and ("saturated", 550.0) not in codes
    # flash skin/reference: 430 nm 8.2%, 550 nm 6.9%, 670 nm 4% off
    assert {("gray_card_drift", 430.0), ("gray_card_drift", 550.0)} <= codes and ("gray_card_drift", 670.0) not in codes
    assert ("misaligned", 430.0) in codes and ("misaligned", 670.0) in codes
    assert any(code == "underexposed" for code, _ in codes)
    assert all(f.message.startswith(f"{f.band_nm:g} nm: ") for f in result.flags)
    mask = result.cube.mask.numpy()
    n = mask.shape[0]
    assert not mask[n // 2 - 2 : n // 2 + 2, n // 2 - 2 : n // 2 + 2].any()  # the clipped patch is masked
    saturated = next(b["saturated_fraction"] for b in result.report["bands"] if b["wavelength_nm"] == 430.0)
    assert 0.005 < saturated < 0.05
    assert result.report["flags"] == [f.as_dict() for f in result.flags]


def test_reference_without_the_spectralon(session_copy, tmp_path, synth):
    # the operator forgot the target: the 670 nm reference shows the tape and the window instead
    from skinlayers.calibration.raw import read_raw

    skin = read_raw(session_copy.path / "skin_430.dng")
    data = (skin.values * 0.5 + np.tile(skin.black_cell, (skin.shape[0] // 2, skin.shape[1] // 2))).astype(np.uint16)
    _replace_frame(session_copy.path, "reference_670.dng", data, synth)
    with pytest.raises(CalibrationError, match=r"reference_670.dng \(reference frame, 670 nm\): the reference is darker under the window than the skin"):
        calibrate_session(session_copy.path, tmp_path / "out")


def test_a_few_pixels_of_the_window_are_masked_without_a_flag():
    """A share that prints as 0.00% is in the band's record, not a flag (a clean session prints none)."""
    from skinlayers.calibration.checks import MIN_FLAGGED_SHARE, exposure_flags
    from skinlayers.calibration.settings import CalibrationSettings

    settings = CalibrationSettings()
    assert exposure_flags(460.0, 0.0, 0.3 * MIN_FLAGGED_SHARE, settings) == []
    assert [f.code for f in exposure_flags(460.0, 2 * MIN_FLAGGED_SHARE, 2 * MIN_FLAGGED_SHARE, settings)] == ["saturated", "underexposed"]


def test_the_contact_sheet_says_why_a_band_is_marked():
    from skinlayers.calibration.report import band_caption

    entry = {"alignment_shift_px": [0.5, -0.25], "alignment_applied": True, "snr": 120.0, "flash_factor": 1.01,
             "saturated_fraction": 0.003}
    plain = band_caption(entry, False)
    marked = band_caption(entry, False, ["saturated", "gray_card_drift", "saturated"])
    assert marked.split("\n") == plain.split("\n") + ["saturated", "gray card drift"]
